"""Argument types of the package's numba-compiled kernels.

Each kernel is compiled for one list of argument types, given where it is defined, so that it
is compiled (first process on a machine) or loaded from numba's cache (later ones) when its
module is imported, not at a first call in the middle of a node's first update. Arrays are
C-contiguous (the callers make them so); the ones a kernel only reads are typed read-only, which
numba also accepts for writable arrays, so one compiled version serves both (a mesh's arrays
are read-only, a state's are not).
"""

from __future__ import annotations

from numba import types

__all__ = ["read_only", "writable"]


def read_only(dtype, ndim: int) -> types.Array:
    return types.Array(dtype, ndim, "C", readonly=True)


def writable(dtype, ndim: int) -> types.Array:
    return types.Array(dtype, ndim, "C")
