"""numpy's large arrays without transparent huge pages, chosen by the programs' entry points.

numpy asks the kernel for transparent huge pages (madvise MADV_HUGEPAGE) for every array of
4 MiB or more. Where THP serves such regions with defrag `madvise` (this project's VMs:
/sys/kernel/mm/transparent_hugepage/enabled and .../defrag both `madvise`), a page fault in one
may compact memory before it returns. A fresh process meets this when it first fills memory it
has never touched: setting up a node on an organ-scale mesh, whose FEM pattern alone makes
arrays of 20-60 MB. On the project's 2-core VM, a fresh process built the FEM model
(core/physics/fem.py) of the 6,393-vertex organ slab in 0.32-2.10 s with numpy's advice and in
0.35-0.38 s without it; in the live pipeline at organ scale (`meshfg bench`'s organ_live
recording, the nodes set up on its mesh as the player plays it) the first cloud's estimate came
0.57-1.59 s after the cloud with the advice (over 1 s in 5 of 8 runs) and 0.56-0.59 s without it
(6 runs). Later allocations reuse pages the process already holds: the organ-scale updates of
`meshfg bench` took the same time either way (median 556-576 against 564-575 ms, back to back).

`NUMPY_MADVISE_HUGEPAGE`, numpy's documented switch, is read when numpy is imported, which the
entry points cannot precede; `configure` therefore sets numpy's runtime form of it
(`_set_madvise_hugepage`, looked up defensively: it is not public API) unless the user set the
variable, which then stays in force. Like blas.configure it is a choice for the whole process,
made by the entry points (the `meshfg` command, the nodes through nodes/runtime.py); importing
meshfg_ros changes nothing.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["ENVIRONMENT_VARIABLE", "configure"]

ENVIRONMENT_VARIABLE = "NUMPY_MADVISE_HUGEPAGE"


def _toggle():
    """numpy's switch (it returns the setting in force before the call), or None."""
    for package in ("_core", "core"):  # numpy 2, numpy 1
        multiarray = getattr(getattr(np, package, None), "multiarray", None)
        toggle = getattr(multiarray, "_set_madvise_hugepage", None)
        if toggle is not None:
            return toggle
    return None


def configure() -> bool | None:
    """Turn numpy's huge-page advice off for this process unless NUMPY_MADVISE_HUGEPAGE is
    set; returns whether numpy advises huge pages from now on (None: this numpy has no switch,
    and its own default stays)."""
    toggle = _toggle()
    if toggle is None:
        return None
    if ENVIRONMENT_VARIABLE in os.environ:
        enabled = bool(toggle(False))  # the setting in force, which is left as it is
        toggle(enabled)
        return enabled
    toggle(False)
    return False
