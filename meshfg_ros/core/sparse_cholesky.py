"""Sparse Cholesky factorisation (CHOLMOD, through cvxopt) with the symbolic analysis kept.

The estimator factors matrices whose sparsity pattern never changes (every state block of a
window shares the mesh's pattern), so the fill-reducing ordering and symbolic analysis are done
once per `SparseCholesky` and every later `refactor` is numeric only. cvxopt's wheels ship
CHOLMOD with an optimised BLAS (supernodal): measured on a 1,344-dof block of the paper-scale
window, numeric factorisation 1.7 ms against 10.4 ms for cholespy's CHOLMOD (which analyses
again at every factorisation, with a reference BLAS) and 12 ms for SuperLU; on a 30k-dof
organ-scale block 0.74 s against ~12 s.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from cvxopt import cholmod, matrix, spmatrix

from .noise import NotPositiveDefiniteError

__all__ = ["SparseCholesky"]


class SparseCholesky:
    """CHOLMOD factor of a symmetric positive definite matrix with a fixed sparsity pattern.

    `matrix`: scipy sparse, symmetric (both triangles stored or not: only the lower triangle
    is read). Raises NotPositiveDefiniteError when CHOLMOD meets a non-positive pivot.
    """

    def __init__(self, matrix_: scipy.sparse.spmatrix):
        csr = scipy.sparse.csr_matrix(matrix_, dtype=np.float64)
        csr.sort_indices()
        if csr.shape[0] != csr.shape[1]:
            raise ValueError(f"Cholesky needs a square matrix, got {csr.shape}")
        self.size = csr.shape[0]
        self._indptr, self._indices = csr.indptr.copy(), csr.indices.copy()
        rows = np.repeat(np.arange(self.size, dtype=np.int64), np.diff(csr.indptr))
        self._lower = np.flatnonzero(csr.indices <= rows)
        self._rows = matrix(rows[self._lower])
        self._columns = matrix(csr.indices[self._lower].astype(np.int64))
        self._factor = cholmod.symbolic(self._cvxopt(csr.data), uplo="L")
        self.refactor(csr.data)

    def _cvxopt(self, data: np.ndarray) -> spmatrix:
        values = matrix(np.ascontiguousarray(data[self._lower], dtype=np.float64))
        return spmatrix(values, self._rows, self._columns, (self.size, self.size))

    def same_pattern(self, matrix_: scipy.sparse.csr_matrix) -> bool:
        """True when `matrix_` (csr, sorted indices) has the pattern this factor was analysed for."""
        return (matrix_.shape == (self.size, self.size) and np.array_equal(matrix_.indptr, self._indptr)
                and np.array_equal(matrix_.indices, self._indices))

    def refactor(self, data: np.ndarray) -> None:
        """Numeric factorisation of the matrix with values `data` on the analysed csr pattern."""
        if not np.all(np.isfinite(data)):
            raise NotPositiveDefiniteError("Cholesky of a matrix with non-finite entries")
        try:
            cholmod.numeric(self._cvxopt(data), self._factor)
        except ArithmeticError as error:
            raise NotPositiveDefiniteError(f"Cholesky failed: pivot {error} not positive") from None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """A^-1 rhs for rhs (n,) or (n, k)."""
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.shape[0] != self.size:
            raise ValueError(f"right-hand side has {rhs.shape[0]} rows, the matrix {self.size}")
        if rhs.size == 0:
            return rhs.copy()
        solution = matrix(rhs.reshape(self.size, -1))
        cholmod.solve(self._factor, solution)
        return np.array(solution).reshape(rhs.shape)
