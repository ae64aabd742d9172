"""Noise models of the measurement factors: the information (inverse covariance) that weights
a point residual, and the robust kernels that reweight point residuals (as GTSAM's noiseModel
holds its m-estimators).

Point-wise models (identity, isotropic sigma, per-point sigma, a depth sensor's noise along
its rays) give one weight 1/sigma^2 per 3-vector residual block (one measurement point);
PointToSurfaceFactor takes its weights from them. The physics prior's information, its
scaled stiffness, depends on the state and may be indefinite (the paper's raw Neo-Hookean
prior), so PhysicsPriorFactor evaluates and holds it itself (factors.py).

Robust kernels: a kernel rho maps a point's squared distance d^2 [m^2] to a robust squared
distance; the point's cost is 0.5 * w * rho(d^2) with w = 1/sigma^2 its noise weight, and its
iteratively-reweighted least-squares weight is w * rho'(d^2). Its second derivative along d is
w * (rho'(s) + 2 s rho''(s)) at s = d^2 (`curvature`): below the IRLS weight, and negative
beyond the scale of a kernel with log tails. The scale k is in metres (as the ROS parameter),
which is the same as a kernel of scale k/sigma on the whitened residual:
  huber:  rho(s) = s                  for s <= k^2,   2 k sqrt(s) - k^2 beyond (linear tails)
  cauchy: rho(s) = k^2 log(1 + s/k^2)                                          (log tails)
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ROBUST_KERNELS",
    "CauchyKernel",
    "HuberKernel",
    "IdentityNoise",
    "IsotropicNoise",
    "NoiseModelError",
    "PerPointNoise",
    "PointNoise",
    "RAY_NOISE_FLOOR",
    "RayNoise",
    "RobustKernel",
    "RobustKernelError",
    "make_robust_kernel",
]

# RayNoise: a point's distance noise is at least this share of that of a point seen head-on
# (see the class).
RAY_NOISE_FLOOR = 0.5


class NoiseModelError(ValueError):
    """A non-positive or non-finite sigma, per-point sigmas of the wrong count, or a ray
    noise floor outside (0, 1]."""


class PointNoise:
    """Base of point-wise noise: weights (K,) = 1 / sigma_k^2 per 3D residual block."""

    def point_weights(self, count: int) -> np.ndarray:
        raise NotImplementedError

    def on_surface(self, points: np.ndarray, normals: np.ndarray, viewpoint: np.ndarray) -> PointNoise:
        """The model of `points` (K, 3), seen from `viewpoint` (3,), lying on surface patches of
        unit `normals` (K, 3). Models that do not depend on the geometry return themselves."""
        return self


class IdentityNoise(PointNoise):
    """Unit information (the paper's measurement factor): weight 1 [1/m^2]."""

    def point_weights(self, count: int) -> np.ndarray:
        return np.ones(count)

    def __repr__(self) -> str:
        return "IdentityNoise()"


class IsotropicNoise(PointNoise):
    """Every point with the same standard deviation sigma [m] per axis."""

    def __init__(self, sigma: float):
        if not (np.isfinite(sigma) and sigma > 0.0):
            raise NoiseModelError(f"sigma must be finite and > 0, got {sigma}")
        self.sigma = float(sigma)

    def point_weights(self, count: int) -> np.ndarray:
        return np.full(count, 1.0 / self.sigma**2)

    def __repr__(self) -> str:
        return f"IsotropicNoise(sigma={self.sigma:g})"


class PerPointNoise(PointNoise):
    """One standard deviation per point, sigmas (K,) [m] (e.g. growing with depth)."""

    def __init__(self, sigmas):
        sigmas = np.asarray(sigmas, dtype=np.float64).reshape(-1)
        if not (np.all(np.isfinite(sigmas)) and np.all(sigmas > 0.0)):
            raise NoiseModelError("per-point sigmas must be finite and > 0")
        self.sigmas = sigmas

    def point_weights(self, count: int) -> np.ndarray:
        if count != self.sigmas.size:
            raise NoiseModelError(f"per-point noise has {self.sigmas.size} sigmas, got {count} points")
        return 1.0 / self.sigmas**2

    def __repr__(self) -> str:
        return f"PerPointNoise({self.sigmas.size} sigmas)"


class RayNoise(IsotropicNoise):
    """A depth sensor's noise: each point is off along its ray from the viewpoint, so its distance
    to the surface it lies on varies with |cos theta| (theta between the ray and the surface
    normal), and a point seen at a grazing angle pins the surface's position more tightly than
    one seen head-on. Per point, sigma_k = sigma s_k / median(s) with s_k = max(|n_k . r_k|,
    floor): `sigma` stays the spread of a point at the cloud's median incidence (what the
    residuals' median measures, weights.py), and the floor stands for what does not shrink with
    the angle (the flat triangles' departure from a curved surface, lateral noise, mixed pixels
    at silhouettes, the association of grazing points to a neighbouring face).

    Measured on the accuracy suite (docs/design-notes.md, "Weights"): with floor 0.5 the median
    factor-graph / simulation ratio falls on every seed, with 0.25 the grazing points' weights
    (up to 16 times a head-on point's) hurt the scenes with sharp silhouettes. Until placed
    on a surface (`on_surface`: measurement_selection.select_points does it when it has a
    plausible viewpoint),
    every point has `sigma`."""

    def __init__(self, sigma: float, floor: float = RAY_NOISE_FLOOR):
        super().__init__(sigma)
        if not (0.0 < floor <= 1.0):
            raise NoiseModelError(f"floor must lie in (0, 1], got {floor}")
        self.floor = float(floor)

    def on_surface(self, points: np.ndarray, normals: np.ndarray, viewpoint: np.ndarray) -> PointNoise:
        points = np.asarray(points, dtype=np.float64)
        if not len(points):
            return self
        rays = points - np.asarray(viewpoint, dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            rays /= np.linalg.norm(rays, axis=1)[:, None]
        # fmax: a degenerate triangle's NaN normal, or a point at the viewpoint, gets the floor.
        incidence = np.fmax(np.abs(np.einsum("ij,ij->i", np.asarray(normals, dtype=np.float64), rays)), self.floor)
        return PerPointNoise(self.sigma * incidence / float(np.median(incidence)))

    def __repr__(self) -> str:
        return f"RayNoise(sigma={self.sigma:g}, floor={self.floor:g})"


# ------------------------------------------------------------------------------ robust kernels


class RobustKernelError(ValueError):
    """Unknown kernel name or a non-positive scale."""


class RobustKernel:
    """Base of robust kernels of scale k [m]."""

    name = ""

    def __init__(self, scale: float):
        if not (np.isfinite(scale) and scale > 0.0):
            raise RobustKernelError(f"robust kernel scale must be finite and > 0, got {scale}")
        self.scale = float(scale)

    def rho(self, squared: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def weight(self, squared: np.ndarray) -> np.ndarray:
        """rho'(d^2), the IRLS weight in (0, 1]."""
        raise NotImplementedError

    def curvature(self, squared: np.ndarray) -> np.ndarray:
        """rho'(s) + 2 s rho''(s) at s = d^2: the second derivative of 0.5 rho(d^2) along d."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(scale={self.scale:g})"


class HuberKernel(RobustKernel):
    name = "huber"

    def rho(self, squared):
        squared = np.asarray(squared, dtype=np.float64)
        distance = np.sqrt(squared)
        k = self.scale
        return np.where(distance <= k, squared, 2.0 * k * distance - k * k)

    def weight(self, squared):
        distance = np.sqrt(np.asarray(squared, dtype=np.float64))
        return np.where(distance <= self.scale, 1.0, self.scale / np.maximum(distance, self.scale))

    def curvature(self, squared):
        # Linear tails: rho' = k / d and 2 s rho'' = -k / d cancel.
        return np.where(np.sqrt(np.asarray(squared, dtype=np.float64)) <= self.scale, 1.0, 0.0)


class CauchyKernel(RobustKernel):
    name = "cauchy"

    def rho(self, squared):
        k2 = self.scale**2
        return k2 * np.log1p(np.asarray(squared, dtype=np.float64) / k2)

    def weight(self, squared):
        return 1.0 / (1.0 + np.asarray(squared, dtype=np.float64) / self.scale**2)

    def curvature(self, squared):
        ratio = np.asarray(squared, dtype=np.float64) / self.scale**2
        return (1.0 - ratio) / (1.0 + ratio) ** 2


# The robust kernels by name (the robust_kernel parameter's choices); "none": plain least squares.
_KERNELS = {kernel.name: kernel for kernel in (HuberKernel, CauchyKernel)}
ROBUST_KERNELS = ("none", *_KERNELS)


def make_robust_kernel(name, scale: float) -> RobustKernel | None:
    """Kernel by name: None or "none" (plain least squares), "huber", "cauchy"."""
    if name is None or name == "none":
        return None
    if name not in _KERNELS:
        raise RobustKernelError(f"robust kernel must be one of {ROBUST_KERNELS}, got {name!r}")
    return _KERNELS[name](scale)
