"""CHOLMOD's solve (`cholmod_l_solve`) and numeric factorisation (`cholmod_l_factorize`) on
cvxopt's factors, called without Python's lock.

cvxopt's `cholmod.solve`, `spsolve` and `numeric` hold the GIL while CHOLMOD works, so two
threads cannot solve at once, nor can Python run while a factor is made, and no other CHOLMOD
binding has wheels for this Python (blas.py). ctypes releases the GIL around a foreign call, so
this module calls the functions of the very library cvxopt loaded (its wheel's
`cvxopt.libs/libcholmod-*.so`, CHOLMOD 3.0) on the factor inside cvxopt's capsule. CHOLMOD is
thread-safe with one `cholmod_common` per thread (its workspace and error state); a solve only
reads the factor. Measured at organ scale (a 31,944-dof block, MKL, one BLAS thread): four
right-hand sides in one call 39 ms, as two calls of two on two threads 24 ms; a factorisation
takes the 0.37 s cvxopt's does, and gives the same factor (its solves agree bit for bit), while
the simulator's K0 of a new Poisson ratio is made beside the loop (core/physics/simulator.py).

`available()` is False where the library cannot be found or bound (another cvxopt build):
sparse_cholesky.py then factors and solves through cvxopt, on one thread.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading

import numpy as np

__all__ = ["available", "factorize", "solve"]

# cholmod_common is a C struct of about 2 KB in CHOLMOD 3; its size is not exported, so each
# thread's is given room to spare.
_COMMON_BYTES = 64 * 1024
_CHOLMOD_REAL, _CHOLMOD_DOUBLE, _CHOLMOD_LONG = 1, 0, 2
_LOWER_STORED = -1  # cholmod_sparse.stype of a symmetric matrix given by its lower triangle


class _Sparse(ctypes.Structure):
    """cholmod_sparse (cholmod_core.h): compressed columns, here packed and sorted."""

    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("nz", ctypes.c_void_p), ("x", ctypes.c_void_p),
                ("z", ctypes.c_void_p), ("stype", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
                ("dtype", ctypes.c_int), ("sorted", ctypes.c_int), ("packed", ctypes.c_int)]


class _CommonHead(ctypes.Structure):
    """The first fields of cholmod_common (CHOLMOD 3), up to its print level."""

    _fields_ = [("dbound", ctypes.c_double), ("grow0", ctypes.c_double), ("grow1", ctypes.c_double),
                ("grow2", ctypes.c_size_t), ("maxrank", ctypes.c_size_t), ("supernodal_switch", ctypes.c_double),
                ("supernodal", ctypes.c_int), ("final_asis", ctypes.c_int), ("final_super", ctypes.c_int),
                ("final_ll", ctypes.c_int), ("final_pack", ctypes.c_int), ("final_monotonic", ctypes.c_int),
                ("final_resymbol", ctypes.c_int), ("zrelax", ctypes.c_double * 3), ("nrelax", ctypes.c_size_t * 3),
                ("prefer_zomplex", ctypes.c_int), ("prefer_upper", ctypes.c_int),
                ("quick_return_if_not_posdef", ctypes.c_int), ("prefer_binary", ctypes.c_int), ("print", ctypes.c_int)]


class _FactorHead(ctypes.Structure):
    """The first fields of cholmod_factor: its order and the column at which a numeric
    factorisation stopped (n where it succeeded)."""

    _fields_ = [("n", ctypes.c_size_t), ("minor", ctypes.c_size_t)]


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
    """Load cvxopt's libcholmod and declare the four functions used; False where it fails."""
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
                    library.cholmod_l_factorize.restype = ctypes.c_int
                    library.cholmod_l_factorize.argtypes = [ctypes.POINTER(_Sparse), ctypes.c_void_p, ctypes.c_void_p]
                except (OSError, AttributeError):
                    library = None
                _library, _bound = library, library is not None
        return _bound


def available() -> bool:
    """Whether CHOLMOD's solve and factorisation can be called without the GIL here."""
    return _bound if _bound is not None else _bind()


def _common() -> ctypes.Array:
    common = getattr(_local, "common", None)
    if common is None:
        common = _local.common = ctypes.create_string_buffer(_COMMON_BYTES)
        _library.cholmod_l_start(common)
        # Silent, as cvxopt's: at its default level CHOLMOD prints a warning for every matrix
        # that is not positive definite, which the callers report themselves. Set only where
        # the defaults read back where this layout puts them.
        head = _CommonHead.from_buffer(common)
        if (head.grow0, head.maxrank, head.supernodal_switch, head.print) == (1.2, 8, 40.0, 3):
            head.print = 0
    return common


def _factor(capsule) -> int:
    """The cholmod_factor in cvxopt's `capsule` (RuntimeError where CHOLMOD cannot be bound)."""
    if not available():
        raise RuntimeError("CHOLMOD cannot be bound here (see cholmod_without_gil.available)")
    return _capsule_pointer(capsule, _capsule_name(capsule))


def solve(capsule, rhs: np.ndarray, systems: tuple[int, ...]) -> np.ndarray:
    """CHOLMOD's `systems` (its sys codes: 0 A, 4 L, 5 L^T, 7 P, 8 P^T) applied in turn to the
    columns of rhs (n, k), for the factor in cvxopt's `capsule`; a new (n, k) array."""
    factor = _factor(capsule)
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


def factorize(capsule, column_starts: np.ndarray, rows: np.ndarray, values: np.ndarray) -> bool:
    """Numeric factorisation, into the factor in cvxopt's `capsule` (its symbolic analysis made),
    of the symmetric matrix whose lower triangle has, column by column in row order, the
    entries `values` at `rows` (int64), column j's at column_starts[j]:column_starts[j + 1]:
    what cvxopt's `cholmod.numeric` does, without the GIL. Returns whether the matrix is
    positive definite (False: CHOLMOD stopped at a non-positive pivot, and the factor must
    not be used)."""
    factor = _factor(capsule)
    column_starts = np.ascontiguousarray(column_starts, dtype=np.int64)
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    values = np.ascontiguousarray(values, dtype=np.float64)
    size = column_starts.size - 1
    matrix = _Sparse(size, size, values.size, column_starts.ctypes.data, rows.ctypes.data, None, values.ctypes.data,
                     None, _LOWER_STORED, _CHOLMOD_LONG, _CHOLMOD_REAL, _CHOLMOD_DOUBLE, 1, 1)
    if not _library.cholmod_l_factorize(ctypes.byref(matrix), factor, _common()):
        raise MemoryError(f"CHOLMOD's factorisation of a {size} x {size} matrix failed")
    head = _FactorHead.from_address(factor)
    return head.minor == head.n
