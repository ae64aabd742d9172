"""Noise models of factors: the information (inverse covariance) that weights a residual.

Point-wise models (identity, isotropic sigma, per-point sigma) give one weight 1/sigma^2 per
3-vector residual block (one measurement point); `InformationMatrixNoise` holds a full sparse
information matrix (the physics prior's scaled stiffness), which may be indefinite (the
paper's raw Neo-Hookean prior): then it has no real square root, and `sqrt_information`
raises. Whitening (r -> R r with R^T R = information) is what least-squares baselines
(scipy, GTSAM) need; the estimator itself works with the information directly.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse

__all__ = [
    "IdentityNoise",
    "InformationMatrixNoise",
    "IsotropicNoise",
    "NoiseModelError",
    "NotPositiveDefiniteError",
    "PerPointNoise",
    "PointNoise",
]


class NoiseModelError(ValueError):
    """A non-positive or non-finite sigma, or an information matrix of the wrong shape."""


class NotPositiveDefiniteError(ValueError):
    """An information matrix without a Cholesky square root (indefinite or singular)."""


class PointNoise:
    """Base of point-wise noise: weights (K,) = 1 / sigma_k^2 per 3D residual block."""

    def point_weights(self, count: int) -> np.ndarray:
        raise NotImplementedError

    def subset(self, mask: np.ndarray) -> PointNoise:
        """The model of the points selected by `mask`: a boolean mask or indices (in their order)."""
        return self

    def whiten(self, residual: np.ndarray) -> np.ndarray:
        """Whitened residual of K points, (K, 3) -> (K, 3)."""
        residual = np.asarray(residual, dtype=np.float64)
        return residual * np.sqrt(self.point_weights(len(residual)))[:, None]


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

    def subset(self, mask: np.ndarray) -> PerPointNoise:
        return PerPointNoise(self.sigmas[np.asarray(mask)])

    def __repr__(self) -> str:
        return f"PerPointNoise({self.sigmas.size} sigmas)"


class InformationMatrixNoise:
    """A full (sparse, symmetric) information matrix Lambda (m, m); cost 0.5 r^T Lambda r."""

    def __init__(self, information):
        information = scipy.sparse.csr_matrix(information, dtype=np.float64)
        if information.shape[0] != information.shape[1]:
            raise NoiseModelError(f"information matrix must be square, got {information.shape}")
        if not np.all(np.isfinite(information.data)):
            raise NoiseModelError("information matrix has NaN or infinite entries")
        self.information = information

    def squared_norm(self, residual: np.ndarray) -> float:
        """r^T Lambda r (negative when Lambda is indefinite)."""
        residual = np.asarray(residual, dtype=np.float64).reshape(-1)
        return float(residual @ (self.information @ residual))

    def sqrt_information(self) -> np.ndarray:
        """Upper-triangular R (m, m) dense with R^T R = Lambda (dense Cholesky: small problems)."""
        try:
            return scipy.linalg.cholesky(self.information.toarray(), lower=False)
        except np.linalg.LinAlgError:
            raise NotPositiveDefiniteError("information matrix is not positive definite (no square root)") from None

    def whiten(self, residual: np.ndarray) -> np.ndarray:
        return self.sqrt_information() @ np.asarray(residual, dtype=np.float64).reshape(-1)

    def __repr__(self) -> str:
        return f"InformationMatrixNoise({self.information.shape[0]}x{self.information.shape[1]})"
