"""The measurement noise estimate: robust to leaks, moving by bounded steps within bounds."""

import numpy as np
import pytest

from meshfg_ros.core.estimation.weights import (MIN_POINTS, MIN_POINTS_PER_TRIANGLE, MeasurementNoise, WeightError,
                                               offsets_within_triangles)


def half_normal(sigma, count, seed=0):
    return np.abs(np.random.default_rng(seed).normal(scale=sigma, size=count))


def test_estimate_reaches_the_real_spread_through_leaks():
    noise = MeasurementNoise(0.5e-3)
    distances = half_normal(1.2e-3, 2000)
    distances[:400] = 0.02  # a fifth of the cloud on the tool and the table
    for _ in range(3):
        noise.observe(distances)
    assert noise.sigma == pytest.approx(1.2e-3 * 1.2, rel=0.15)  # leaks lift the median by about a fifth
    clean = MeasurementNoise(0.5e-3)
    clean.observe(half_normal(1.2e-3, 2000, seed=1))
    assert clean.sigma == pytest.approx(1.2e-3, rel=0.05)


def test_steps_and_bounds_and_too_few_points():
    noise = MeasurementNoise(1e-3, max_step=4.0, bounds=10.0)
    change = noise.observe(half_normal(50e-3, 1000))
    assert noise.sigma == pytest.approx(4e-3) and change == pytest.approx(3.0)
    for _ in range(5):
        noise.observe(half_normal(50e-3, 1000))
    assert noise.sigma == pytest.approx(10e-3)  # the upper bound
    assert noise.observe(half_normal(1e-3, MIN_POINTS - 1)) == 0.0 and noise.sigma == pytest.approx(10e-3)
    with pytest.raises(WeightError):
        MeasurementNoise(0.0)
    with pytest.raises(WeightError):
        MeasurementNoise(1e-3, max_step=1.0)


def test_a_spread_beyond_the_bounds_is_flagged():
    noise = MeasurementNoise(1e-3, bounds=10.0)
    assert not noise.spread_beyond_bounds and not noise.observed  # nothing observed yet
    noise.observe(half_normal(2e-3, 10))  # too few points to tell: still the nominal sigma
    assert not noise.observed and noise.sigma == 1e-3
    noise.observe(half_normal(2e-3, 1000))  # twice the nominal: a real sensor's spread
    assert noise.observed and not noise.spread_beyond_bounds and noise.spread == pytest.approx(2e-3, rel=0.1)
    noise.observe(half_normal(0.05e-3, 1000))  # a twentieth: a nominal sigma given 20x too large
    assert noise.spread_beyond_bounds and noise.spread == pytest.approx(0.05e-3, rel=0.1)
    noise.observe(half_normal(15e-3, 1000))  # fifteen times
    assert noise.spread_beyond_bounds


def test_offsets_within_triangles_keep_the_noise_and_drop_each_triangles_common_offset():
    """Signed distances = a large offset per triangle (a prediction's smooth error) + noise of
    sigma: the robust spread of what is left is sigma (the m / (m - 1) scaling undoes the mean's
    share), where the raw distances' spread is several times it; triangles with fewer than
    MIN_POINTS_PER_TRIANGLE points are left out."""
    rng = np.random.default_rng(2)
    sigma, triangles = 1e-3, 3000
    per_triangle = rng.integers(MIN_POINTS_PER_TRIANGLE, 7, triangles)
    triangle = np.repeat(np.arange(triangles), per_triangle)
    signed = rng.normal(scale=5 * sigma, size=triangles)[triangle] + rng.normal(scale=sigma, size=triangle.size)
    lone = np.arange(triangles, triangles + 50)  # one point each
    left = offsets_within_triangles(np.concatenate([signed, rng.normal(size=50)]), np.concatenate([triangle, lone]))
    assert left.shape == signed.shape and np.all(left >= 0)
    noise = MeasurementNoise(sigma, max_step=100.0)
    noise.observe(left)
    assert noise.spread == pytest.approx(sigma, rel=0.05)
    noise.observe(np.abs(signed))
    assert noise.spread > 3 * sigma
