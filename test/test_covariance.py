"""The published estimate's covariance (core/estimation/covariance.py): sampled marginals against dense
inverses, the mixing formula against a Monte Carlo of the linear-Gaussian model it describes,
and the prior's error scale learnt from an innovation."""

import threading

import numpy as np
import pytest
import scipy.sparse
from scipy.stats import chi2

from meshfg_ros.core.estimation.covariance import (
    DENSE_MAX_DOFS,
    MIN_SHARED_TRIANGLES,
    ForgettingMean,
    MarginalCovariance,
    _chi_squared_density,
    chi_squared_quantile,
    clipped_inverse,
    persistent_offset_scale,
    prior_error_scale,
    published_covariance,
    triangle_offsets,
)
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky


def _blocks(matrix: np.ndarray) -> np.ndarray:
    vertices = matrix.shape[0] // 3
    return matrix.reshape(vertices, 3, vertices, 3)[np.arange(vertices), :, np.arange(vertices), :]


def _chain_information(vertices: int, seed: int) -> scipy.sparse.csr_matrix:
    """A mesh-like SPD matrix: vertices coupled to their neighbours along a chain, random 3x3 blocks."""
    rng = np.random.default_rng(seed)
    size = 3 * vertices
    rows, cols, values = [], [], []
    for offset in (0, 1, 2):
        for i in range(vertices - offset):
            block = rng.normal(size=(3, 3))
            rows += list(np.repeat(3 * i + np.arange(3), 3))
            cols += list(np.tile(3 * (i + offset) + np.arange(3), 3))
            values += list(block.ravel())
    half = scipy.sparse.csr_matrix((values, (rows, cols)), shape=(size, size))
    return (half @ half.T + 0.1 * scipy.sparse.identity(size)).tocsr()


@pytest.mark.parametrize("vertices", [40, DENSE_MAX_DOFS // 3 + 100])
def test_marginal_blocks_match_the_dense_inverse(vertices):
    information = _chain_information(vertices, seed=1)
    exact = _blocks(np.linalg.inv(information.toarray()))
    estimate = MarginalCovariance(samples=6000).blocks(information, seed=3)
    # Sampled beyond DENSE_MAX_DOFS: 6000 draws give about 1.1 % relative spread per variance.
    tolerance = 1e-9 if 3 * vertices <= DENSE_MAX_DOFS else 0.06
    ratios = np.einsum("vii->v", estimate) / np.einsum("vii->v", exact)
    assert np.max(np.abs(ratios - 1.0)) < tolerance
    np.testing.assert_allclose(estimate, exact, atol=tolerance * np.abs(exact).max())


def test_marginal_draws_through_a_given_factor_are_rescaled_to_the_matrix():
    vertices = DENSE_MAX_DOFS // 3 + 100
    information = _chain_information(vertices, seed=4)
    exact = _blocks(np.linalg.inv(information.toarray()))
    marginals = MarginalCovariance(samples=4000)
    own = marginals.blocks(information, seed=7)
    # A factor of 2 H draws N(0, H^-1 / 2): rescaled, H's own factor's draws to within the
    # scale's sampling spread, sqrt(2 / (n k)) = 6e-4 for n = 1,500 unknowns and k = 4,000 draws.
    given = marginals.blocks(information, seed=7, factor=SparseCholesky(2.0 * information, node_size=3))
    np.testing.assert_allclose(given, own, rtol=3e-3, atol=1e-6 * np.abs(own).max())
    unscaled = marginals.blocks(information, seed=7, factor=SparseCholesky(2.0 * information, node_size=3)) * 0.5
    assert not np.allclose(unscaled, own, rtol=0.1)
    # A factor of a nearby matrix at another scale (an earlier state's block, weighted with an
    # earlier noise estimate): the variances within sampling of H's.
    nearby = 1.5 * (information + 1e-4 * scipy.sparse.diags(information.diagonal()))
    close = marginals.blocks(information, seed=7, factor=SparseCholesky(nearby.tocsr(), node_size=3))
    ratios = np.einsum("vii->v", close) / np.einsum("vii->v", exact)
    assert np.median(np.abs(ratios - 1.0)) < 0.1


def test_sampled_marginals_are_the_same_for_the_same_seed_and_refactor_on_the_kept_pattern():
    vertices = DENSE_MAX_DOFS // 3 + 10
    first = _chain_information(vertices, seed=4)
    marginals = MarginalCovariance(samples=16)
    a = marginals.blocks(first, seed=7)
    b = marginals.blocks(2.0 * first, seed=7)  # same pattern: numeric refactorisation
    np.testing.assert_allclose(b, 0.5 * a, rtol=1e-9)


@pytest.mark.parametrize("threads", ["1", "2"])
def test_prepared_draws_give_the_blocks_drawn_on_demand_and_stale_ones_are_not_used(monkeypatch, threads):
    """Draws prepared ahead through a factor (`prepare`, beside the caller with two worker
    threads, not at all with one) give the blocks drawn on demand through it; prepared for
    another seed, or through a factor refactored since, they are not used."""
    monkeypatch.setenv("MESHFG_WORKER_THREADS", threads)
    information = _chain_information(DENSE_MAX_DOFS // 3 + 100, seed=4)
    factor = SparseCholesky(information, node_size=3)
    on_demand = MarginalCovariance().blocks(information, seed=7, factor=factor)
    marginals = MarginalCovariance()
    caller, drawn_by = threading.get_ident(), []
    original = MarginalCovariance._draw_through
    monkeypatch.setattr(MarginalCovariance, "_draw_through",
                        lambda self, *args: drawn_by.append(threading.get_ident()) or original(self, *args))
    for prepared_seed in (7, 8):
        marginals.prepare(factor, seed=prepared_seed)
        before = drawn_by.count(caller)
        np.testing.assert_allclose(marginals.blocks(information, seed=7, factor=factor), on_demand, rtol=1e-12, atol=0)
        # Prepared for its seed, beside the caller: the blocks draw nothing of their own.
        used = threads == "2" and prepared_seed == 7
        assert drawn_by.count(caller) - before == (0 if used else 1)
    marginals.prepare(factor, seed=7)
    nearby = (information + 0.3 * scipy.sparse.diags(information.diagonal())).tocsr()
    nearby.sort_indices()
    factor.refactor(nearby.data)  # after the prepared draws have ended: they are of the old values
    refactored = MarginalCovariance().blocks(information, seed=7, factor=factor)
    assert not np.allclose(refactored, on_demand, rtol=1e-3)
    np.testing.assert_allclose(marginals.blocks(information, seed=7, factor=factor), refactored, rtol=1e-12, atol=0)


def test_a_matrix_that_is_not_positive_definite_is_refused():
    matrix = -scipy.sparse.identity(6, format="csr")
    with pytest.raises(NotPositiveDefiniteError):
        MarginalCovariance().blocks(matrix)


@pytest.mark.parametrize("alpha, scale", [(1.0, 1.0), (0.0, 1.0), (0.6, 1.0), (0.0, 2.5), (0.6, 4.0), (0.3, 0.2)])
def test_published_covariance_is_the_published_means_at_lambda_one_and_above_it_otherwise(alpha, scale):
    """m = Xhat + alpha S H^T (y - H Xhat) with Xhat - X ~ N(0, scale A^-1) and unit noise on y:
    the formula is its covariance at scale 1, and bounds it from above (the noise term's bound) else."""
    rng = np.random.default_rng(5)
    size, observed = 6, 4
    half = rng.normal(size=(size, size))
    prior_information = half @ half.T + np.eye(size)
    observation = rng.normal(size=(observed, size))
    posterior = np.linalg.inv(prior_information + observation.T @ observation)
    prior = np.linalg.inv(prior_information)
    draws = 200_000
    prediction_error = rng.multivariate_normal(np.zeros(size), scale * prior, size=draws)
    innovation = rng.normal(size=(draws, observed)) - prediction_error @ observation.T
    published_error = prediction_error + alpha * (innovation @ observation) @ posterior
    empirical = _blocks(published_error.T @ published_error / draws)
    model = published_covariance(_blocks(posterior), _blocks(prior), alpha, scale)
    sampling = 0.02 * np.abs(empirical).max()  # 200k draws: about 0.3 % per entry
    if scale == 1.0:
        np.testing.assert_allclose(model, empirical, atol=sampling)
    else:
        assert np.linalg.eigvalsh(model - empirical).min() > -sampling


def test_published_covariance_without_a_prior_is_the_posterior():
    posterior = np.tile(np.eye(3), (4, 1, 1))
    assert published_covariance(posterior, None, 0.3, 5.0) is posterior


def test_clipped_inverse_inverts_and_says_where_it_clamped():
    blocks = np.stack([np.diag([1.0, 2.0, 4.0]), np.diag([1.0, 1.0, -1.0])])
    inverse, clamped = clipped_inverse(blocks)
    np.testing.assert_allclose(inverse[0], np.diag([1.0, 0.5, 0.25]))
    assert clamped and np.all(np.isfinite(inverse))


@pytest.mark.parametrize("scale", [0.01, 1.0, 30.0])
def test_prior_error_scale_recovers_the_prediction_error_despite_leaks(scale):
    rng = np.random.default_rng(int(scale * 100))
    points = 4000
    variance = rng.uniform(0.5e-8, 2e-8, points)
    sigma = 1e-4
    distances = np.abs(rng.normal(size=points)) * np.sqrt(scale * variance + sigma**2)
    distances[: points // 5] = rng.uniform(0.0, 1e-2, points // 5)  # 20 % leaks, far off
    estimate = prior_error_scale(distances, variance, sigma, gate_spreads=5.0)
    total = scale * variance.mean() + sigma**2
    # Judged on the whole variance it explains (noise masks a small prediction error); the leaks
    # within the gate bias it up, never down.
    explained = estimate * variance.mean() + sigma**2
    assert 0.95 * total < explained < 1.25 * total


def test_prior_error_scale_needs_enough_points():
    assert prior_error_scale(np.ones(10), np.ones(10), 1.0, 5.0) is None
    assert prior_error_scale(np.full(100, np.nan), np.ones(100), 1.0, 5.0) is None


def test_prior_error_scale_puts_the_median_normalised_innovation_at_chi2_ones():
    """Where the error follows the prior's shape (here: none, the noise alone) the median
    estimate is the one taken, and it puts the median normalised innovation at chi^2(1)'s."""
    rng = np.random.default_rng(9)
    distances, variance = np.abs(rng.normal(size=501)) * 1e-3, rng.uniform(1e-8, 4e-8, 501)
    sigma = 2e-4
    scale = prior_error_scale(distances, variance, sigma, gate_spreads=np.inf)
    assert np.median(distances**2 / (scale * variance + sigma**2)) == pytest.approx(chi2.ppf(0.5, 1), rel=1e-9)
    # A cloud explained by the noise alone gives the lower bound, not a negative scale.
    assert prior_error_scale(np.full(100, 1e-9), np.ones(100), 1.0, 5.0) == pytest.approx(1e-6)


def _median_estimate(distances, variance, sigma):
    return np.median((distances**2 / chi2.ppf(0.5, 1) - sigma**2) / variance)


def test_prior_error_scale_holds_when_the_noise_estimate_is_off():
    """The median estimate subtracts the estimated noise, so a noise estimate 10 % high (the
    optimum's residuals set it) takes most of a small prediction error away; the slope over the
    prior variance takes the noise from its intercept and keeps at least half of it."""
    rng = np.random.default_rng(0)
    points, sigma, scale = 20000, 2e-4, 4.0
    variance = rng.uniform(1e-9, 6e-9, points)
    distances = np.abs(rng.normal(size=points)) * np.sqrt(scale * variance + sigma**2)
    assert _median_estimate(distances, variance, 1.1 * sigma) < 0.5 * scale
    assert 0.5 * scale < prior_error_scale(distances, variance, 1.1 * sigma, gate_spreads=5.0) < 1.2 * scale


@pytest.mark.parametrize("relative_spread", [0.0, 1e-12, 1e-3])
def test_prior_error_scale_is_the_median_estimate_where_the_prior_variances_do_not_spread(relative_spread):
    """Without a spread of prior variances the slope has no leverage: its noise must not lift
    the estimate above the median's (a wild slope would stay in the forgetting mean for long)."""
    rng = np.random.default_rng(3)
    points, sigma = 2000, 1e-4
    for _ in range(20):  # clouds
        variance = 1e-8 * (1.0 + relative_spread * rng.uniform(size=points))
        distances = np.abs(rng.normal(size=points)) * np.sqrt(variance + sigma**2)
        assert prior_error_scale(distances, variance, sigma, gate_spreads=np.inf) == pytest.approx(
            _median_estimate(distances, variance, sigma), rel=1e-9)


def _two_clouds(rng, error_std, noise_sigma, faces=2000, points_per_face=20, leak_share=0.0):
    """Two clouds' signed distances to a predicted surface of `faces` triangles whose normal
    error is one N(0, error_std^2) offset per triangle, the same for both clouds, with
    independent N(0, noise_sigma^2) noise; `leak_share` of the points are leaks, 10 noise
    sigmas off the surface at the same triangles in both clouds."""
    surface = np.arange(3 * faces).reshape(faces, 3)
    error = rng.normal(0.0, error_std, faces)
    leaking = np.arange(faces) < leak_share * faces
    clouds = []
    for _ in range(2):
        triangle = rng.integers(0, faces, faces * points_per_face)
        signed = error[triangle] + rng.normal(0.0, noise_sigma, triangle.size)
        signed[leaking[triangle]] = 10.0 * noise_sigma
        clouds.append((signed, triangle))
    return surface, clouds


@pytest.mark.parametrize("error_std", [0.0, 1e-5, 3e-5])
def test_persistent_offsets_size_the_normal_error_without_the_noise(error_std):
    """The noise variance is 11 times the error's or more: the median estimate, with a noise
    estimate 3 % low (as the optimum's residuals may set it), is off by several times the
    error's scale; the persistent offsets, which need no noise estimate, are not."""
    rng = np.random.default_rng(int(error_std * 1e6))
    sigma, variance = 1e-4, 1e-10  # lambda^2 = error_std^2 / variance: 0, 1, 9
    surface, clouds = _two_clouds(rng, error_std, sigma)
    offsets = [triangle_offsets(signed, triangle, np.full(signed.size, variance), surface)
               for signed, triangle in clouds]
    assert persistent_offset_scale(None, offsets[0]) is None
    estimate = persistent_offset_scale(offsets[0], offsets[1])
    truth = error_std**2 / variance
    # standard error: the triangle means' noise sigma^2 / 20 over variance, / sqrt(2000): about 0.11
    assert abs(estimate - truth) < 0.4 + 0.15 * truth
    signed, _ = clouds[1]
    median = _median_estimate(np.abs(signed), np.full(signed.size, variance), 0.97 * sigma)
    assert median - truth > 3.0


def test_persistent_offsets_leave_out_leaks_beyond_their_gate():
    rng = np.random.default_rng(5)
    sigma, variance, error_std = 1e-4, 1e-10, 2e-5
    surface, clouds = _two_clouds(rng, error_std, sigma, leak_share=0.2)
    offsets = [triangle_offsets(signed, triangle, np.full(signed.size, variance), surface)
               for signed, triangle in clouds]
    leaking = offsets[0].counts[:400]  # _two_clouds' leaking triangles: the first 20 %
    assert not leaking.any()  # their points are all gated out
    assert persistent_offset_scale(offsets[0], offsets[1]) == pytest.approx(error_std**2 / variance, abs=0.5)


def test_persistent_offsets_need_the_same_surface_and_enough_shared_triangles():
    rng = np.random.default_rng(1)
    surface, clouds = _two_clouds(rng, 1e-5, 1e-4, faces=50)
    offsets = [triangle_offsets(signed, triangle, np.full(signed.size, 1e-10), surface) for signed, triangle in clouds]
    assert persistent_offset_scale(offsets[0], offsets[1]) is not None
    cut = triangle_offsets(*clouds[1], np.full(clouds[1][0].size, 1e-10), surface[:-1])
    assert persistent_offset_scale(offsets[0], cut) is None
    few = clouds[1][1] < MIN_SHARED_TRIANGLES - 1
    sparse = triangle_offsets(clouds[1][0][few], clouds[1][1][few], np.full(np.count_nonzero(few), 1e-10), surface)
    assert persistent_offset_scale(offsets[0], sparse) is None
    # Too few usable points for the gate's spread: nothing passes.
    assert not triangle_offsets(np.zeros(5), np.zeros(5, int), np.ones(5), surface).counts.any()


def test_prior_error_scale_takes_the_persistent_estimate_where_it_is_the_larger():
    rng = np.random.default_rng(2)
    distances, variance = np.abs(rng.normal(size=1000)) * 1e-4, np.full(1000, 1e-10)
    alone = prior_error_scale(distances, variance, 1e-4, 5.0)
    assert prior_error_scale(distances, variance, 1e-4, 5.0, persistent=alone - 1.0) == pytest.approx(alone)
    assert prior_error_scale(distances, variance, 1e-4, 5.0, persistent=alone + 7.0) == pytest.approx(alone + 7.0)
    assert prior_error_scale(distances, variance, 1e-4, 5.0, persistent=1e9) == pytest.approx(1e6)


def test_forgetting_mean_starts_at_its_initial_value_and_follows_the_values():
    mean = ForgettingMean(0.5, initial=1.0)
    assert mean.add(3.0) == pytest.approx((0.5 * 1.0 + 3.0) / 1.5)
    for _ in range(30):
        value = mean.add(3.0)
    assert value == pytest.approx(3.0, rel=1e-6)
    with pytest.raises(ValueError):
        ForgettingMean(1.0, initial=1.0)


def test_forgetting_mean_standard_error_is_the_weighted_scatter_over_the_effective_count():
    """Values that do not scatter have no standard error; for independent values the mean's
    scatter over many runs matches the standard error each run states."""
    steady = ForgettingMean(0.7, initial=2.0)
    for _ in range(5):
        steady.add(2.0)
    assert steady.standard_error() == pytest.approx(0.0, abs=1e-12)
    one = ForgettingMean(0.5, initial=0.0)
    one.add(3.0)  # weights 0.5 and 1: mean 2, weighted variance 2, effective count 1.8
    assert one.standard_error() == pytest.approx(np.sqrt(2.0 / 1.8))
    rng = np.random.default_rng(0)
    means, errors = [], []
    for _ in range(4000):
        mean = ForgettingMean(0.7, initial=5.0)
        for value in rng.normal(5.0, 2.0, 40):
            last = mean.add(value)
        means.append(last)
        errors.append(mean.standard_error())
    # the spread of the means against the stated error, whose variance is the weighted sample
    # variance's: low by the factor 1 - 1 / (effective count)
    effective = mean.weight**2 / mean.weight_squares
    assert np.std(means) == pytest.approx(np.sqrt(np.mean(np.square(errors)) / (1.0 - 1.0 / effective)), rel=0.04)


@pytest.mark.parametrize("dof", [1, 2, 3, 7.5])
def test_chi_squared_quantile_and_density_are_scipy_stats_ones(dof):
    probability = np.linspace(0.001, 0.999, 999)
    np.testing.assert_allclose(chi_squared_quantile(probability, dof), chi2.ppf(probability, dof), rtol=1e-13)
    x = np.linspace(0.01, 40.0, 1000)
    np.testing.assert_allclose(_chi_squared_density(x, dof), chi2.pdf(x, dof), rtol=1e-13)
    assert chi_squared_quantile(0.95, 3) == pytest.approx(7.8147, abs=1e-4)
