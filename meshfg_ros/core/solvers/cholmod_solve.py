"""CHOLMOD's solve (`cholmod_l_solve`) on cvxopt's factors, called without Python's lock.

cvxopt's `cholmod.solve` and `spsolve` hold the GIL while CHOLMOD works, so two threads cannot
solve at once, and no other CHOLMOD binding has wheels for this Python (blas.py). ctypes
releases the GIL around a foreign call, so this module calls the `cholmod_l_solve` of the very
library cvxopt loaded (its wheel's `cvxopt.libs/libcholmod-*.so`, CHOLMOD 3.0) on the factor
inside cvxopt's capsule. CHOLMOD is thread-safe with one `cholmod_common` per thread (its
workspace and error state); the factor is only read. Measured at organ scale (a 31,944-dof
block, MKL, one BLAS thread): four right-hand sides in one call 39 ms, as two calls of two on
two threads 24 ms.

`available()` is False where the library cannot be found or bound (another cvxopt build):
sparse_cholesky.py then solves through cvxopt, on one thread.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading

import numpy as np

__all__ = ["available", "solve"]

# cholmod_common is a C struct of about 2 KB in CHOLMOD 3; its size is not exported, so each
# thread's is given room to spare.
_COMMON_BYTES = 64 * 1024
_CHOLMOD_REAL, _CHOLMOD_DOUBLE = 1, 0


class _Dense(ctypes.Structure):
    """cholmod_dense (cholmod_core.h): a column-major matrix with leading dimension d."""

    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("d", ctypes.c_size_t), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("xtype", ctypes.c_int), ("dtype", ctypes.c_int)]


_library: ctypes.CDLL | None = None
_bound: bool | None = None
_bind_lock = threading.Lock()
_local = threading.local()
_capsule_name = ctypes.pythonapi.PyCapsule_GetName
_capsule_name.restype, _capsule_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype, _capsule_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]


def _bind() -> bool:
    """Load cvxopt's libcholmod and declare the three functions used; False where it fails."""
    global _library, _bound
    with _bind_lock:
        if _bound is None:
            _bound = False
            import cvxopt.cholmod  # loads libcholmod with its dependencies, which a path alone would not find

            found = glob.glob(os.path.join(os.path.dirname(cvxopt.__file__), os.pardir, "cvxopt.libs", "libcholmod-*.so*"))
            if len(found) == 1:
                try:
                    library = ctypes.CDLL(found[0])
                    library.cholmod_l_start.argtypes = [ctypes.c_void_p]
                    library.cholmod_l_solve.restype = ctypes.POINTER(_Dense)
                    library.cholmod_l_solve.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(_Dense), ctypes.c_void_p]
                    library.cholmod_l_free_dense.argtypes = [ctypes.POINTER(ctypes.POINTER(_Dense)), ctypes.c_void_p]
                except (OSError, AttributeError):
                    library = None
                _library, _bound = library, library is not None
        return _bound


def available() -> bool:
    """Whether CHOLMOD's solve can be called without the GIL here."""
    return _bound if _bound is not None else _bind()


def _common() -> ctypes.Array:
    common = getattr(_local, "common", None)
    if common is None:
        common = _local.common = ctypes.create_string_buffer(_COMMON_BYTES)
        _library.cholmod_l_start(common)
    return common


def solve(capsule, rhs: np.ndarray, systems: tuple[int, ...]) -> np.ndarray:
    """CHOLMOD's `systems` (its sys codes: 0 A, 4 L, 5 L^T, 7 P, 8 P^T) applied in turn to the
    columns of rhs (n, k), for the factor in cvxopt's `capsule`; a new (n, k) array."""
    if not available():
        raise RuntimeError("CHOLMOD's solve cannot be bound here (see cholmod_solve.available)")
    factor = _capsule_pointer(capsule, _capsule_name(capsule))
    common = _common()
    solution = np.asfortranarray(rhs, dtype=np.float64)
    rows, columns = solution.shape
    for system in systems:
        given = _Dense(rows, columns, rows * columns, rows, solution.ctypes.data, None, _CHOLMOD_REAL, _CHOLMOD_DOUBLE)
        result = _library.cholmod_l_solve(system, factor, ctypes.byref(given), common)
        if not result:
            raise MemoryError(f"CHOLMOD's solve (sys {system}) of {rows} x {columns} returned nothing")
        try:
            values = ctypes.cast(result.contents.x, ctypes.POINTER(ctypes.c_double))
            solution = np.ctypeslib.as_array(values, shape=(columns, rows)).T.copy(order="F")
        finally:
            _library.cholmod_l_free_dense(ctypes.byref(result), common)
    return solution
