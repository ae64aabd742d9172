"""Independent pieces of one computation run at once on the process's worker threads.

The update's costliest pieces are independent and run in C without Python's lock: the
right-hand sides of a CHOLMOD solve (sparse_cholesky.py), the state blocks of the window's
product (linear_system.py). On a robot computer of two cores the estimator otherwise computes on
one while the other waits for the simulator. Work is split coarsely, one part per thread and
call, so a thread that loses its core to another process delays its own part only; and the
pool's threads block on a queue between calls, they never spin, so with another process on
each core an update slows in proportion to the CPU it gets (`meshfg bench` measures it). This
is unlike a threaded BLAS, which meets all its threads at every supernode (blas.py).

`MESHFG_WORKER_THREADS` sets how many threads split such work, the calling thread included:
1 computes everything on the calling thread. With more than one, the simulator also makes the
stiffness factor of a newly learnt Poisson ratio on a thread of its own (core/physics/simulator.py,
RestFactor). The default is the number of cores the process
may run on, at most 2 (on this package's 2-core target the estimator and the simulator take
turns, so both cores serve whichever computes).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence, TypeVar

__all__ = ["Background", "WorkerThreadsSettingError", "count", "ranges", "run_parts", "split", "start_background"]

DEFAULT_MAX_THREADS = 2

T = TypeVar("T")

_usable_cores: int | None = None  # the cores the process may use, read at the first count()
_pool: ThreadPoolExecutor | None = None
_pool_workers = 0
_pool_lock = threading.Lock()
_local = threading.local()


class WorkerThreadsSettingError(ValueError):
    """MESHFG_WORKER_THREADS is not a positive integer."""


def count() -> int:
    """Threads that split work, the caller included: MESHFG_WORKER_THREADS, else the cores the
    process may use (read once) up to DEFAULT_MAX_THREADS."""
    global _usable_cores
    setting = os.environ.get("MESHFG_WORKER_THREADS")
    if setting is None:
        if _usable_cores is None:
            _usable_cores = len(os.sched_getaffinity(0))
        return max(1, min(DEFAULT_MAX_THREADS, _usable_cores))
    try:
        threads = int(setting)
    except ValueError:
        threads = 0
    if threads < 1:
        raise WorkerThreadsSettingError(f"MESHFG_WORKER_THREADS must be a positive integer, got {setting!r}")
    return threads


def ranges(length: int, most: int) -> list[slice]:
    """range(length) in at most `most` (and at most count()) contiguous, non-empty slices of
    nearly equal length; one slice when `most` < 2 (an empty one for length 0)."""
    parts = max(1, min(count(), most, length))
    bounds = [length * k // parts for k in range(parts + 1)]
    return [slice(low, high) for low, high in zip(bounds[:-1], bounds[1:])]


def split(items: Sequence[T], most: int) -> list[Sequence[T]]:
    """`items` in at most `most` (and at most count()) contiguous, non-empty groups of nearly
    equal length; one group when `most` < 2."""
    return [items[part] for part in ranges(len(items), most)]


def _submit(function: Callable[..., T], parts: Sequence[tuple]) -> list:
    """Futures of function(*part) on the pool, made with at least len(parts) threads (a larger
    one replaces it: the old one's threads end after their work). Submitted under the lock, so
    that no other caller replaces the pool in between."""
    global _pool, _pool_workers
    with _pool_lock:
        if _pool is None or _pool_workers < len(parts):
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(max_workers=len(parts), thread_name_prefix="meshfg-worker",
                                       initializer=_mark_worker)
            _pool_workers = len(parts)
        return [_pool.submit(function, *part) for part in parts]


def _mark_worker() -> None:
    _local.worker = True


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist there, so a new pool is made
    at the child's first split instead of waiting on them (and its cores are read again)."""
    global _pool, _pool_workers, _pool_lock, _usable_cores
    _pool, _pool_workers, _pool_lock, _usable_cores = None, 0, threading.Lock(), None


os.register_at_fork(after_in_child=_forget_pool)


def run_parts(function: Callable[..., T], parts: Sequence[tuple]) -> list[T]:
    """[function(*part) for part in parts], the first part on the calling thread and the others
    on worker threads at the same time. Inline, in order, on a worker thread itself (no pool
    waits on itself) or with a single part. An exception of any part is raised after all ended."""
    if len(parts) <= 1 or getattr(_local, "worker", False):
        return [function(*part) for part in parts]
    futures = _submit(function, parts[1:])
    try:
        first = function(*parts[0])
    finally:
        others = [future.exception() for future in futures]  # waits for every part
    for error in others:
        if error is not None:
            raise error
    return [first] + [future.result() for future in futures]


class Background:
    """function(*args) running on a thread of its own, started by `start_background`."""

    def __init__(self, function: Callable[..., T], args: tuple):
        self._outcome: tuple | None = None
        # Not a daemon: the interpreter's exit waits for it (under a second), rather than freeing
        # a factor that CHOLMOD is still writing.
        self._thread = threading.Thread(target=self._run, args=(function, args), name="meshfg-background")
        self._thread.start()

    def _run(self, function, args) -> None:
        _mark_worker()  # its own splits run in line: the pool stays the caller's
        try:
            self._outcome = (function(*args), None)
        except BaseException as error:  # raised to the caller of result()
            self._outcome = (None, error)

    def result(self):
        """The function's value once it has ended; its exception, if it raised one."""
        self._thread.join()
        value, error = self._outcome
        if error is not None:
            raise error
        return value


def start_background(function: Callable[..., T], *args) -> Background:
    """Run function(*args) on a thread of its own, beside the caller's work (work the caller
    needs later, such as a factor for the next step), one part at a time: its run_parts calls
    run in line, leaving the worker threads to the caller. The work should release the GIL
    (CHOLMOD through cholmod_without_gil.py) or it only takes turns with the caller."""
    return Background(function, args)
