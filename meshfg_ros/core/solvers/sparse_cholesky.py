"""Sparse Cholesky factorisation (CHOLMOD, through cvxopt) with the symbolic analysis kept.

The estimator factors matrices whose sparsity pattern never changes (every state block of a
window shares the mesh's pattern), so the fill-reducing ordering and symbolic analysis are done
once per `SparseCholesky` and every later `refactor` is numeric only. cvxopt's wheels ship
CHOLMOD (supernodal) with an optimised BLAS, the one the entry point chose (blas.py): measured
on a 1,344-dof block of the paper-scale window, with cvxopt's BLAS, numeric factorisation
1.7 ms against 10.4 ms for cholespy's CHOLMOD (which analyses again at every factorisation,
with a reference BLAS) and 12 ms for SuperLU; on a 30k-dof organ-scale block 0.74 s against
~12 s.

The fill-reducing ordering is METIS nested dissection (pymetis) of the node graph: cvxopt's
CHOLMOD is built without its METIS module (libcholmod has no cholmod_metis symbol) and orders by AMD, whose fill on 3D tetrahedral meshes is
much larger. Measured on the elastic stiffness of the organ-scale box (10,648 vertices, 31,944
dofs): nnz(L) 16.5M against 25.8M, numeric factorisation 0.46 s against 0.97 s, solve 22 ms
against 32 ms; 2,744 vertices: nnz(L) 2.3M against 3.3M, 40 ms against 69 ms.
"""

from __future__ import annotations

import contextlib
import copy
import threading
from concurrent.futures import Future

import numpy as np
import scipy.sparse
import pymetis

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.solvers import cholmod_without_gil

__all__ = ["PARALLEL_MIN_SIZE", "NotPositiveDefiniteError", "SparseCholesky", "nested_dissection"]

# Below this many nodes AMD (CHOLMOD's own choice) is nearly as good and METIS's call costs
# more than it saves: on the 512-vertex paper-scale block METIS takes 2.3 ms and saves 0.4 ms
# of a 2.7 ms factorisation.
NESTED_DISSECTION_MIN_NODES = 1000
# Solves of several right-hand sides split them over the worker threads (core/worker_threads.py)
# from this many rows: on a 3,000-dof block two columns take 0.64 ms on two threads against
# 0.74 ms in one call (a hand-off to a thread costs about 0.1 ms).
PARALLEL_MIN_SIZE = 3000


def nested_dissection(matrix_: scipy.sparse.csr_matrix, node_size: int = 1) -> np.ndarray | None:
    """Fill-reducing permutation p (P A P^T factored, row k of it is row p[k] of A) from METIS
    nested dissection of the graph whose nodes are consecutive groups of `node_size` dofs (a
    mesh vertex's x, y, z), the dofs of a node kept together; None for small matrices."""
    size = matrix_.shape[0]
    if size % node_size or size // node_size < NESTED_DISSECTION_MIN_NODES:
        return None
    coo = matrix_.tocoo()
    nodes = size // node_size
    graph = scipy.sparse.csr_matrix((np.ones(coo.nnz, dtype=np.int8), (coo.row // node_size, coo.col // node_size)),
                                    shape=(nodes, nodes))
    graph = (graph + graph.T).tocsr()  # METIS needs both directions; `matrix_` may hold one triangle
    graph.setdiag(0)
    graph.eliminate_zeros()
    graph.sort_indices()
    node_order, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(graph.indptr, graph.indices))
    node_order = np.asarray(node_order, dtype=np.int64)
    return (node_size * node_order[:, None] + np.arange(node_size)).reshape(-1)


def _cvxopt():
    """cvxopt with its CHOLMOD, imported on first use: the loader binds CHOLMOD's BLAS then, to
    the library the entry point loaded (blas.configure), so importing this module binds nothing."""
    import cvxopt.cholmod

    return cvxopt


class NotPositiveDefiniteError(ValueError):
    """An information matrix without a Cholesky square root (indefinite or singular)."""


class SparseCholesky:
    """CHOLMOD factor of a symmetric positive definite matrix with a fixed sparsity pattern.

    `matrix`: scipy sparse, symmetric (both triangles stored or not: only the lower triangle
    is read); `node_size`: dofs per graph node for the ordering (3 for mesh vertices);
    `numeric`: False makes the ordering and the symbolic analysis only, for a factor whose values
    come later (`refactor`, before any solve): a spare factor made before its first matrix is
    known. Raises NotPositiveDefiniteError when CHOLMOD meets a non-positive pivot.
    """

    def __init__(self, matrix_: scipy.sparse.spmatrix, node_size: int = 1, numeric: bool = True):
        csr = scipy.sparse.csr_matrix(matrix_, dtype=np.float64)
        csr.sort_indices()
        if csr.shape[0] != csr.shape[1]:
            raise ValueError(f"Cholesky needs a square matrix, got {csr.shape}")
        self.size = csr.shape[0]
        self._indptr, self._indices = csr.indptr.copy(), csr.indices.copy()
        rows = np.repeat(np.arange(self.size, dtype=np.int64), np.diff(csr.indptr))
        lower = np.flatnonzero(csr.indices <= rows)
        # cvxopt stores column-major; the lower entries in that order, so a refactor only
        # assigns values to one kept spmatrix (2 ms against 24 ms to build one, organ scale).
        self._lower = lower[np.lexsort((rows[lower], csr.indices[lower]))]
        cvxopt = _cvxopt()
        self._matrix = cvxopt.spmatrix(self._values(csr.data), cvxopt.matrix(rows[self._lower]),
                                       cvxopt.matrix(csr.indices[self._lower].astype(np.int64)), (self.size, self.size))
        # Its lower triangle's compressed columns, for CHOLMOD's factorisation without the GIL.
        self._column_starts, self._rows = (np.array(part, dtype=np.int64).ravel() for part in self._matrix.CCS[:2])
        order = nested_dissection(csr, node_size)
        self._ordering = {} if order is None else {"p": cvxopt.matrix(order.tolist(), tc="i")}
        self._analyse(csr.data if numeric else None)

    def _analyse(self, data: np.ndarray | None) -> None:
        """Symbolic analysis of the kept matrix with the kept ordering, then the numeric one of
        `data` (none for None)."""
        self._factor = _cvxopt().cholmod.symbolic(self._matrix, uplo="L", **self._ordering)
        self._numeric = False  # whether the factor holds a successful numeric factorisation
        self.revision = 0  # numeric factorisations begun: which values a kept result was computed with
        self._readers = threading.Lock()  # held by `reading`, which a refactor waits for
        if data is not None:
            self.refactor(data)

    def sibling(self, data: np.ndarray | None) -> SparseCholesky:
        """A new factor of the matrix with values `data` on this factor's pattern, sharing the
        pattern bookkeeping and the ordering (a new state's block in a window whose factors are
        all in use: 3.0 ms against 4.6 ms for a new SparseCholesky on a paper-scale block);
        None: its symbolic analysis only, values to come (`refactor`)."""
        twin = copy.copy(self)
        twin._matrix = self._matrix * 1.0  # its own copy (8 us; building one takes 0.7 ms)
        twin._analyse(data)
        return twin

    def _values(self, data: np.ndarray):
        return _cvxopt().matrix(np.ascontiguousarray(data[self._lower], dtype=np.float64))

    def same_pattern(self, matrix_: scipy.sparse.csr_matrix) -> bool:
        """True when `matrix_` (csr, sorted indices) has the pattern this factor was analysed for."""
        return (matrix_.shape == (self.size, self.size) and np.array_equal(matrix_.indptr, self._indptr)
                and np.array_equal(matrix_.indices, self._indices))

    def refactor(self, data: np.ndarray) -> None:
        """Numeric factorisation of the matrix with values `data` on the analysed csr pattern;
        through cholmod_without_gil.py where it binds, which releases the GIL (a refactor can run on a
        thread of its own while Python works on)."""
        if not np.all(np.isfinite(data)):
            raise NotPositiveDefiniteError("Cholesky of a matrix with non-finite entries")
        with self._readers:
            self.revision += 1
            self._refactor(data)

    def refactor_beside(self, data: np.ndarray) -> Future:
        """`refactor` on the process's background thread (worker_threads.start_background):
        the factor is counted as refactored at once (`revision`), so that work queued behind it
        there (covariance draws through it) is judged against the values it factors; solves on
        this thread must wait for the returned future first. Its `result()` raises
        NotPositiveDefiniteError or MemoryError as `refactor` would."""
        data = np.asarray(data, dtype=np.float64)
        if not np.all(np.isfinite(data)):
            raise NotPositiveDefiniteError("Cholesky of a matrix with non-finite entries")
        self.revision += 1
        self._numeric = False
        return worker_threads.start_background(self._refactor_reading, data)

    def _refactor_reading(self, data: np.ndarray) -> None:
        with self._readers:
            self._refactor(data)

    def _refactor(self, data: np.ndarray) -> None:
        self._numeric = False
        if cholmod_without_gil.available():
            if not cholmod_without_gil.factorize(self._factor, self._column_starts, self._rows, data[self._lower]):
                raise NotPositiveDefiniteError("Cholesky failed: a pivot is not positive")
        else:
            try:
                self._matrix.V = self._values(data)
                _cvxopt().cholmod.numeric(self._matrix, self._factor)
            except ArithmeticError as error:
                raise NotPositiveDefiniteError(f"Cholesky failed: pivot {error} not positive") from None
        self._numeric = True

    @contextlib.contextmanager
    def reading(self):
        """Solves on another thread than the one that refactors this factor are made inside
        this: a refactor waits until they end (CHOLMOD would overwrite the factor under them)."""
        with self._readers:
            yield self

    def solve(self, rhs: np.ndarray, split: bool = True) -> np.ndarray:
        """A^-1 rhs for rhs (n,) or (n, k) (CHOLMOD's sys code 0); `split` as in `back_solve`."""
        return self._substitutions(rhs, (0,), split)

    def forward_solve(self, rhs: np.ndarray) -> np.ndarray:
        """L^-1 P rhs for rhs (n,) or (n, k), the first half of `solve` (sys codes 7, x = P b, and
        4, L x = b): solve(b) = back_solve(forward_solve(b)), and B^T A^-1 B is the Gram matrix
        of forward_solve(B)'s columns."""
        return self._substitutions(rhs, (7, 4))

    def back_solve(self, rhs: np.ndarray, split: bool = True) -> np.ndarray:
        """P^T L^-T rhs for rhs (n,) or (n, k), the second half of `solve`: with rhs ~ N(0, I),
        samples of N(0, A^-1), since A = P^T L L^T P. `split`: the columns over the worker
        threads (else one call, whose results do not depend on the thread count)."""
        return self._substitutions(rhs, (5, 8), split)

    def _substitutions(self, rhs: np.ndarray, systems: tuple[int, ...], split: bool = True) -> np.ndarray:
        """CHOLMOD's `systems` applied in turn to rhs (n,) or (n, k). The columns are split over
        the worker threads (worker_threads.py), each part one CHOLMOD call without the GIL
        (cholmod_without_gil.py): at organ scale (31k dofs) four columns in 24 ms on two threads
        against 39 ms in one call. Without that binding, through cvxopt on one thread: its
        sparse solve hands CHOLMOD blocks of columns, where its dense one solves a column at a
        time (two columns in 0.82 of the time of two single solves, three in 0.65)."""
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.shape[0] != self.size:
            raise ValueError(f"right-hand side has {rhs.shape[0]} rows, the matrix {self.size}")
        if not self._numeric:  # CHOLMOD would answer a failed factor with NaN, a symbolic one with an error
            raise NotPositiveDefiniteError("solve with a factor whose numeric factorisation failed or was never made")
        if rhs.size == 0:
            return rhs.copy()
        columns = rhs.reshape(self.size, -1)
        if cholmod_without_gil.available():
            most = columns.shape[1] if split and self.size >= PARALLEL_MIN_SIZE else 1
            parts = [(self._factor, columns[:, share], systems) for share in worker_threads.ranges(columns.shape[1], most)]
            return np.hstack(worker_threads.run_parts(cholmod_without_gil.solve, parts)).reshape(rhs.shape)
        cvxopt = _cvxopt()
        if columns.shape[1] == 1:
            solution = cvxopt.matrix(columns)
            for system in systems:
                cvxopt.cholmod.solve(self._factor, solution, sys=system)
            return np.array(solution).reshape(rhs.shape)
        solution = cvxopt.sparse(cvxopt.matrix(columns))
        for system in systems:
            solution = cvxopt.cholmod.spsolve(self._factor, solution, sys=system)
        return np.array(cvxopt.matrix(solution)).reshape(rhs.shape)
