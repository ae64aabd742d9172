"""The factors' weights from the data: the measurement noise, and the prior's trust tied to it.

A user knows the sensor's nominal noise, not its real spread: the quadratic depth term, the
grazing angles and the surface's roughness put the real spread of the points about the tissue
surface at 0.8-2.2x the datasheet value in the accuracy suite's scenes (estimated). The
measurement sigma is therefore estimated after every update, from the distances d_k of the
cloud's points to the optimised surface: sigma = 1.4826 median(d_k), the scale of a half-normal,
robust to the leaks the gate and the robust kernel left in (up to half of the points). Before
the first update, which has no optimum yet, the estimator takes the selected points' spread
about the predicted surface where the prediction fits them to within their noise (estimator.py,
`_estimate_noise_before_first_update`): their spread once each triangle's mean offset is removed
(`offsets_within_triangles`) tells, since the prediction's error is a smooth field, nearly one
offset along the normal over a triangle, while the noise is independent between points. The
redundancy correction sqrt(n / (n - tr(H^-1 H_m))) of a variance-component estimate changes it
by 1-7 % with a thousand points (Hutchinson traces, measured on liver-push) and is left out.

The simulator's trust is not estimated from the residuals. Variance-component (Foerstner)
estimates of the physics prior's scale, tried on the accuracy suite, cost accuracy: the
FEM-stiffness information models the simulator's error as rough, strain-driven noise while the
real error is a few smooth, systematic fields (a missed load, a stiffer inclusion, a tool
offset). Unbounded, the estimate ran to its upper bound (a simulation sigma of 0.01 mm) on the
three bundled scenes and for most updates of the others, so the estimate followed the
simulation (liver-gravity: 1.08x the simulation's error); bounded to [0.1, 1] measurement
sigmas it weakened the prior on dome-tilted and kidney-drag, which then ended at 1.21x and
1.64x with LM unconverged in most of their updates. The prior instead follows the estimated
noise: simulation sigma = PRIOR_NOISE_RATIO * measurement sigma, so the simulation outweighs
any one point by 1 / ratio^2 = 100 per coordinate, wherever the noise level sits. Of the ratios
0.05, 0.1 and 0.2, 0.1 gave the lowest median error over the suite (docs/design-notes.md).
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.inputs.input_checks import innovation_spread

__all__ = ["NOISE_BOUNDS", "PRIOR_NOISE_RATIO", "MeasurementNoise", "WeightError", "offsets_within_triangles"]

PRIOR_NOISE_RATIO = 0.1
# The noise estimate stays within this factor below and above the nominal sigma.
NOISE_BOUNDS = 10.0


class WeightError(ValueError):
    """A non-positive nominal sigma, step or bound."""


class MeasurementNoise:
    """The measurement sigma: starts at the nominal value; each `observe` moves it towards the
    robust spread of an update's residual distances by at most a factor `max_step`, within
    `bounds` (a factor below and above the nominal value). `spread_beyond_bounds` says whether
    the last observed spread lay outside those bounds: the nominal value is then off by more
    than `bounds` (the suite's clouds spread 0.8-2.2x their datasheet sigma), as a value given
    in the wrong units is."""

    def __init__(self, nominal_sigma: float, max_step: float = 4.0, bounds: float = NOISE_BOUNDS):
        for name, value, low in (("nominal_sigma", nominal_sigma, 0.0), ("max_step", max_step, 1.0),
                                 ("bounds", bounds, 1.0)):
            if not (np.isfinite(value) and value > low):
                raise WeightError(f"{name} must be finite and > {low:g}, got {value}")
        self.nominal_sigma = float(nominal_sigma)
        self.sigma = self.nominal_sigma
        self.max_step, self.bounds = float(max_step), float(bounds)
        self.spread = float("nan")  # m, the last observed robust spread

    @property
    def observed(self) -> bool:
        """Whether any cloud's spread has been observed (sigma is then an estimate, not the
        nominal value)."""
        return bool(np.isfinite(self.spread))

    @property
    def spread_beyond_bounds(self) -> bool:
        """Whether the last observed spread lay outside the bounds about the nominal sigma."""
        low, high = self.nominal_sigma / self.bounds, self.nominal_sigma * self.bounds
        return self.observed and not low <= self.spread <= high

    def observe(self, distances: np.ndarray) -> float:
        """Move sigma towards 1.4826 median(distances) [m]; returns the relative change (>= 0).
        Fewer than MIN_POINTS distances leave it unchanged."""
        distances = np.asarray(distances, dtype=np.float64)
        if distances.size < MIN_POINTS:
            return 0.0
        target = innovation_spread(distances)
        self.spread = target
        log_step = np.clip(np.log(max(target, 1e-300) / self.sigma), -np.log(self.max_step), np.log(self.max_step))
        sigma = float(np.clip(self.sigma * np.exp(log_step), self.nominal_sigma / self.bounds,
                              self.nominal_sigma * self.bounds))
        change = abs(sigma / self.sigma - 1.0)
        self.sigma = sigma
        return change


# A noise estimate from fewer points than this is not trusted (a median of a handful).
MIN_POINTS = 30


# offsets_within_triangles: a triangle's points count when it holds at least this many.
MIN_POINTS_PER_TRIANGLE = 3


def offsets_within_triangles(signed_distances: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Points' signed distances d (K,) [m] to their closest triangles `triangles` (K,) less
    each triangle's common offset: |d_k - mean of d over k's triangle| sqrt(m / (m - 1)) for
    the points of the triangles that hold m >= MIN_POINTS_PER_TRIANGLE of them (the scaling
    keeps the spread of independent noise, of which the mean of m removes a share 1/m). Their
    robust spread (`MeasurementNoise.observe`) estimates the noise without a smooth offset of
    the surface the distances were measured to."""
    signed_distances = np.asarray(signed_distances, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    counts = np.bincount(triangles)
    sums = np.bincount(triangles, weights=signed_distances)
    count = counts[triangles]
    kept = count >= MIN_POINTS_PER_TRIANGLE
    count = count[kept]
    offsets = signed_distances[kept] - sums[triangles[kept]] / count
    return np.abs(offsets) * np.sqrt(count / (count - 1.0))
