"""Per-vertex 3x3 marginal covariance blocks of a sparse Gaussian, and the covariance of the
estimate the estimator publishes.

Marginals. The diagonal 3x3 blocks of H^-1 for a sparse symmetric positive definite information
matrix H over vertex coordinates (x0 y0 z0 x1 ...). Small matrices (up to DENSE_MAX_DOFS) are
inverted densely, exactly. Larger ones are estimated from `samples` draws x = P^T L^-T z,
z ~ N(0, I), of N(0, H^-1) through the sparse Cholesky factor P H P^T = L L^T (CHOLMOD, whose
solves take many right-hand sides at once): each block is the draws' second moment. The estimate
of a vertex's variance trace/3 has a relative standard deviation of sqrt(2 / (3 samples))
(20 % at 16 draws, 10 % in its std); the draws are seeded, so one matrix gives one answer.
Selected inversion (Takahashi's recursion on L) would be exact at about a factorisation's cost,
but neither CHOLMOD through cvxopt nor any kept Python package exposes it.

The published estimate's covariance. The estimator publishes m = Xhat + alpha (X* - Xhat): the
prediction plus the persisting share alpha of the MAP's correction (core/estimation/persistence.py). In a
linear-Gaussian model with the prior's information A (the FEM stiffness, weighted by the
simulation sigma), the measurements' information B, the MAP's posterior S = (A + B)^-1, and a
prediction whose real error is N(0, lambda^2 A^-1), the error of m has the covariance

    Sigma = lambda^2 [(1 - beta) S + beta A^-1] + alpha^2 (1 - lambda^2) S B S,   beta = (1 - alpha)^2.

alpha = 1 (the MAP published) and lambda = 1 give S; alpha = 0 (the prediction published) gives
lambda^2 A^-1. The last term is the measurement noise the MAP's gain passes on, which
lambda^2 S counts lambda^2 times instead of once. It is bounded, 0 <= S B S <= S, and
`published_covariance` takes the bound that keeps Sigma at or above the model's: 0 when
lambda > 1, S when lambda < 1. Drawing S B S itself (as S - S A S, with draws through the
prior's factor) would triple the draws' cost for a few per cent of NEES (docs/design-notes.md,
"Published uncertainty").

The factor. LM's linear solver already holds a Cholesky factor for the newest state's block
(PCGSolver's block preconditioner: the state's own, refreshed when its block drifts by 5 % from
a multiple of the values it was made from, damping included, or one it borrows from an earlier
state, 1-25 % off on the bench's boxes); the draws go through it, and the block is factored
here only where the solver holds none. A factor of M draws N(0, M^-1); where M is close to c H
(a factor made at an earlier noise estimate: the whole block scales with 1 / sigma_m^2),
E[x^T H x] = n / c, so the draws are rescaled by sqrt(n / mean x^T H x), one product with H.
Rescaled draws through a borrowed factor give the NEES of a fresh factor's within a few per
cent (docs/design-notes.md), and a fresh factor would cost about 0.1 s of an update at 5,000
vertices and 0.3 s at 10,000.
The next state borrows the same factor while its block stays close, or the one the solver
makes of this state's block beside the caller when the borrowed one drifted
(PCGSolver.refactor_newest_beside), so the draws of the next update are made through it beside
the caller as soon as this one's are taken (`MarginalCovariance.prepare`, queued behind that
factorisation),
while the estimator waits for its next cloud: at organ scale the covariance then takes about
17 ms of an update instead of 40-45 (the draws' solves). Prepared or drawn in the update, the
draws are one CHOLMOD call, so that both give the same numbers; drawn in the update, they do
not queue behind other work beside the loop (the simulator's refactor, in one process).

lambda^2, the prior's real error relative to its model, is learnt from the innovation: the
distances d_k of a cloud's points to the predicted surface, each with the model's variance
lambda^2 n_k^T A^-1 n_k + sigma_m^2 (n_k the predicted surface's normal at the closest point,
A^-1's blocks interpolated over the triangle). `prior_error_scale` gives the lambda^2 at which
the median of d_k^2 / variance_k is that of chi^2(1), c: point k's ratio is above c exactly when
lambda^2 is below s_k = (d_k^2 / c - sigma_m^2) / p_k, so that lambda^2 is the median of the s_k,
in closed form. The prediction's error is not lambda^2 A^-1 everywhere, though: a drift far from
the fixed boundary (the airway's sticky tool) shows in the few points where the prior is soft,
while most points see the noise alone, and the median follows those (on the airway, mean NEES
11-27 on seeds 0-2). The published lambda^2 is therefore the larger of the median and a second estimate
that weighs the soft points: the slope of the points' d_k^2 / c over p_k (the medians of
PRIOR_VARIANCE_BINS bins of equal count, a least-squares line through them; its intercept takes
the noise's variance, so the estimated sigma_m does not enter it), less two of its standard
errors, so that only a slope the clouds clearly show counts. Where the error follows the
prior's shape the median is the larger (the slope's margin); where the error is concentrated
on the soft parts the slope is. It guards the hidden, soft parts, where an overconfident std
misleads a planner most. Only the points within the caller's gate (robust spreads of the
distances, as the measurement factor gates its points) count: a cloud may hold leaks, which lie
farther from the surface than the tissue's points. Leaks within the gate still raise the
estimate (a conservative bias: with 20 % leaks spread over 10 spreads, about 15 %).
The median estimate subtracts the noise, which is most of the distances' spread: at lambda^2 = 1
the prior's variance along the normal (the median over a cloud's points) is a thirteenth to a
nineteenth of the points' noise variance on six of the accuracy suite's nine scenes, so a few
per cent of error in the noise estimate is an error of one in lambda^2; the slope needs prior variances that spread. A third
estimate holds no noise term: the prediction's error persists from cloud to cloud, the noise
does not, so the product of two successive clouds' mean signed distances over a triangle of the
predicted surface has the squared normal error there as its mean, whatever the noise
(`persistent_offset_scale`: summed over the triangles both clouds saw, over the prior's variance
along the normal there). An update's estimate is the largest of the three, never this one
alone: the normal part is not all of the error (the sheared cube's error is 20 times its normal part,
where the prior's shape says 4), and leaks that recur at the same places raise it (its gate is
therefore tighter, PERSISTENT_OFFSET_GATE). It raises the estimate where the drift shows along
the normals but the noise estimate hides it (slab-inclusion). One cloud's estimate is noisy
where the prediction's error is below the measurement noise (it often reaches the bound 0
there), so lambda^2 is learnt as the mean of the recent updates' estimates, each
weighted by PRIOR_ERROR_MEMORY times the next one's weight, and of the model's own lambda^2 = 1,
weighted as an estimate made before the first update: the prediction's error grows as the
simulation drifts, and the mean follows within a few updates. Where the estimator estimates the
noise from the clouds, the first cloud adds no estimate: no earlier cloud has estimated the noise
its distances would be held against, and the nominal sigma, off by tens of per cent, puts that
estimate far above the prediction's error (liver-push, seed 1: 3.5 where the prediction's error
called for 0.004; `SlidingWindowEstimator.prepare`). The published lambda^2 is that
mean plus PRIOR_ERROR_STANDARD_ERRORS of its standard error (the estimates' scatter about it):
where successive clouds' estimates scatter (the airway's slope estimate between 0.9 and 33 over
ten clouds, while the error it should size grows steadily), a mean the scatter leaves low would
publish an overconfident std, which misleads a planner more than a conservative one
(docs/design-notes.md, "Published uncertainty"). A^-1's blocks at the rest shape
are drawn once per estimator (again on the cut mesh after a cut), beside its set-up where there
are two worker threads (estimator.py, `unit_prior_covariance`), and scaled with the simulation
sigma of each update.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.special import gammaincinv, gammaln, xlogy

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.inputs.input_checks import innovation_spread
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky
from meshfg_ros.core.estimation.weights import MIN_POINTS

__all__ = ["DENSE_MAX_DOFS", "MARGINAL_SAMPLES", "MIN_SHARED_TRIANGLES", "PERSISTENT_OFFSET_GATE", "PRIOR_ERROR_MEMORY",
           "PRIOR_ERROR_STANDARD_ERRORS", "PRIOR_VARIANCE_BINS", "SLOPE_STANDARD_ERRORS", "ForgettingMean",
           "MarginalCovariance", "TriangleOffsets", "chi_squared_quantile", "clipped_inverse", "persistent_offset_scale",
           "prior_error_scale", "published_covariance", "triangle_offsets"]

# Up to this many unknowns the marginals are exact (a dense inverse takes a few milliseconds).
DENSE_MAX_DOFS = 600
# Draws per marginal estimate beyond DENSE_MAX_DOFS (see the module doc).
MARGINAL_SAMPLES = 16
# The slope estimate of lambda^2 (module doc): bins of the points' prior variance, and the
# standard errors taken off the slope.
PRIOR_VARIANCE_BINS = 8
SLOPE_STANDARD_ERRORS = 2.0
# Weight of an update's lambda^2 estimate relative to the next one's, and the standard errors of
# their mean added to it in the published lambda^2 (module doc).
PRIOR_ERROR_MEMORY = 0.7
PRIOR_ERROR_STANDARD_ERRORS = 1.0
# The persistent-offset estimate of lambda^2 (module doc): its gate, in robust spreads of the
# signed distances (leaks recur at the same places and pass a wider one: docs/design-notes.md),
# and the fewest triangles two clouds must share for it.
PERSISTENT_OFFSET_GATE = 2.5
MIN_SHARED_TRIANGLES = 10


def chi_squared_quantile(probability, dof: float):
    """x with P(chi^2_dof <= x) = probability: scipy.stats.chi2.ppf, through the scipy.special
    function it calls (the same numbers), since importing scipy.stats takes about half a second
    of every node's and command's start-up."""
    return 2.0 * gammaincinv(dof / 2.0, probability)


def _chi_squared_density(x, dof: float):
    """The density of chi^2_dof at x > 0: scipy.stats.chi2.pdf, as chi_squared_quantile says why."""
    return np.exp(xlogy(dof / 2.0 - 1.0, x) - x / 2.0 - gammaln(dof / 2.0) - np.log(2.0) * dof / 2.0)


# The median of chi^2 with one degree of freedom: of d^2 / variance for a normal d.
_CHI2_1_MEDIAN = float(chi_squared_quantile(0.5, 1))
# The standard error of the median of n values v x / c (x ~ chi^2(1)) is _MEDIAN_ERROR v / sqrt(n):
# 1 / (2 sqrt(n) f(v)), the density of v x / c at its median v being c pdf_chi2(c) / v.
_MEDIAN_ERROR = 1.0 / (2.0 * _CHI2_1_MEDIAN * float(_chi_squared_density(_CHI2_1_MEDIAN, 1)))
# Bounds of lambda^2 (a prior's std 1000 times too small or too large).
_SCALE_RANGE = (1e-6, 1e6)


def _blocks_of_dense(inverse: np.ndarray) -> np.ndarray:
    vertices = inverse.shape[0] // 3
    blocks = inverse.reshape(vertices, 3, vertices, 3)[np.arange(vertices), :, np.arange(vertices), :]
    return 0.5 * (blocks + blocks.transpose(0, 2, 1))


class MarginalCovariance:
    """The diagonal 3x3 blocks of H^-1 for information matrices H that share one sparsity
    pattern (the estimator's state block): the ordering and symbolic analysis of a factor it
    makes are kept for the next. Raises NotPositiveDefiniteError for a matrix that is not SPD."""

    def __init__(self, samples: int = MARGINAL_SAMPLES):
        self.samples = int(samples)
        self._factor: SparseCholesky | None = None
        # (factor, its revision, seed, the draws running beside the caller): see `prepare`
        self._prepared: tuple | None = None

    def prepare(self, factor: SparseCholesky | None, seed: int) -> None:
        """Start the draws that `blocks` will take through `factor` for `seed`, on a thread of
        their own (core/worker_threads.py, with more than one worker thread), so that they run
        while the caller waits for its next input: the estimator prepares the next update's
        draws through the factor the next state will borrow (the newest state's, or the one its
        solver makes beside the caller, whose factorisation these draws queue behind). `blocks`
        uses them only if they were made for its factor, unchanged since
        (SparseCholesky.revision), and its seed; a refactor waits for them to end."""
        self._prepared = None
        if factor is None or factor.size <= DENSE_MAX_DOFS or worker_threads.count() < 2:  # nothing to gain
            return
        self._prepared = (factor, factor.revision, seed, worker_threads.start_background(self._draw_through, factor, seed))

    def blocks(self, information: scipy.sparse.csr_matrix, seed: int = 0,
               factor: SparseCholesky | None = None) -> np.ndarray:
        """(V, 3, 3) blocks of H^-1, H = `information`: exact up to DENSE_MAX_DOFS, else from
        draws seeded by `seed`, through `factor` when given (of H, or of a matrix close to it
        on H's pattern: its draws are rescaled to H, module doc), else through a factor of H
        made here."""
        matrix = scipy.sparse.csr_matrix(information, dtype=np.float64)
        matrix.sort_indices()
        size = matrix.shape[0]
        if size % 3:
            raise ValueError(f"a matrix over vertex coordinates has a multiple of 3 rows, got {size}")
        if size <= DENSE_MAX_DOFS:
            return _blocks_of_dense(_dense_inverse(matrix))
        if factor is None or not factor.same_pattern(matrix):
            if self._factor is None or not self._factor.same_pattern(matrix):
                self._factor = SparseCholesky(matrix, node_size=3)
            else:
                self._factor.refactor(matrix.data)
            factor = self._factor
        draws = self._draws(factor, seed)
        if factor is not self._factor:
            # A factor of M = c H draws N(0, H^-1 / c), and E[x^T H x] = size / c: rescaled by it.
            draws *= np.sqrt(size * self.samples / np.einsum("is,is->", draws, matrix @ draws))
        vertices = draws.reshape(size // 3, 3, self.samples)
        return np.einsum("vis,vjs->vij", vertices, vertices) / self.samples

    def _draws(self, factor: SparseCholesky, seed: int) -> np.ndarray:
        """x = P^T L^-T z (size, samples) through `factor`, z ~ N(0, I) seeded by `seed`: the
        prepared ones where they match (`prepare`; others are cancelled, or left with whatever
        they met), else drawn now, on this thread, the same way (_draw_through)."""
        prepared, self._prepared = self._prepared, None
        if prepared is not None:
            prepared_factor, revision, prepared_seed, draws = prepared
            if prepared_factor is not factor or prepared_seed != seed:
                draws.cancel()
            else:
                try:
                    result = draws.result()
                except NotPositiveDefiniteError:  # through a failed factor that may be refactored since
                    result = None
                # The revision read once they ended: a refactor waits for them.
                if result is not None and revision == factor.revision:
                    return result
        return self._draw_through(factor, seed)

    def _draw_through(self, factor: SparseCholesky, seed: int) -> np.ndarray:
        """The draws in one CHOLMOD call (not split over the worker threads), so that they are
        the same numbers whichever thread makes them."""
        normal = np.random.default_rng(seed).standard_normal((factor.size, self.samples))
        with factor.reading():
            return factor.back_solve(normal, split=False)


def _dense_inverse(matrix: scipy.sparse.csr_matrix) -> np.ndarray:
    try:
        factor = scipy.linalg.cho_factor(matrix.toarray(), lower=True)
    except np.linalg.LinAlgError as error:
        raise NotPositiveDefiniteError(f"Cholesky failed: {error}") from None
    return scipy.linalg.cho_solve(factor, np.eye(matrix.shape[0]))


class ForgettingMean:
    """The mean of `initial` (weight 1) and the values added, each weighted by `memory` times
    the next one's weight: it starts at `initial` and follows the values within a few additions;
    and its standard error, from the values' weighted scatter about it."""

    def __init__(self, memory: float, initial: float):
        if not 0.0 <= memory < 1.0:
            raise ValueError(f"memory must lie in [0, 1), got {memory}")
        self.memory = float(memory)
        self.total = float(initial)
        self.squares = float(initial) ** 2
        self.weight = 1.0
        self.weight_squares = 1.0

    def add(self, value: float) -> float:
        """Add `value`; returns the mean."""
        self.total = self.memory * self.total + float(value)
        self.squares = self.memory * self.squares + float(value) ** 2
        self.weight = self.memory * self.weight + 1.0
        self.weight_squares = self.memory**2 * self.weight_squares + 1.0
        return self.total / self.weight

    def standard_error(self) -> float:
        """The mean's standard error: the values' weighted variance about it over their
        effective count (sum of the weights)^2 / (sum of their squares), as for independent
        values."""
        mean = self.total / self.weight
        variance = max(self.squares / self.weight - mean**2, 0.0)
        return float(np.sqrt(variance * self.weight_squares / self.weight**2))


def prior_error_scale(distances: np.ndarray, prior_variance: np.ndarray, measurement_sigma: float,
                      gate_spreads: float, persistent: float | None = None) -> float | None:
    """lambda^2 (see the module doc) from a cloud's distances d_k (K,) to the predicted surface,
    the model's prior variance along each point's normal (K,), the measurement sigma, and the gate
    in robust spreads of the distances: the largest of the median estimate, the slope estimate
    (`_slope_estimate`) and `persistent` (`persistent_offset_scale`, where there is one); None
    when fewer than MIN_POINTS points have a finite distance and a positive variance."""
    distances = np.asarray(distances, dtype=np.float64)
    prior_variance = np.asarray(prior_variance, dtype=np.float64)
    usable = np.isfinite(distances) & np.isfinite(prior_variance) & (prior_variance > 0.0)
    if np.count_nonzero(usable) < MIN_POINTS:
        return None
    usable &= distances <= gate_spreads * innovation_spread(distances[usable])
    squared, variance = distances[usable] ** 2 / _CHI2_1_MEDIAN, prior_variance[usable]
    median = float(np.median((squared - float(measurement_sigma) ** 2) / variance))
    estimates = [median, _slope_estimate(squared, variance)] + ([] if persistent is None else [float(persistent)])
    return float(np.clip(max(estimates), *_SCALE_RANGE))


@dataclass(frozen=True)
class TriangleOffsets:
    """One cloud's points on the predicted surface, per triangle (`triangle_offsets`): how many
    passed the gate, their mean signed distance [m] (0 where none did) and the mean of the
    prior's variance along their normals [m^2], on the surface `triangles` (F, 3)."""

    triangles: np.ndarray
    counts: np.ndarray
    means: np.ndarray
    prior_variances: np.ndarray


def triangle_offsets(signed_distances: np.ndarray, triangle: np.ndarray, prior_variance: np.ndarray,
                     surface_triangles: np.ndarray) -> TriangleOffsets:
    """Per triangle of `surface_triangles` (F, 3), the points' signed distances (K,) [m] to the
    predicted surface, with their closest triangles (K,) and the prior's variance along their
    normals (K,) [m^2], within PERSISTENT_OFFSET_GATE robust spreads of the distances: the
    counts, mean distances and mean variances of `TriangleOffsets`."""
    signed_distances = np.asarray(signed_distances, dtype=np.float64)
    prior_variance = np.asarray(prior_variance, dtype=np.float64)
    triangle = np.asarray(triangle, dtype=np.int64)
    faces = len(surface_triangles)
    usable = np.isfinite(signed_distances) & np.isfinite(prior_variance) & (prior_variance > 0.0)
    if np.count_nonzero(usable) >= MIN_POINTS:
        usable &= np.abs(signed_distances) <= PERSISTENT_OFFSET_GATE * innovation_spread(
            np.abs(signed_distances[usable]))
    else:
        usable[:] = False
    kept = triangle[usable]
    counts = np.bincount(kept, minlength=faces)
    seen = np.maximum(counts, 1)
    means = np.bincount(kept, weights=signed_distances[usable], minlength=faces) / seen
    variances = np.bincount(kept, weights=prior_variance[usable], minlength=faces) / seen
    return TriangleOffsets(surface_triangles, counts, means, variances)


def persistent_offset_scale(previous: TriangleOffsets | None, current: TriangleOffsets) -> float | None:
    """lambda^2 from what two successive clouds' offsets share (module doc): the sum over the
    triangles both saw of the product of their mean signed distances, over the sum of the
    prior's variance along the normal there. Its mean is the prediction's squared normal error
    over the model's, for an error that persists between the clouds, with no term of their
    independent noise (which makes it scatter about zero where the error is below the noise).
    None without a previous cloud, on another surface (a cut), or with fewer than
    MIN_SHARED_TRIANGLES triangles seen by both."""
    if previous is None or not np.array_equal(previous.triangles, current.triangles):
        return None
    both = (previous.counts > 0) & (current.counts > 0)
    if np.count_nonzero(both) < MIN_SHARED_TRIANGLES:
        return None
    shared = float(previous.means[both] @ current.means[both])
    return shared / float(current.prior_variances[both].sum())


def _slope_estimate(squared: np.ndarray, variance: np.ndarray) -> float:
    """lambda^2 as the slope of the points' d_k^2 / c over their prior variance p_k: the points
    in PRIOR_VARIANCE_BINS bins of equal count by p_k, each bin's median of d_k^2 / c against
    its mean p_k, and the least-squares line through them, whose intercept is the noise's
    variance (not the estimated sigma, which the optimum's residuals set). Returned less
    SLOPE_STANDARD_ERRORS of its standard errors, propagated from each bin median's own
    sampling error (that of a median of n scaled chi^2(1) values: _MEDIAN_ERROR times the
    median over sqrt(n)), so that a slope the noise makes up counts for nothing (a narrow
    spread of p_k gives the line little leverage and a large error), whereas a hinge (an error
    on the soft points only) still counts; -inf with fewer than 3 bins or prior variances all
    alike."""
    order = np.argsort(variance, kind="stable")
    bins = np.array_split(order, min(PRIOR_VARIANCE_BINS, order.size))
    mean_variance = np.array([variance[group].mean() for group in bins])
    centred = mean_variance - mean_variance.mean()
    leverage = float(centred @ centred)
    if len(bins) < 3 or not leverage > 0.0:
        return -np.inf
    median_squared = np.array([np.median(squared[group]) for group in bins])
    median_errors = _MEDIAN_ERROR * median_squared / np.sqrt([group.size for group in bins])
    slope = float(centred @ median_squared) / leverage
    return slope - SLOPE_STANDARD_ERRORS * float(np.sqrt(centred**2 @ median_errors**2)) / leverage


def published_covariance(posterior: np.ndarray, prior: np.ndarray | None, alpha: float, scale: float) -> np.ndarray:
    """(V, 3, 3) covariance of the published estimate (module doc) from the blocks (V, 3, 3) of
    the posterior S and of the prior A^-1, the persisting share alpha in [0, 1] and
    lambda^2 = scale, the noise term bounded as the module doc says. Without a prior (no physics
    prior in the configuration) the posterior as it is."""
    if prior is None:
        return posterior
    beta = (1.0 - alpha) ** 2
    return scale * ((1.0 - beta) * posterior + beta * prior) + alpha**2 * max(1.0 - scale, 0.0) * posterior


def clipped_inverse(blocks: np.ndarray) -> tuple[np.ndarray, bool]:
    """(V, 3, 3) inverses of symmetric blocks whose eigenvalues are raised to 1e-12 of the
    largest of all, and whether any was raised (a block not positive definite)."""
    eigenvalues, eigenvectors = np.linalg.eigh(blocks)
    floor = 1e-12 * max(float(np.abs(eigenvalues).max(initial=0.0)), 1e-300)
    inverse = np.einsum("vij,vj,vkj->vik", eigenvectors, 1.0 / np.maximum(eigenvalues, floor), eigenvectors)
    return inverse, bool(np.any(eigenvalues <= floor))
