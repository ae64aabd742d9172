"""Swappable solvers for the (damped) normal equations of the sliding window.

They solve a `WindowSystem` (linear_system.py): the window's block-tridiagonal Gauss-Newton
matrix, kept in blocks so that PCG never builds the global matrix.

Solvers (all return the solution and `SolveStats`):
  "pcg"       conjugate gradients with a preconditioner built on the time structure (see
              PCGSolver): sparse Cholesky factors (CHOLMOD, sparse_cholesky.py) made once and
              reused across LM iterations and updates while they stay accurate.
  "cholesky"  sparse Cholesky of the whole window (CHOLMOD); raises NotPositiveDefiniteError.
  "superlu"   scipy SuperLU (LU, no definiteness check).
`FallbackSolver` tries solvers in order and says in its message when one failed; a
NotPositiveDefiniteError is not a failure to fall back from: Levenberg-Marquardt answers it
by raising the damping.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.solvers.linear_system import WindowSystem, diagonal_positions
from meshfg_ros.core.solvers.sparse_cholesky import PARALLEL_MIN_SIZE, NotPositiveDefiniteError, SparseCholesky

__all__ = [
    "BESIDE_ITERATIONS",
    "BORROWED_ITERATIONS",
    "LINEAR_SOLVERS",
    "CholeskySolver",
    "FallbackSolver",
    "LinearSolveError",
    "LinearSolver",
    "NotPositiveDefiniteError",
    "PCGSolver",
    "PRECONDITIONERS",
    "SolveStats",
    "SuperLUSolver",
    "make_linear_solver",
]

LINEAR_SOLVERS = ("pcg", "cholesky", "superlu")
PRECONDITIONERS = ("auto", "block", "vertex")
# PCGSolver leaves out of a solve the blocks whose parts of the right-hand side together are at
# most this share of its tolerance (times |b|): see the class doc.
LEFT_OUT_SHARE = 0.5
# ... and solves the rest to this share of the tolerance, so that the whole residual (the
# left-out parts included) usually meets it without a second pass.
KEPT_SHARE = 0.8
# A state that joins a window borrows the newest factor (see PCGSolver); PCG gets this many
# iterations with a borrowed factor before the state gets its own.
BORROWED_ITERATIONS = 8
# A newest state that borrows gets a factor made beside the caller after an update where one of
# its solves took this many PCG iterations (PCGSolver.refactor_newest_beside): 2-3 while the
# factor fits (the bench's organ-scale box over 16 updates), 4-9 as it drifts.
BESIDE_ITERATIONS = 4


class LinearSolveError(RuntimeError):
    """A solver failed for a reason other than indefiniteness (no convergence, singular LU)."""


@dataclass
class SolveStats:
    """What one linear solve did: method, iterations (0 for direct), wall time, refactored
    blocks (pcg) and a message (fallbacks)."""

    method: str
    time_ms: float
    iterations: int = 0
    factorizations: int = 0
    message: str = ""


class LinearSolver:
    name = ""

    def solve(self, system: WindowSystem, rhs: np.ndarray) -> tuple[np.ndarray, SolveStats]:
        raise NotImplementedError

    def decrement(self, system: WindowSystem, gradient: np.ndarray) -> float:
        """0.5 g^T A^-1 g: the cost decrease a Newton step on A would predict (LM's stopping
        test). This base version solves; PCG estimates it with its preconditioner alone."""
        step, _ = self.solve(system, -gradient)
        return -0.5 * float(gradient @ step)

    def reserve(self, pattern: scipy.sparse.csr_matrix, count: int) -> None:
        """Make, before any solve, what solves of windows of `count` states with state blocks of
        `pattern` would otherwise make at their first use. Nothing to make for this solver."""

    def state_factor(self, key) -> SparseCholesky | None:
        """The Cholesky factor this solver's last solves used for state `key`'s block (of that
        block, or of one close to it), or None: this solver keeps none."""
        return None

    def refactor_newest_beside(self) -> SparseCholesky | None:
        """Start, beside the caller, what the next update's solves will want (PCGSolver: a
        fresh factor for the state that joins next to borrow); the factor it makes, or None:
        nothing to start for this solver."""
        return None


class CholeskySolver(LinearSolver):
    """Sparse Cholesky (CHOLMOD) of the whole window; the symbolic analysis is kept while the
    window's pattern stays the same (a full window)."""

    name = "cholesky"

    def __init__(self):
        self._factor: SparseCholesky | None = None

    def solve(self, system, rhs):
        start = time.perf_counter()
        matrix = system.to_csr()
        matrix.sort_indices()
        if self._factor is not None and self._factor.same_pattern(matrix):
            self._factor.refactor(matrix.data)
        else:
            self._factor = SparseCholesky(matrix, node_size=3)
        x = self._factor.solve(rhs)
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("Cholesky solve produced non-finite values")
        return x, SolveStats(self.name, 1e3 * (time.perf_counter() - start), factorizations=1)


class SuperLUSolver(LinearSolver):
    """scipy SuperLU (LU with partial pivoting) of the whole window; no definiteness check."""

    name = "superlu"

    def solve(self, system, rhs):
        start = time.perf_counter()
        try:
            factor = scipy.sparse.linalg.splu(system.to_csr().tocsc(), permc_spec="COLAMD")
        except RuntimeError as error:
            raise LinearSolveError(f"SuperLU failed: {error}") from None
        x = factor.solve(np.asarray(rhs, dtype=np.float64))
        if not np.all(np.isfinite(x)):
            raise LinearSolveError("SuperLU produced non-finite values")
        return x, SolveStats(self.name, 1e3 * (time.perf_counter() - start), factorizations=1)


class _BlockFactor:
    """A state block's cached Cholesky factor and the block values R it was made from.

    A factor of R serves c R exactly once its solves are divided by c, and whole blocks scale
    so: the estimated measurement sigma weighs the prior too (the prior's sigma is a tenth of
    it), so a new noise estimate scales a state's block and nothing else. `scale` gives c from
    the diagonals (a thirty-sixth of the entries; exact for a multiple of R), as every solve
    needs it; `distance` gives |B - c R| / |B|, as only a state's own factor needs it (a
    borrowed one is judged by PCG's iterations). Blocks of one revision
    (WindowSystem.revisions) differ only on the diagonal, so the off-diagonal parts of <B, R>
    and |B|^2 are computed once per revision and the diagonal's per call.
    """

    def __init__(self, factor: SparseCholesky, reference: np.ndarray, diagonal_index: np.ndarray, revision):
        self.factor = factor
        self.reference = reference
        self.reference_squared = max(float(reference @ reference), 1e-300)
        self.reference_diagonal = reference[diagonal_index]
        self.reference_diagonal_squared = max(float(self.reference_diagonal @ self.reference_diagonal), 1e-300)
        # (<B, R>, |B|^2) over the off-diagonal entries for blocks of revision seen_revision
        # (B = R for the revision the factor was made from)
        self.seen_revision = revision
        off_diagonal_squared = self.reference_squared - self.reference_diagonal_squared
        self.off_diagonal = (off_diagonal_squared, off_diagonal_squared)
        self.borrowed = False            # another state's factor (PCGSolver: borrowing)
        self.multiple = 1.0              # c: the block it serves is c R (PCGSolver._refresh sets it)

    def lent(self) -> _BlockFactor:
        """This factor, borrowed by a state that has none (a copy: its multiple is that state's)."""
        borrowed = copy.copy(self)
        borrowed.borrowed = True
        return borrowed

    def scale(self, system: WindowSystem, t: int) -> float:
        """c = <b, r> / |r|^2 for the diagonals b of block t of `system` and r of R (1 where it
        is not positive, or the pattern differs)."""
        if system.pattern.data.shape != self.reference.shape:
            return 1.0
        scale = float(system.block_diagonal(t) @ self.reference_diagonal) / self.reference_diagonal_squared
        return scale if scale > 0.0 else 1.0

    def distance(self, system: WindowSystem, t: int, scale: float) -> float:
        """|B - c R| / |B| for block t of `system` and c = `scale`."""
        if system.pattern.data.shape != self.reference.shape:
            return np.inf
        revision = system.revisions[t]
        diagonal = system.block_diagonal(t)
        diagonal_product, diagonal_squared = float(diagonal @ self.reference_diagonal), float(diagonal @ diagonal)
        if revision is None or revision != self.seen_revision:
            data = system.block_data(t)
            self.off_diagonal = (float(data @ self.reference) - diagonal_product, float(data @ data) - diagonal_squared)
            self.seen_revision = revision
        product = self.off_diagonal[0] + diagonal_product
        squared = max(self.off_diagonal[1] + diagonal_squared, 1e-300)
        remainder = squared - 2.0 * scale * product + scale**2 * self.reference_squared
        return float(np.sqrt(max(remainder, 0.0) / squared))


class PCGSolver(LinearSolver):
    """Preconditioned conjugate gradients exploiting the window's time structure.

    Preconditioners (`preconditioner`):
      "block"   block Jacobi over the time steps: each state's block Cholesky-factored
                (sparse_cholesky.py) and cached by its key, refreshed when the block drifts by
                more than `refresh_change` from a multiple of the values it was made from
                (relative Frobenius norm: a re-linearisation, damping, a new temporal
                neighbour; a factor of R serves c R divided by c) or PCG needs more than
                `refresh_iterations` iterations; a state that joins the window borrows the
                newest factor (below). Exact without couplings.
      "vertex"  M = I (x) Bbar + T (x) I, Bbar the 3x3 vertex blocks of the states' mean block
                and T the (W, W) time Laplacian of the couplings. With T = Q diag(mu) Q^T it
                is block diagonal in the time eigenbasis, so applying it is a batch of 3x3
                solves with (Bbar_v + mu_j I): no factorisation, for meshes where a state's
                sparse Cholesky is too slow. Exact in the couplings, which tie the smooth
                deformation modes (weakly held by K) through time. Refreshed when the mean
                block drifts by more than `refresh_change` or T changes.
      "auto"    "block" up to `cholesky_max_block` dofs per state, else "vertex".
    Block Jacobi with a factor per state needs the fewest iterations on the estimator's
    windows: about 20 against 120 for "vertex" on a 512-vertex window (W=10, 13k unknowns,
    tolerance 1e-8), where whole-window Cholesky or SuperLU is over 100 times slower. On an
    organ-scale window (10.6k vertices, W=5, 152k unknowns, the estimator's tolerance 0.1) PCG
    needs 1-3 iterations, and one state's factorisation (30k dofs: 0.26 s with CHOLMOD's BLAS
    on MKL, 0.45 s on single-threaded OpenBLAS, blas.py) would cost a third of an update, so
    a state that joins the window borrows the newest factor (that of the state before it, or
    the one that state borrowed) instead of making its own: consecutive states' blocks differ
    by what one step moved and saw. With it, PCG needs 2-3 iterations there, and updates
    take 0.7 of the time with the same LM iterations and vertex RMSE. When PCG misses the
    tolerance within BORROWED_ITERATIONS, the newest borrowing state gets a factor of its own
    (lent to the next state when it is the newest), the others keep borrowing until a further
    miss: a borrowed factor serves while it is good enough, however old, and a miss costs one
    factorisation (in a replay of the organ-scale live recording, the 10th update's solves took
    204 ms with one, against 421 ms with one for each of its three borrowing states). Where a
    borrowed factor has drifted (a solve took BESIDE_ITERATIONS), the caller has the newest
    block factored beside it after the update (`refactor_newest_beside`), for the next joining
    state to borrow instead of the old one. Only one joining state borrows: a solver facing a
    window of states without factors factors each (a borrowed factor for a whole window would
    serve none well). Other ways to save factorisations cost more than
    they save: Cholesky for the two newest states and vertex blocks for the rest (some
    updates take 40 or more iterations), x/y/z-separated scalar blocks (a 9 times smaller
    factor, 25-29 iterations); MKL PARDISO's OpenMP threads slow numpy down.
    Blocks whose parts of b are together at most LEFT_OUT_SHARE of the tolerance (times |b|)
    are left out: their part of x is zero and the others are solved on their own rows and
    columns (to KEPT_SHARE of the tolerance); when the whole residual then misses the
    tolerance, PCG goes on over every block from there. In a sliding window the states that
    earlier updates converged carry a part of the gradient 1e-13 to 7e-2 of the newest state's
    (the temporal coupling to it is weak; docs/design-notes.md has the measurements), so a
    solve and the decrement work on two to four states' factors instead of all W (iSAM2's
    "wildfire" threshold does the like for variables whose updates are negligible).
    tolerance: relative residual |b - A x| / |b|; max_iterations: cap (LinearSolveError).
    `reserve` makes a window's factors of a block pattern before any solve (their ordering,
    symbolic analysis and memory), so that solves factor into them numerically only: the first
    touch of fresh pages is slow (an organ-scale factor holds about 130 MB, and factoring into
    fresh memory takes two to three times as long as a refactor), and without them the updates
    that fill the window would pay it. The estimator reserves its window's W at construction.
    The loop is hand-written because scipy's cg cannot report negative curvature, which is
    how an indefinite system is detected (NotPositiveDefiniteError).
    """

    name = "pcg"

    def __init__(self, tolerance: float = 1e-8, max_iterations: int = 1000, preconditioner: str = "auto",
                 refresh_iterations: int = 100, refresh_change: float = 0.05, cholesky_max_block: int = 100_000):
        if preconditioner not in PRECONDITIONERS:
            raise ValueError(f"preconditioner must be one of {PRECONDITIONERS}, got {preconditioner!r}")
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.preconditioner = preconditioner
        self.refresh_iterations = int(refresh_iterations)
        self.refresh_change = float(refresh_change)
        self.cholesky_max_block = int(cholesky_max_block)
        self._block_factors: dict = {}   # key -> _BlockFactor
        self._spare: list = []           # factors not in use (reserved, or left), their symbolic analysis reusable
        self._latest: _BlockFactor | None = None  # the factor last made or borrowed: the one to lend
        self._vertex: dict | None = None  # "vertex": laplacian, eigenvectors, inverse blocks, mean data
        self.factorizations = 0
        self._revision = 0               # counts changes of the preconditioner
        self._preconditioned = None      # (system, revision, b, M^-1 b) of the last `decrement`
        self._prepared = None            # (system, revision) the preconditioner was last made to fit
        self._kept = None                # (system, kept block indices, their restricted system)
        self._beside = None              # the factor `refactor_newest_beside` makes: see there
        self._window = None              # the whole window of the last solve or decrement
        self._most_iterations = 0        # PCG's most iterations in one solve since that was last asked

    def _mode(self, block_size: int) -> str:
        if self.preconditioner != "auto":
            return self.preconditioner
        return "vertex" if block_size > self.cholesky_max_block else "block"

    def reserve(self, pattern: scipy.sparse.csr_matrix, count: int) -> None:
        """Make `count` spare factors of block pattern `pattern` (csr, sorted indices, the whole
        diagonal held): its ordering and symbolic analysis, the numeric factorisation left to the
        first block it serves (`_factor`), so that a node's start-up does not factor placeholder
        values; nothing when the "vertex" preconditioner serves blocks of its size."""
        if count < 1 or self._mode(pattern.shape[0]) != "block":
            return
        identity = np.zeros(pattern.nnz)
        identity[diagonal_positions(pattern)] = 1.0
        first = SparseCholesky(scipy.sparse.csr_matrix((identity, pattern.indices, pattern.indptr), shape=pattern.shape),
                               node_size=3, numeric=False)
        self._spare.extend([first] + [first.sibling(None) for _ in range(count - 1)])

    def state_factor(self, key):
        """The factor serving state `key` ("block" preconditioner): its own, or the one it
        borrows from an earlier state; None without one."""
        cached = self._block_factors.get(key)
        return None if cached is None else cached.factor

    def refactor_newest_beside(self) -> SparseCholesky | None:
        """A factor of the newest block of the last window solved (the whole window LM handed
        over, whatever blocks its solve kept), made on the background thread
        (SparseCholesky.refactor_beside) while the caller waits for its next cloud, when
        the newest state borrows and a solve since the last call took BESIDE_ITERATIONS PCG
        iterations or more (the borrowed factor drifted): at the next solve or decrement it
        replaces that state's borrowed factor (`_install_beside`), and the state that joins then
        borrows it. Without it a joining state borrows a factor made however many updates ago,
        and PCG's iterations grow with the drift until a miss factors in the update (in a replay
        of the organ-scale live recording, 2-3 iterations per solve at the second update, 6-9 at
        the ninth and tenth, and a factorisation of 0.2 s in the tenth). The factor is made from
        the block's values at the end of this update, whoever runs it and however long it
        takes, so the estimates do not depend on timing (the next solve waits for it: with an
        update time budget, that wait counts in it); it goes into a spare factor (reserved, or
        left by a state), and nothing is started without one. Returns the factor, or None."""
        system = self._window
        if system is None or self._beside is not None:
            return None
        drifted, self._most_iterations = self._most_iterations >= BESIDE_ITERATIONS, 0
        if not drifted:
            return None
        t = len(system.keys) - 1
        key = system.keys[t]
        cached = self._block_factors.get(key)
        if self._mode(system.block_size) != "block" or cached is None or not cached.borrowed:
            return None
        factor = next((spare for spare in self._spare if spare.same_pattern(system.pattern)), None)
        if factor is None:
            return None
        data = system.block_data(t)
        try:
            done = factor.refactor_beside(data)
        except NotPositiveDefiniteError:
            return None
        self._spare.remove(factor)
        self.factorizations += 1
        self._beside = (key, _BlockFactor(factor, data, system.diagonal_index, system.revisions[t]), done)
        return factor

    def _install_beside(self) -> None:
        """Put the factor `refactor_newest_beside` made (waiting for it) in place of its state's
        borrowed one, as the factor to lend; a spare again where it failed (not positive
        definite, or out of memory: the solves go on with the borrowed one), or its state left
        the window or got a factor of its own meanwhile."""
        beside, self._beside = self._beside, None
        if beside is None:
            return
        key, fresh, done = beside
        try:
            done.result()
        except (NotPositiveDefiniteError, MemoryError):
            self._spare.append(fresh.factor)
            return
        cached = self._block_factors.get(key)
        if cached is None or not cached.borrowed:
            self._spare.append(fresh.factor)
            return
        self._release(key)
        # Judged, like the borrowed factor it replaces, by PCG's iterations (_solve_to).
        self._block_factors[key] = self._latest = fresh.lent()
        self._revision += 1

    @staticmethod
    def _change(data: np.ndarray, reference: np.ndarray) -> float:
        if reference.shape != data.shape:
            return np.inf
        return float(np.linalg.norm(data - reference) / max(np.linalg.norm(reference), 1e-300))

    def _factor(self, data: np.ndarray, like: scipy.sparse.csr_matrix) -> SparseCholesky:
        """Factor of the matrix with values `data` on `like`'s pattern; reuses the symbolic
        analysis of a spare factor (reserved, or a state's that left the window) when the
        pattern matches, else the pattern work and ordering of a factor in use
        (`SparseCholesky.sibling`)."""
        self.factorizations += 1
        while self._spare:
            factor = self._spare.pop()
            if factor.same_pattern(like):
                try:
                    factor.refactor(data)
                except NotPositiveDefiniteError:
                    self._spare.append(factor)
                    raise
                return factor
        for cached in self._block_factors.values():
            if cached.factor.same_pattern(like):
                return cached.factor.sibling(data)
        return SparseCholesky(scipy.sparse.csr_matrix((data, like.indices, like.indptr), shape=like.shape), node_size=3)

    # ------------------------------------------------------------------ preparation
    def _mean_block_data(self, system: WindowSystem) -> np.ndarray:
        mean = np.mean([system.block_data(t) for t in range(len(system.keys))], axis=0)
        mean[system.diagonal_index] -= float(np.mean(system.coupling_diagonal))
        return mean

    def _prepare(self, system: WindowSystem, mode: str, force: bool) -> None:
        """Make the preconditioner fit `system`: factors refreshed where they drifted (all with
        `force`). Nothing to check for the system it was last made to fit, unchanged since
        (Levenberg-Marquardt's decrement test and the step after it share one system)."""
        prepared = self._prepared
        if not force and prepared is not None and prepared[0] is system and prepared[1] == self._revision:
            return
        self._refresh(system, mode, force)
        self._prepared = (system, self._revision)

    def _in_use(self, factor: SparseCholesky) -> bool:
        return any(cached.factor is factor for cached in self._block_factors.values())

    def _release(self, key) -> None:
        """Drop state `key`'s factor; it becomes a spare unless another state borrowed it."""
        factor = self._block_factors.pop(key).factor
        self._revision += 1  # a preconditioner without this block's factor is another one
        if not self._in_use(factor):
            self._spare.append(factor)

    def _evict(self, window: WindowSystem) -> None:
        """Factors of states that left the window become spares (those still borrowed stay)."""
        for key in list(self._block_factors):
            if key not in window.keys:
                self._release(key)

    def _solved_part(self, window: WindowSystem, b: np.ndarray) -> tuple[WindowSystem, np.ndarray, np.ndarray | None]:
        """(system, right-hand side, kept block indices or None for all) of a solve for b on
        `window`: the blocks whose parts of b are together at most LEFT_OUT_SHARE of the
        tolerance are left out. One restricted system per (window, kept blocks), so the
        decrement and the step after it share it."""
        squared = np.sum(window.split(b) ** 2, axis=1)
        order = np.argsort(squared, kind="stable")
        left_out = np.cumsum(squared[order]) <= (LEFT_OUT_SHARE * self.tolerance) ** 2 * squared.sum()
        if not left_out.any() or left_out.all():
            return window, b, None
        kept = np.sort(order[~left_out])
        cached = self._kept
        if cached is None or cached[0] is not window or not np.array_equal(cached[1], kept):
            cached = self._kept = (window, kept, window.restricted(kept))
        return cached[2], window.split(b)[kept].reshape(-1), kept

    def _lender(self, system: WindowSystem) -> _BlockFactor | None:
        """The factor a state without one borrows: the latest, when exactly one state of
        `system` has none (a state joined the window) and that factor is still in use."""
        latest = self._latest
        if latest is None or not self._in_use(latest.factor) or not latest.factor.same_pattern(system.pattern):
            return None
        if sum(key not in self._block_factors for key in system.keys) != 1:
            return None
        return latest

    def _outdated(self, cached: _BlockFactor, system: WindowSystem, t: int, scale: float) -> bool:
        """Whether block t, `scale` times `cached`'s values give or take its distance, needs a
        factor of its own instead: an own factor that drifted beyond refresh_change (a borrowed
        one is judged by PCG's iterations, `_own_factor_for_newest_borrower`)."""
        return not cached.borrowed and cached.distance(system, t, scale) > self.refresh_change

    def _own_factor_for_newest_borrower(self, system: WindowSystem) -> None:
        """PCG missed the tolerance with borrowed factors: the newest state that borrows gets a
        factor of its own, which the next state joining borrows when it is the window's newest.
        The other borrowing states keep theirs (their parts of a step are the small ones), so
        that a miss costs one factorisation, not one per borrowing state; a further miss gives
        the next one its own (`_solve_to`)."""
        t = max(t for t, key in enumerate(system.keys) if self._block_factors[key].borrowed)
        self._release(system.keys[t])
        own = self._own_factor(system, t)
        if t == len(system.keys) - 1:  # the newest state's: the one a joining state borrows
            self._latest = own

    def _own_factor(self, system: WindowSystem, t: int) -> _BlockFactor:
        """A factor of block t of `system`, made and kept as its state's own."""
        data = system.block_data(t)
        own = self._block_factors[system.keys[t]] = _BlockFactor(
            self._factor(data, system.pattern), data, system.diagonal_index, system.revisions[t])
        self._revision += 1
        return own

    def _refresh(self, system: WindowSystem, mode: str, force: bool) -> None:
        """Factors that fit `system`: a joining state borrows (see the class doc), a factor of
        its own is made where a block has none or drifted beyond refresh_change; with `force`,
        for every block."""
        if mode == "block":
            lender = None if force else self._lender(system)
            for t, key in enumerate(system.keys):
                cached = self._block_factors.get(key)
                if cached is None and lender is not None:
                    cached = self._block_factors[key] = self._latest = lender.lent()
                    self._revision += 1
                if cached is not None:
                    scale = cached.scale(system, t)
                    if force or self._outdated(cached, system, t, scale):
                        self._release(key)
                        cached = None
                if cached is None:
                    cached = self._latest = self._own_factor(system, t)
                    scale = 1.0
                if cached.multiple != scale:
                    cached.multiple = scale
                    self._revision += 1
            return
        laplacian = system.time_laplacian()
        mean = self._mean_block_data(system)
        cached = self._vertex
        if (not force and cached is not None and cached["laplacian"].shape == laplacian.shape
                and np.allclose(cached["laplacian"], laplacian, rtol=1e-12, atol=0.0)
                and self._change(mean, cached["mean"]) <= self.refresh_change):
            return
        eigenvalues, eigenvectors = np.linalg.eigh(laplacian)
        vertex_blocks = system.vertex_blocks(mean)  # (V, 3, 3)
        shifted = vertex_blocks[None] + eigenvalues[:, None, None, None] * np.eye(3)
        if not np.all(np.linalg.eigvalsh(shifted) > 0.0):
            raise NotPositiveDefiniteError("a vertex block of the preconditioner is not positive definite")
        inverses = np.linalg.inv(shifted)  # (W, V, 3, 3)
        self._revision += 1
        self._vertex = dict(laplacian=laplacian, eigenvectors=eigenvectors, inverses=inverses, mean=mean)

    # ------------------------------------------------------------------ application
    def _precondition(self, system: WindowSystem, mode: str, residual: np.ndarray) -> np.ndarray:
        parts = residual.reshape(len(system.keys), system.block_size)
        if mode == "block":
            # The blocks that share a factor (a state borrowing the latest one, usually the
            # newest two) are solved together, as one solve of several columns.
            sharing: dict[int, tuple[SparseCholesky, list[int]]] = {}
            for t, key in enumerate(system.keys):
                factor = self._block_factors[key].factor
                sharing.setdefault(id(factor), (factor, []))[1].append(t)
            out = np.zeros_like(parts)
            groups = list(sharing.values())
            if len(groups) == 1 or system.block_size < PARALLEL_MIN_SIZE:
                for factor, blocks in groups:
                    out[blocks] = factor.solve(parts[blocks].T).T
            else:
                # Several factors (states with factors of their own): each one's solve is one
                # CHOLMOD call, the calls side by side on the worker threads (from the size at
                # which a solve's columns are split, below which a hand-off costs more).
                chunks = worker_threads.split(groups, len(groups))
                solved = worker_threads.run_parts(_solve_groups, [(chunk, parts) for chunk in chunks])
                for (_, blocks), values in zip(groups, [values for chunk in solved for values in chunk]):
                    out[blocks] = values
            # A factor of R serves the block c R (_BlockFactor.scale): (c R)^-1 = R^-1 / c.
            out /= np.array([self._block_factors[key].multiple for key in system.keys])[:, None]
            return out.reshape(-1)
        eigenvectors = self._vertex["eigenvectors"]
        rotated = eigenvectors.T @ parts
        solved = np.einsum("wvij,wvj->wvi", self._vertex["inverses"], rotated.reshape(len(parts), -1, 3))
        return (eigenvectors @ solved.reshape(rotated.shape)).reshape(-1)

    def solve(self, system, rhs):
        start = time.perf_counter()
        before = self.factorizations
        mode = self._mode(system.block_size)
        self._evict(system)
        self._install_beside()
        self._window = system
        b = np.asarray(rhs, dtype=np.float64)
        target = self.tolerance * float(np.linalg.norm(b))
        kept_system, kept_b, kept = self._solved_part(system, b)
        x, total = np.zeros_like(b), 0
        if kept is not None:
            kept_x, kept_residual, total = self._solve_to(kept_system, mode, kept_b, KEPT_SHARE * target)
            system.split(x)[kept] = kept_x.reshape(len(kept), -1)
            if np.linalg.norm(_whole_residual(system, b, x, kept, kept_residual)) > target:
                x, _, more = self._solve_to(system, mode, b, target, x)
                total += more
        else:
            x, _, total = self._solve_to(system, mode, b, target)
        self._most_iterations = max(self._most_iterations, total)
        stats = SolveStats(f"{self.name}/{mode}", 1e3 * (time.perf_counter() - start), total,
                           self.factorizations - before)
        return x, stats

    def _solve_to(self, system: WindowSystem, mode: str, b: np.ndarray, target: float,
                  x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
        """PCG from x (default 0) until |b - A x| <= target: (x, PCG's residual b - A x,
        iterations). A miss within BORROWED_ITERATIONS with borrowed factors gives the newest
        borrowing state a factor of its own (`_own_factor_for_newest_borrower`), one per miss;
        a miss within refresh_iterations with none borrowed refactors every block once; PCG goes
        on after each."""
        before = self.factorizations
        self._prepare(system, mode, force=False)
        x = np.zeros_like(b) if x is None else x
        total, refreshed = 0, before != self.factorizations
        first = self._known_preconditioned(system, b)
        while True:
            borrowing = mode == "block" and any(self._block_factors[key].borrowed for key in system.keys)
            if refreshed:
                limit = self.max_iterations - total
            else:
                limit = min(BORROWED_ITERATIONS if borrowing else self.refresh_iterations, self.max_iterations - total)
            x, residual, iterations, converged = self._pcg(system, mode, b, x, limit, target, first)
            first = None
            total += iterations
            if converged:
                return x, residual, total
            if refreshed or total >= self.max_iterations:
                raise LinearSolveError(f"PCG did not reach relative residual {self.tolerance:g} in {total} iterations")
            if borrowing:  # the newest borrowing state gets a factor of its own, the others keep theirs
                self._own_factor_for_newest_borrower(system)
            else:
                self._refresh(system, mode, force=True)
                refreshed = True
            self._prepared = (system, self._revision)

    def decrement(self, system, gradient):
        """0.5 g^T M^-1 g with the preconditioner M (cached factors, block Jacobi: exact in each
        state's block, blind to the weak temporal coupling) over the blocks a solve for -g keeps
        (the others' parts of g are below the tolerance: see the class doc): one preconditioner
        application instead of a PCG solve.

        Levenberg-Marquardt solves for the step on the same system with -g when the test fails,
        and PCG's first iteration applies M to that very -g: M^-1 (-g) = -(M^-1 g) exactly in
        floating point (every operation of the triangular solves is odd in its input), so it is
        kept for `solve` (`_known_preconditioned`) while the system and M stay the same."""
        mode = self._mode(system.block_size)
        self._evict(system)
        self._install_beside()
        self._window = system
        system, gradient, _ = self._solved_part(system, np.asarray(gradient, dtype=np.float64))
        self._prepare(system, mode, force=False)
        preconditioned = self._precondition(system, mode, gradient)
        self._preconditioned = (system, self._revision, -gradient, -preconditioned)
        return 0.5 * float(gradient @ preconditioned)

    def _known_preconditioned(self, system: WindowSystem, b: np.ndarray) -> np.ndarray | None:
        """M^-1 b from the last `decrement` when it was for this system, this b and the current M."""
        known = self._preconditioned
        if known is None or known[0] is not system or known[1] != self._revision or not np.array_equal(known[2], b):
            return None
        return known[3]

    def _pcg(self, system: WindowSystem, mode: str, b: np.ndarray, x: np.ndarray, limit: int,
             target: float, first: np.ndarray | None = None):
        """Preconditioned CG from x for at most `limit` iterations, until |b - A x| <= target:
        (x, the residual b - A x as CG updates it, iterations, converged). `first`: M^-1 b when
        it is known (for a cold start, x = 0, only)."""
        if not b.any():
            return np.zeros_like(b), b, 0, True
        cold = not x.any()
        residual = b if cold else b - system.matvec(x)  # a cold start needs no product
        if np.linalg.norm(residual) <= target:
            return x, residual, 0, True
        z = first if cold and first is not None else self._precondition(system, mode, residual)
        direction = z.copy()
        rz = residual @ z
        if not rz > 0.0:
            raise NotPositiveDefiniteError("preconditioner not positive definite")
        for iteration in range(1, limit + 1):
            product = system.matvec(direction)
            curvature = direction @ product
            if not curvature > 0.0:
                raise NotPositiveDefiniteError(f"negative curvature {curvature:.3g} in PCG: system not positive definite")
            step = rz / curvature
            x = x + step * direction
            residual = residual - step * product
            if np.linalg.norm(residual) <= target:
                return x, residual, iteration, True
            z = self._precondition(system, mode, residual)
            rz_new = residual @ z
            direction = z + (rz_new / rz) * direction
            rz = rz_new
        return x, residual, limit, False


def _solve_groups(groups: list, parts: np.ndarray) -> list[np.ndarray]:
    """Each (factor, block indices) group's blocks of `parts` (W, n) solved, in one CHOLMOD call
    per factor (PCGSolver._precondition)."""
    return [factor.solve(parts[blocks].T, split=False).T for factor, blocks in groups]


def _whole_residual(system: WindowSystem, b: np.ndarray, x: np.ndarray, kept: np.ndarray,
                    kept_residual: np.ndarray) -> np.ndarray:
    """b - A x over the whole window for an x that is zero outside the blocks `kept`, from the
    residual of the kept blocks' own system (restricted: the same rows, as x is zero in the
    columns it leaves out): a left-out block's row of A x is its couplings to its neighbours'
    parts of x alone, so no product with the blocks is needed."""
    parts = system.split(x)
    coupled = np.zeros_like(parts)
    system.add_couplings(parts, coupled)
    residual = system.split(b) - coupled
    residual[kept] = kept_residual.reshape(len(kept), -1)
    return residual.reshape(-1)


class FallbackSolver(LinearSolver):
    """Try `solvers` in order; a failure (LinearSolveError, MemoryError) moves to the next and
    is named in the message. NotPositiveDefiniteError propagates (the caller adds damping).
    Direct solvers are skipped above `direct_max_size` unknowns, where one factorisation of a
    whole window takes minutes (a 152k-unknown window: one state alone takes ~12 s)."""

    def __init__(self, solvers, direct_max_size: int = 30000):
        self.solvers = list(solvers)
        self.name = self.solvers[0].name
        self.direct_max_size = int(direct_max_size)

    def solve(self, system, rhs):
        failures = []
        for solver in self.solvers:
            if isinstance(solver, (CholeskySolver, SuperLUSolver)) and system.size > self.direct_max_size:
                failures.append(f"{solver.name} skipped ({system.size} unknowns)")
                continue
            try:
                x, stats = solver.solve(system, rhs)
            except (LinearSolveError, MemoryError) as error:
                failures.append(f"{solver.name} failed ({error})")
                continue
            if failures:
                stats.message = "; ".join(failures) + f"; solved with {solver.name}"
            return x, stats
        raise LinearSolveError("; ".join(failures))

    def decrement(self, system, gradient):
        """PCG's estimate when PCG comes first, else a full solve through the fallbacks."""
        if isinstance(self.solvers[0], PCGSolver):
            return self.solvers[0].decrement(system, gradient)
        return super().decrement(system, gradient)

    def reserve(self, pattern, count):
        """The first solver's reservation (the others serve only when it fails)."""
        self.solvers[0].reserve(pattern, count)

    def state_factor(self, key):
        """The first solver's factor of state `key` (the others serve only when it fails)."""
        return self.solvers[0].state_factor(key)

    def refactor_newest_beside(self):
        """The first solver's (the others serve only when it fails)."""
        return self.solvers[0].refactor_newest_beside()


def make_linear_solver(name: str, fallback: bool = True, **pcg_options) -> LinearSolver:
    """Solver by name ("pcg", "cholesky", "superlu"); with fallback, the others follow it.
    pcg_options go to PCGSolver (tolerance, max_iterations, ...)."""
    factories = {"pcg": lambda: PCGSolver(**pcg_options), "cholesky": CholeskySolver, "superlu": SuperLUSolver}
    if name not in factories:
        raise ValueError(f"linear solver must be one of {LINEAR_SOLVERS}, got {name!r}")
    if not fallback:
        return factories[name]()
    order = [name] + [other for other in ("pcg", "cholesky", "superlu") if other != name]
    return FallbackSolver([factories[other]() for other in order])
