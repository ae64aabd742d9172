"""The process-wide choices each entry point makes before its work, in one call.

CHOLMOD's BLAS (blas.py: bound before anything loads cvxopt), numpy's huge-page advice
(huge_pages.py: off before a node sets up on its mesh) and the worker-thread count
(core/worker_threads.py: read here, so that a bad MESHFG_WORKER_THREADS stops the program at
start-up rather than in its first update). The `meshfg` command, the nodes (nodes/runtime.py)
and the fuzz workers call `configure` first; `meshfg bench` reports what it chose. Each part
is idempotent, so a second call changes nothing and returns the same settings.
"""

from __future__ import annotations

from dataclasses import dataclass

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros import blas, huge_pages

__all__ = ["ProcessSettings", "configure"]


@dataclass(frozen=True)
class ProcessSettings:
    """What `configure` chose: the BLAS, whether numpy advises huge pages (None: this numpy has
    no switch) and the worker threads."""

    blas: blas.BlasBackend
    numpy_huge_pages: bool | None
    worker_threads: int


def configure() -> ProcessSettings:
    """Make the process-wide choices (module doc). Raises blas.BlasSettingError for an unknown
    MESHFG_BLAS and worker_threads.WorkerThreadsSettingError for a bad MESHFG_WORKER_THREADS."""
    return ProcessSettings(blas.configure(), huge_pages.configure(), worker_threads.count())
