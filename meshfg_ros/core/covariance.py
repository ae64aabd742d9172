"""Per-vertex 3x3 marginal covariance blocks of a sparse Gaussian, and the covariance of the
estimate the estimator publishes.

Marginals. The diagonal 3x3 blocks of H^-1 for a sparse symmetric positive definite information
matrix H over vertex coordinates (x0 y0 z0 x1 ...). Small matrices (up to DENSE_MAX_DOFS) are
inverted densely, exactly. Larger ones are estimated from `samples` draws x = P^T L^-T z,
z ~ N(0, I), of N(0, H^-1) through the sparse Cholesky factor P H P^T = L L^T (CHOLMOD, whose
solves take many right-hand sides at once): each block is the draws' second moment. The estimate
of a vertex's variance trace/3 has a relative standard deviation of sqrt(2 / (3 samples))
(14 % at 32 draws, 7 % in its std); the draws are seeded, so one matrix gives one answer.
Selected inversion (Takahashi's recursion on L) would be exact at about a factorisation's cost,
but neither CHOLMOD through cvxopt nor any kept Python package exposes it.

The published estimate's covariance. The estimator publishes m = Xhat + alpha (X* - Xhat): the
prediction plus the persisting share alpha of the MAP's correction (core/persistence.py). In a
linear-Gaussian model with the prior's information A (the FEM stiffness, weighted by the
simulation sigma), the measurements' information B, the MAP's posterior S = (A + B)^-1, and a
prediction whose real error is N(0, lambda^2 A^-1), the error of m has the covariance

    Sigma = lambda^2 [(1 - beta) S + beta A^-1] + alpha^2 (1 - lambda^2) S B S,   beta = (1 - alpha)^2.

alpha = 1 (the MAP published) and lambda = 1 give S; alpha = 0 (the prediction published) gives
lambda^2 A^-1. The last term is the measurement noise the MAP's gain passes on, which lambda^2 S
counts lambda^2 times instead of once; S B S = S - S A S, and S A S is drawn as S A e with
e ~ N(0, A^-1) through the prior's own factor (made once: A is the prior's information at the
rest shape, which the estimator's prior departs from only by the corotation of its elements).

lambda^2, the prior's real error relative to its model, is learnt from the innovation: the
distances d_k of a cloud's points to the predicted surface, each with the model's variance
lambda^2 n_k^T A^-1 n_k + sigma_m^2 (n_k the predicted surface's normal at the closest point,
A^-1's blocks interpolated over the triangle). `prior_error_scale` solves for the lambda^2 at
which the median of d_k^2 / variance_k is that of chi^2(1), over the points within
INNOVATION_GATE robust spreads of the surface (as the measurement factor gates its points): a
cloud may hold leaks, which lie farther from the surface than the tissue's points. Leaks within
the gate still raise the estimate (a conservative bias: with 20 % leaks spread over 10 spreads,
about 15 %). One cloud's estimate is noisy where the prediction's error is below the
measurement noise (it often reaches the bound 0 there), so the published lambda^2 is the mean of
the recent updates' estimates, each weighted by PRIOR_ERROR_MEMORY times the next one's weight,
and of the model's own lambda^2 = 1, weighted as an estimate made before the first update: the
prediction's error grows as the simulation drifts, and the mean follows within a few updates.
A^-1's blocks at the rest shape are computed once, when the estimator is
made, and scaled with the simulation sigma of each update.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.stats import chi2

from meshfg_ros.core.noise import NotPositiveDefiniteError
from meshfg_ros.core.sparse_cholesky import SparseCholesky

__all__ = ["DENSE_MAX_DOFS", "INNOVATION_GATE", "MARGINAL_SAMPLES", "PRIOR_ERROR_MEMORY", "ForgettingMean", "MarginalCovariance",
           "prior_error_scale", "published_covariance"]

# Up to this many unknowns the marginals are exact (a dense inverse takes a few milliseconds).
DENSE_MAX_DOFS = 600
# Draws per marginal estimate beyond DENSE_MAX_DOFS (see the module doc).
MARGINAL_SAMPLES = 32
# Weight of an update's lambda^2 estimate relative to the next one's (module doc).
PRIOR_ERROR_MEMORY = 0.7
# Points farther from the predicted surface than this many robust spreads 1.4826 median(d) do
# not judge the prediction (estimator.GATE_SIGMAS's gate).
INNOVATION_GATE = 5.0
# The median of chi^2 with one degree of freedom: of d^2 / variance for a normal d.
_CHI2_1_MEDIAN = float(chi2.ppf(0.5, 1))
# Bounds of lambda^2 searched by prior_error_scale (a prior 1000 times too confident or too shy).
_SCALE_RANGE = (1e-6, 1e6)


def _blocks_of_dense(inverse: np.ndarray) -> np.ndarray:
    vertices = inverse.shape[0] // 3
    blocks = inverse.reshape(vertices, 3, vertices, 3)[np.arange(vertices), :, np.arange(vertices), :]
    return 0.5 * (blocks + blocks.transpose(0, 2, 1))


class MarginalCovariance:
    """The diagonal 3x3 blocks of S = H^-1 and of S A S for information matrices H that share
    one sparsity pattern (the estimator's state block) and a fixed prior information A on it
    (module doc). The ordering and symbolic analysis of H's factor are made at the first call
    and kept; A's factor is made once. Raises NotPositiveDefiniteError for a matrix that is not SPD."""

    def __init__(self, prior_information: scipy.sparse.csr_matrix | None = None, samples: int = MARGINAL_SAMPLES):
        self.samples = int(samples)
        self.prior_information = None if prior_information is None else scipy.sparse.csr_matrix(prior_information)
        self._prior_factor: SparseCholesky | None = None
        self._factor: SparseCholesky | None = None

    def prior_blocks(self, samples: int) -> np.ndarray:
        """(V, 3, 3) blocks of A^-1 (exact up to DENSE_MAX_DOFS, else from `samples` draws)."""
        size = self.prior_information.shape[0]
        if size <= DENSE_MAX_DOFS:
            return _blocks_of_dense(_dense_inverse(self.prior_information))
        draws = np.random.default_rng(0).standard_normal((size, samples))
        return _second_moment(self._prior().sample(draws))

    def _prior(self) -> SparseCholesky:
        if self._prior_factor is None:
            self._prior_factor = SparseCholesky(self.prior_information, node_size=3)
        return self._prior_factor

    def blocks(self, information: scipy.sparse.csr_matrix, prior_scale: float = 1.0,
               seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
        """(S, S A' S) blocks (V, 3, 3) for H = `information`, A' = prior_scale * A (None
        without a prior); exact up to DENSE_MAX_DOFS, else sampled (seeded by `seed`)."""
        matrix = scipy.sparse.csr_matrix(information, dtype=np.float64)
        matrix.sort_indices()
        size = matrix.shape[0]
        if size % 3:
            raise ValueError(f"a matrix over vertex coordinates has a multiple of 3 rows, got {size}")
        prior = self.prior_information
        if size <= DENSE_MAX_DOFS:
            inverse = _dense_inverse(matrix)
            through_prior = None if prior is None else prior_scale * inverse @ (prior @ inverse)
            return _blocks_of_dense(inverse), None if prior is None else _blocks_of_dense(through_prior)
        if self._factor is None or not self._factor.same_pattern(matrix):
            self._factor = SparseCholesky(matrix, node_size=3)
        else:
            self._factor.refactor(matrix.data)
        rng = np.random.default_rng(seed)
        posterior = _second_moment(self._factor.sample(rng.standard_normal((size, self.samples))))
        if prior is None:
            return posterior, None
        # A' e with e ~ N(0, A'^-1) is N(0, A'); S of it is N(0, S A' S).
        prior_draws = self._prior().sample(rng.standard_normal((size, self.samples)))
        through_prior = self._factor.solve(np.sqrt(prior_scale) * (prior @ prior_draws))
        return posterior, _second_moment(through_prior)


def _dense_inverse(matrix) -> np.ndarray:
    try:
        factor = scipy.linalg.cho_factor(scipy.sparse.csr_matrix(matrix).toarray(), lower=True)
    except np.linalg.LinAlgError as error:
        raise NotPositiveDefiniteError(f"Cholesky failed: {error}") from None
    return scipy.linalg.cho_solve(factor, np.eye(matrix.shape[0]))


def _second_moment(draws: np.ndarray) -> np.ndarray:
    """(V, 3, 3) mean outer products of the draws (3V, k) per vertex."""
    x = draws.reshape(draws.shape[0] // 3, 3, draws.shape[1])
    return np.einsum("vis,vjs->vij", x, x) / draws.shape[1]


class ForgettingMean:
    """The mean of `initial` (weight 1) and the values added, each weighted by `memory` times
    the next one's weight: it starts at `initial` and follows the values within a few additions."""

    def __init__(self, memory: float, initial: float):
        if not 0.0 <= memory < 1.0:
            raise ValueError(f"memory must lie in [0, 1), got {memory}")
        self.memory = float(memory)
        self.total = float(initial)
        self.weight = 1.0

    def add(self, value: float) -> float:
        """Add `value`; returns the mean."""
        self.total = self.memory * self.total + float(value)
        self.weight = self.memory * self.weight + 1.0
        return self.total / self.weight


def prior_error_scale(distances: np.ndarray, prior_variance: np.ndarray, measurement_sigma: float) -> float | None:
    """lambda^2 (see the module doc) from a cloud's distances d_k (K,) to the predicted surface,
    the model's prior variance along each point's normal (K,) and the measurement sigma; None
    when fewer than 30 points have a finite distance and a positive variance. Bisection in
    log lambda^2 over _SCALE_RANGE: the median of d^2 / (lambda^2 p + sigma^2) falls as lambda^2 grows."""
    distances = np.asarray(distances, dtype=np.float64)
    prior_variance = np.asarray(prior_variance, dtype=np.float64)
    usable = np.isfinite(distances) & np.isfinite(prior_variance) & (prior_variance > 0.0)
    if np.count_nonzero(usable) < 30:
        return None
    usable &= distances <= INNOVATION_GATE * 1.4826 * float(np.median(distances[usable]))
    squared, variance, noise = distances[usable] ** 2, prior_variance[usable], float(measurement_sigma) ** 2

    def excess(log_scale: float) -> float:
        return float(np.median(squared / (np.exp(log_scale) * variance + noise))) - _CHI2_1_MEDIAN

    low, high = np.log(_SCALE_RANGE[0]), np.log(_SCALE_RANGE[1])
    if excess(low) <= 0.0:
        return _SCALE_RANGE[0]
    if excess(high) >= 0.0:
        return _SCALE_RANGE[1]
    for _ in range(40):  # 2.5e-11 of the log range: far below the estimate's own spread
        middle = 0.5 * (low + high)
        low, high = (middle, high) if excess(middle) > 0.0 else (low, middle)
    return float(np.exp(0.5 * (low + high)))


def published_covariance(posterior: np.ndarray, through_prior: np.ndarray | None, prior: np.ndarray | None,
                         alpha: float, scale: float) -> np.ndarray:
    """(V, 3, 3) covariance of the published estimate (module doc) from the blocks (V, 3, 3) of
    the posterior S, of S A S (`through_prior`) and of the prior A^-1, the persisting share
    alpha in [0, 1] and lambda^2 = scale. Without a prior (no physics prior in the
    configuration) the posterior as it is."""
    if prior is None or through_prior is None:
        return posterior
    beta = (1.0 - alpha) ** 2
    # S B S and (1 - beta) S + beta A^-1 - alpha^2 S B S (at least S A S) are positive
    # semidefinite; sampled, their blocks may not be, and are clipped to it.
    noise_part = _semidefinite(posterior - through_prior)
    model_part = _semidefinite((1.0 - beta) * posterior + beta * prior - alpha**2 * noise_part)
    return scale * model_part + alpha**2 * noise_part


def _semidefinite(blocks: np.ndarray) -> np.ndarray:
    """(V, 3, 3) symmetric blocks with negative eigenvalues set to zero."""
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (blocks + blocks.transpose(0, 2, 1)))
    return np.einsum("vij,vj,vkj->vik", eigenvectors, np.clip(eigenvalues, 0.0, None), eigenvectors)
