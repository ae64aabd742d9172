"""Robust kernels for point residuals: IRLS weights (as GTSAM's m-estimators) and curvatures.

A kernel rho maps a point's squared distance d^2 [m^2] to a robust squared distance; the
point's cost is 0.5 * w * rho(d^2) with w = 1/sigma^2 its noise weight, and its
iteratively-reweighted least-squares weight is w * rho'(d^2). Its second derivative along d is
w * (rho'(s) + 2 s rho''(s)) at s = d^2 (`curvature`): below the IRLS weight, and negative
beyond the scale of a kernel with log tails. The scale k is in metres (as the ROS parameter),
which is the same as a kernel of scale k/sigma on the whitened residual:
  huber:  rho(s) = s                  for s <= k^2,   2 k sqrt(s) - k^2 beyond (linear tails)
  cauchy: rho(s) = k^2 log(1 + s/k^2)                                          (log tails)
"""

from __future__ import annotations

import numpy as np

__all__ = ["ROBUST_KERNELS", "CauchyKernel", "HuberKernel", "RobustKernel", "RobustKernelError", "make_robust_kernel"]

ROBUST_KERNELS = ("none", "huber", "cauchy")


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


def make_robust_kernel(name, scale: float) -> RobustKernel | None:
    """Kernel by name: None or "none" (plain least squares), "huber", "cauchy"."""
    if name is None or name == "none":
        return None
    kernels = {"huber": HuberKernel, "cauchy": CauchyKernel}
    if name not in kernels:
        raise RobustKernelError(f"robust kernel must be one of {ROBUST_KERNELS}, got {name!r}")
    return kernels[name](scale)
