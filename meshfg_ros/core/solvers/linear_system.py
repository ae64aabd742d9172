"""The linearised window: the damped Gauss-Newton matrix in its block-tridiagonal form.

The window's Gauss-Newton matrix is block tridiagonal in time: one sparse block per state
(physics prior + measurements + the temporal terms' diagonal) and, between consecutive
states, the temporal factor's -c I. `WindowSystem` keeps that structure, so a matrix-vector
product never builds the global matrix, and converts to one sparse matrix for direct
solvers. FactorGraph.linearize builds it; the linear solvers (linear_solvers.py) solve it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

import meshfg_ros.core.worker_threads as worker_threads

__all__ = ["WindowSystem", "diagonal_positions"]

# A matrix-vector product is split over the worker threads (core/worker_threads.py) in parts of
# at least this many stored entries: a 10,648-vertex state block holds 1.3 million, its product
# takes 0.8 ms, and a hand-off to a thread about 0.1 ms.
PARALLEL_MIN_ENTRIES = 500_000


def diagonal_positions(matrix: scipy.sparse.csr_matrix) -> np.ndarray:
    """Index into matrix.data of every diagonal entry (the pattern must hold the whole diagonal)."""
    rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    positions = np.flatnonzero(matrix.indices == rows)
    if positions.size != matrix.shape[0]:
        raise ValueError("sparse pattern lacks diagonal entries")
    return positions


class WindowSystem:
    """Symmetric block-tridiagonal matrix: blocks[t] (csr, n x n) on the diagonal and
    couplings[t] * I between block t and t + 1; keys name the blocks (for factor caching).

    All blocks share one sparse pattern whose diagonal is at `diagonal_index` in `data`.
    revisions[t] (optional) names block t's off-diagonal values: two blocks with the same key
    and revision differ at most on the diagonal (damping, temporal terms), which lets the PCG
    preconditioner compare them on the diagonal alone. `diagonal_shift` (W, n) (optional) is
    added to the blocks' diagonals without copying them: the temporal factors' c I terms of each
    state (FactorGraph.linearize) and LM's damping on top of them (`with_added_diagonal`, one
    shift per trial damping of a linearisation: damped copies of ten blocks would cost 0.8 ms
    per trial at paper scale); `block_data(t)` and `blocks` include it.
    """

    def __init__(self, blocks, couplings, keys, diagonal_index: np.ndarray, coupling_diagonal=None,
                 vertex_block_index: np.ndarray | None = None, revisions=None, diagonal_shift=None):
        self._base_blocks = list(blocks)
        self.couplings = np.asarray(couplings, dtype=np.float64).reshape(-1)
        self.keys = list(keys)
        self.diagonal_index = diagonal_index
        # The part c_t of each block's diagonal that comes from the couplings (temporal
        # factors), so blocks minus it and the couplings form the time Laplacian exactly.
        self.coupling_diagonal = (
            np.zeros(len(self.keys)) if coupling_diagonal is None else np.asarray(coupling_diagonal, dtype=np.float64)
        )
        self._vertex_block_index = vertex_block_index
        self.revisions = [None] * len(self.keys) if revisions is None else list(revisions)
        if len(self.couplings) != max(len(self._base_blocks) - 1, 0) or len(self.keys) != len(self._base_blocks):
            raise ValueError("a window system needs W blocks, W keys and W - 1 couplings")
        self.pattern = self._base_blocks[0]  # the shared sparsity pattern (its values: block 0's)
        self.block_size = self.pattern.shape[0]
        self.size = self.block_size * len(self.keys)
        self.diagonal_shift = (None if diagonal_shift is None
                               else np.asarray(diagonal_shift, dtype=np.float64).reshape(len(self.keys), self.block_size))
        self._shifted_blocks: list | None = None

    @property
    def blocks(self) -> list:
        """The diagonal blocks as csr matrices, the diagonal shift included (built on first use)."""
        if self.diagonal_shift is None:
            return self._base_blocks
        if self._shifted_blocks is None:
            self._shifted_blocks = [
                scipy.sparse.csr_matrix((self.block_data(t), block.indices, block.indptr), shape=block.shape)
                for t, block in enumerate(self._base_blocks)
            ]
        return self._shifted_blocks

    def block_data(self, t: int) -> np.ndarray:
        """Values of block t on the shared pattern, the shift included (a new array)."""
        data = self._base_blocks[t].data.copy()
        if self.diagonal_shift is not None:
            data[self.diagonal_index] += self.diagonal_shift[t]
        return data

    def block_diagonal(self, t: int) -> np.ndarray:
        diagonal = self._base_blocks[t].data[self.diagonal_index]
        return diagonal if self.diagonal_shift is None else diagonal + self.diagonal_shift[t]

    def vertex_blocks(self, data: np.ndarray) -> np.ndarray:
        """The 3x3 diagonal (vertex) blocks, (n/3, 3, 3), of a block with values `data` on the
        shared pattern (entries missing from the pattern are zero)."""
        if self._vertex_block_index is not None:
            return data[self._vertex_block_index]
        if self.block_size % 3:
            raise ValueError("vertex blocks need a block size divisible by 3")
        first = self.pattern
        matrix = scipy.sparse.csr_matrix((data, first.indices, first.indptr), shape=first.shape)
        dofs = 3 * np.arange(self.block_size // 3)[:, None, None] + np.arange(3)
        rows = np.broadcast_to(dofs, (self.block_size // 3, 3, 3))
        return np.asarray(matrix[rows.reshape(-1), rows.transpose(0, 2, 1).reshape(-1)]).reshape(-1, 3, 3)

    def time_laplacian(self) -> np.ndarray:
        """(W, W) matrix of the couplings: coupling_diagonal on the diagonal, couplings beside it."""
        laplacian = np.diag(self.coupling_diagonal)
        index = np.arange(len(self.couplings))
        laplacian[index, index + 1] = laplacian[index + 1, index] = self.couplings
        return laplacian

    @classmethod
    def single(cls, matrix, key=0) -> WindowSystem:
        """A plain sparse symmetric matrix as a one-block system."""
        matrix = scipy.sparse.csr_matrix(matrix, dtype=np.float64)
        matrix = (matrix + scipy.sparse.diags(np.zeros(matrix.shape[0]))).tocsr()
        matrix.sum_duplicates()
        matrix.sort_indices()
        return cls([matrix], [], [key], diagonal_positions(matrix))

    def split(self, x: np.ndarray) -> np.ndarray:
        """x (size,) as (W, block_size), one row per state: a view, so writing to a row writes x."""
        return x.reshape(len(self.keys), self.block_size)

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """A x; blocks of x that are zero cost no sparse product (PCGSolver's partial solves).
        The blocks' products run on the worker threads (scipy's product releases the GIL) when
        each thread gets at least PARALLEL_MIN_ENTRIES of them."""
        parts = self.split(x)
        out = np.zeros_like(parts)
        active = [t for t in range(len(self.keys)) if parts[t].any()]
        worker_threads.run_parts(self._block_products, [
            (group, parts, out) for group in worker_threads.split(active, len(active) * self.pattern.nnz // PARALLEL_MIN_ENTRIES)])
        if self.diagonal_shift is not None:
            out += self.diagonal_shift * parts
        self.add_couplings(parts, out)
        return out.reshape(-1)

    def add_couplings(self, parts: np.ndarray, out: np.ndarray) -> None:
        """out += the temporal couplings' share of A x, for x as `parts` (W, block_size)."""
        if len(self.couplings):
            out[:-1] += self.couplings[:, None] * parts[1:]
            out[1:] += self.couplings[:, None] * parts[:-1]

    def _block_products(self, blocks, parts: np.ndarray, out: np.ndarray) -> None:
        for t in blocks:
            out[t] = self._base_blocks[t] @ parts[t]

    def restricted(self, blocks) -> WindowSystem:
        """The system of the blocks `blocks` (increasing indices) alone: their rows and columns,
        with the couplings between those that are neighbours; shares the blocks."""
        index = np.asarray(blocks, dtype=np.int64)
        couplings = [self.couplings[t] if s == t + 1 else 0.0 for t, s in zip(index[:-1], index[1:])]
        shift = None if self.diagonal_shift is None else self.diagonal_shift[index]
        return WindowSystem([self._base_blocks[t] for t in index], couplings, [self.keys[t] for t in index],
                            self.diagonal_index, self.coupling_diagonal[index], self._vertex_block_index,
                            [self.revisions[t] for t in index], shift)

    def diagonal(self) -> np.ndarray:
        return np.concatenate([self.block_diagonal(t) for t in range(len(self.keys))])

    def with_added_diagonal(self, values: np.ndarray) -> WindowSystem:
        """A new system with `values` (size,) added to the diagonal (the damping); shares the
        blocks with this one."""
        shift = self.split(np.asarray(values, dtype=np.float64))
        if self.diagonal_shift is not None:
            shift = shift + self.diagonal_shift
        return WindowSystem(self._base_blocks, self.couplings, self.keys, self.diagonal_index, self.coupling_diagonal,
                            self._vertex_block_index, self.revisions, shift)

    def to_coo(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, data) of the whole matrix, int32 indices."""
        first = self.pattern
        block_rows = np.repeat(np.arange(self.block_size, dtype=np.int64), np.diff(first.indptr))
        rows, cols, data = [], [], []
        for t, block in enumerate(self._base_blocks):
            offset = t * self.block_size
            rows.append(block_rows + offset)
            cols.append(block.indices.astype(np.int64) + offset)
            data.append(self.block_data(t))
        local = np.arange(self.block_size, dtype=np.int64)
        for t, coupling in enumerate(self.couplings):
            upper, lower = local + t * self.block_size, local + (t + 1) * self.block_size
            rows += [upper, lower]
            cols += [lower, upper]
            data += [np.full(self.block_size, coupling)] * 2
        return (
            np.concatenate(rows).astype(np.int32),
            np.concatenate(cols).astype(np.int32),
            np.concatenate(data),
        )

    def to_csr(self) -> scipy.sparse.csr_matrix:
        rows, cols, data = self.to_coo()
        return scipy.sparse.csr_matrix((data, (rows, cols)), shape=(self.size, self.size))

