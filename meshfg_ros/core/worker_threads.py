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
1 computes everything on the calling thread. With more than one, work needed only later also
runs beside the caller (`start_background`): the simulator's stiffness factor of a newly learnt
Poisson ratio (core/physics/simulator.py, RestFactor), the block factor the next state of the
estimator's window borrows (core/solvers/linear_solvers.py, PCGSolver.refactor_newest_beside),
the next update's covariance draws (core/estimation/covariance.py) and, while an estimator is
set up, its prior's covariance blocks at rest (core/estimation/estimator.py). The default is the
number of cores the process may run on, at most 2 (on this package's 2-core target the
estimator and the simulator take turns, so both cores serve whichever computes).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Sequence, TypeVar

__all__ = ["WorkerThreadsSettingError", "count", "ranges", "run_parts", "split", "start_background"]

DEFAULT_MAX_THREADS = 2

T = TypeVar("T")

_usable_cores: int | None = None  # the cores the process may use, read at the first count()
_pool: ThreadPoolExecutor | None = None
_pool_workers = 0
_background: ThreadPoolExecutor | None = None  # start_background's thread
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
    """In a forked child: the parent's pool and background threads do not exist there, so new
    ones are made at the child's first use instead of waiting on them (and its cores are read
    again)."""
    global _pool, _pool_workers, _pool_lock, _usable_cores, _background
    _pool, _pool_workers, _pool_lock, _usable_cores, _background = None, 0, threading.Lock(), None, None


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


def start_background(function: Callable[..., T], *args) -> Future:
    """Run function(*args) beside the caller, on the process's background thread (work the
    caller needs later, such as a factor for the next step); its `result()` waits for it and
    gives its value or raises its exception. With one worker thread it runs now, on the
    calling thread. One thread, made once and blocking on its queue between tasks, takes them
    in turn: CHOLMOD keeps workspace in each thread's cholmod_common, so a thread per task
    would leave it behind. Its own splits run in line, leaving the worker threads to the
    caller. The work should release the GIL (CHOLMOD through cholmod_without_gil.py), or it
    only takes turns with the caller."""
    global _background
    if count() < 2:
        done = Future()
        try:
            done.set_result(function(*args))
        except Exception as error:  # raised by result(), as from the background thread
            done.set_exception(error)
        return done
    with _pool_lock:
        if _background is None:
            _background = ThreadPoolExecutor(max_workers=1, thread_name_prefix="meshfg-background",
                                             initializer=_mark_worker)
        return _background.submit(function, *args)
