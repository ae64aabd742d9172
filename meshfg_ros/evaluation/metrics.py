"""Building blocks of the paper's evaluation (evaluation/evaluate.py computes the surface
metrics d_CD, d_RMSE and d_H95 from them): vertex RMSE, the alignment of a correction with
the one the truth needed, the calibration of a published per-vertex uncertainty against the
truth, area-uniform samples of a surface, the observable split, and the mean and spread of
per-step values.

The observable split follows the paper's ex vivo study: rays from the camera centre through
the measured (depth) points are cast onto a surface; the triangles they first hit form the
region the depth sensor could observe, and the surface vertices on none of them are the
"unobserved external" vertices. All lengths are in the units of the inputs (metres in this
project).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from meshfg_ros.core.estimation.covariance import chi_squared_quantile
from meshfg_ros.synthetic.camera import as_point_array, as_triangle_array, first_ray_hits


def vertex_rmse(estimate, truth, indices=None) -> float:
    """Root mean square of per-vertex Euclidean errors, over all vertices or `indices`."""
    estimate = as_point_array("estimate", estimate)
    truth = as_point_array("truth", truth)
    if estimate.shape != truth.shape:
        raise ValueError(f"estimate {estimate.shape} and truth {truth.shape} differ in shape")
    errors = estimate - truth
    if indices is not None:
        errors = errors[_as_indices("indices", indices, len(errors))]
    if len(errors) == 0:
        raise ValueError("vertex_rmse needs at least one vertex")
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", errors, errors))))


def correction_alignment(prediction, estimate, truth, indices=None, directions=None,
                         across: bool = False) -> dict[str, float]:
    """How the estimator's correction of a prediction compares with the one the truth needed.

    With a = estimate - prediction (what the measurements changed) and b = truth - prediction
    (what they should have changed), over `indices` (all vertices by default) and, with unit
    `directions` (N, 3), of their components along them (a vertex normal: what a
    point-to-surface measurement sees) or, with `across`, orthogonal to them (sliding along
    the surface, which it does not see):
      alignment = a.b / (|a| |b|): 1 when the correction points at the truth, 0 when it is
                  unrelated to the error (noise), -1 when it moves away from the truth;
      gain      = a.b / b.b: the share of the needed correction made along it (1: all of it).
    Vertex RMSE says whether the estimate improved; these say why not: a correction in the
    wrong direction (the prior's extrapolation) or too small a one (a prior that is too stiff,
    or an error the measurements cannot see). NaN when either correction is zero."""
    prediction = as_point_array("prediction", prediction)
    estimate = as_point_array("estimate", estimate)
    truth = as_point_array("truth", truth)
    if not prediction.shape == estimate.shape == truth.shape:
        raise ValueError(f"prediction {prediction.shape}, estimate {estimate.shape} and truth {truth.shape} differ")
    made, needed = estimate - prediction, truth - prediction
    if directions is not None:
        directions = as_point_array("directions", directions)
        if directions.shape != prediction.shape:
            raise ValueError(f"directions {directions.shape} and prediction {prediction.shape} differ in shape")
        made_along = np.einsum("ij,ij->i", made, directions)
        needed_along = np.einsum("ij,ij->i", needed, directions)
        if across:
            made = made - made_along[:, None] * directions
            needed = needed - needed_along[:, None] * directions
        else:
            made, needed = made_along, needed_along
    elif across:
        raise ValueError("across needs directions")
    if indices is not None:
        selected = _as_indices("indices", indices, len(prediction))
        made, needed = made[selected], needed[selected]
    made, needed = made.ravel(), needed.ravel()
    both = float(made @ needed)
    made_norm, needed_norm = float(np.linalg.norm(made)), float(np.linalg.norm(needed))
    if made_norm == 0.0 or needed_norm == 0.0:
        return {"alignment": float("nan"), "gain": float("nan")}
    return {"alignment": both / (made_norm * needed_norm), "gain": both / needed_norm**2}


# Nominal levels of a reliability curve: the share of vertices inside their ellipsoid of each
# level is compared with the level (a calibrated estimator's curve is the diagonal).
CALIBRATION_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)
# Degrees of freedom of a vertex's position error: its NEES is chi-squared with 3 of them.
_POSITION_DOF = 3


@dataclass(frozen=True)
class Calibration:
    """How well a published per-vertex standard deviation describes the actual errors.

    With std_i = sqrt(trace(Sigma_ii) / 3), the normalised estimation error squared (NEES) of
    vertex i is |estimate_i - truth_i|^2 / std_i^2. For an error drawn from N(0, std_i^2 I3) it
    is chi-squared with 3 degrees of freedom: mean 3, and a vertex lies inside its level-p
    ellipsoid (NEES <= chi_squared_quantile(p, 3)) with probability p. For an anisotropic
    Sigma_ii the mean is still 3 and the coverage approximate. Mean NEES above 3 and coverage
    below the level: the uncertainty is too small (overconfident); below 3 and above it: too
    large.

    nees and std hold the judged vertices only (finite positive std). Vertices with a zero or
    non-finite std are left out and counted in `left_out`; of them, those published with a zero
    std and a nonzero error (infinitely overconfident) also in `zero_std_vertices`, so that they
    stay visible instead of vanishing from the mean. Calibrations of several steps or sets are
    pooled per vertex by `pooled`.
    """

    nees: np.ndarray  # (K,) per judged vertex
    std: np.ndarray  # (K,) their published standard deviation (metres)
    left_out: int
    zero_std_vertices: int

    @property
    def vertices(self) -> int:
        """The number of judged vertices."""
        return len(self.nees)

    @property
    def mean_nees(self) -> float:
        """Mean NEES over the judged vertices (3 when calibrated); NaN without any."""
        return float(self.nees.mean()) if self.vertices else float("nan")

    def coverage(self, levels=CALIBRATION_LEVELS) -> np.ndarray:
        """(L,) share of judged vertices inside their ellipsoid of each nominal level (the
        level itself when calibrated); NaN without any vertex."""
        levels = np.asarray(levels, dtype=np.float64)
        if levels.ndim != 1 or not ((levels > 0) & (levels < 1)).all():
            raise ValueError(f"levels must be a 1-D array of values in (0, 1), got {levels}")
        if not self.vertices:
            return np.full(len(levels), np.nan)
        bounds = chi_squared_quantile(levels, _POSITION_DOF)
        return np.count_nonzero(self.nees[:, None] <= bounds[None, :], axis=0) / self.vertices

    @property
    def coverage_95(self) -> float:
        """Share of judged vertices inside their 95 % ellipsoid (0.95 when calibrated)."""
        return float(self.coverage((0.95,))[0])

    @property
    def median_std(self) -> float:
        """Median published std of the judged vertices (metres); NaN without any."""
        return float(np.median(self.std)) if self.vertices else float("nan")

    @property
    def median_error(self) -> float:
        """Median position error |estimate - truth| of the judged vertices (metres, from their
        NEES and std); NaN without any."""
        return float(np.median(np.sqrt(self.nees) * self.std)) if self.vertices else float("nan")

    @classmethod
    def pooled(cls, calibrations) -> Calibration:
        """One calibration over every vertex of `calibrations` (for instance of several steps)."""
        calibrations = list(calibrations)
        return cls(
            nees=np.concatenate([np.zeros(0)] + [c.nees for c in calibrations]),
            std=np.concatenate([np.zeros(0)] + [c.std for c in calibrations]),
            left_out=sum(c.left_out for c in calibrations),
            zero_std_vertices=sum(c.zero_std_vertices for c in calibrations),
        )

    def summary(self, levels=CALIBRATION_LEVELS) -> dict:
        """JSON-ready figures (None for an undefined value): counts, mean NEES, 95 % coverage, the
        median std and median error (metres) and the reliability curve (empirical coverage at the
        nominal levels)."""
        def number(value):
            return float(value) if np.isfinite(value) else None

        return {
            "vertices": self.vertices,
            "left_out": self.left_out,
            "zero_std_vertices": self.zero_std_vertices,
            "mean_nees": number(self.mean_nees),
            "coverage_95": number(self.coverage_95),
            "median_std_m": number(self.median_std),
            "median_error_m": number(self.median_error),
            "reliability": {"nominal": [float(level) for level in levels],
                            "empirical": [number(value) for value in self.coverage(levels)]},
        }


def calibration(estimate, truth, std, vertices=None) -> Calibration:
    """The calibration of per-vertex standard deviations `std` (N,) (metres, as published with
    the estimate: sqrt(trace(Sigma_ii) / 3)) against the errors of `estimate` (N, 3) to `truth`
    (N, 3), over all vertices or the ids `vertices`. A zero or non-finite std leaves its vertex
    out (counted, see Calibration); a negative one is an error."""
    estimate = as_point_array("estimate", estimate)
    truth = as_point_array("truth", truth)
    std = np.asarray(std, dtype=np.float64)
    if estimate.shape != truth.shape:
        raise ValueError(f"estimate {estimate.shape} and truth {truth.shape} differ in shape")
    if std.shape != (len(estimate),):
        raise ValueError(f"std must have shape ({len(estimate)},), got {std.shape}")
    if (std < 0).any():
        raise ValueError("std holds negative values")
    errors = estimate - truth
    if vertices is not None:
        selected = _as_indices("vertices", vertices, len(errors))
        errors, std = errors[selected], std[selected]
    squared_errors = np.einsum("ij,ij->i", errors, errors)
    judged = np.isfinite(std) & (std > 0)
    return Calibration(
        nees=squared_errors[judged] / std[judged] ** 2,
        std=std[judged],
        left_out=int(np.count_nonzero(~judged)),
        zero_std_vertices=int(np.count_nonzero((std == 0) & (squared_errors > 0))),
    )


def sample_surface(vertices, triangles, count: int, seed=0, return_faces: bool = False):
    """`count` points drawn uniformly by area on the triangle surface, deterministic by `seed`
    (an int or a numpy Generator). With return_faces, also the (count,) triangle index of each
    point, so that points can be split by triangle region."""
    vertices = as_point_array("vertices", vertices)
    triangles = as_triangle_array("triangles", triangles, len(vertices))
    if int(count) != count or count < 1:
        raise ValueError(f"count must be a positive integer, got {count}")
    surface = trimesh.Trimesh(vertices, triangles, process=False)
    if not surface.area > 0:
        raise ValueError("surface has zero area; nothing to sample")
    points, faces = trimesh.sample.sample_surface(surface, int(count), seed=seed)
    points = np.asarray(points, dtype=np.float64)
    return (points, np.asarray(faces, dtype=np.int64)) if return_faces else points


def observable_triangles(
    camera_center, measured_points, surface_vertices, surface_triangles
) -> np.ndarray:
    """(F,) bool: triangles first hit by a ray from the camera centre through a measured point.

    Noise along a pixel ray does not change which triangle its ray hits, so noisy depth points
    define the same region as clean ones."""
    camera_center = np.asarray(camera_center, dtype=np.float64)
    if camera_center.shape != (3,):
        raise ValueError(f"camera_center must have shape (3,), got {camera_center.shape}")
    measured_points = as_point_array("measured_points", measured_points)
    if len(measured_points) == 0:
        raise ValueError("measured_points is empty; no observable region can be defined")
    directions = measured_points - camera_center
    if (np.linalg.norm(directions, axis=1) == 0).any():
        raise ValueError("a measured point coincides with the camera centre")
    hits = first_ray_hits(camera_center, directions, surface_vertices, surface_triangles)
    mask = np.zeros(len(surface_triangles), dtype=bool)
    mask[hits.triangles[hits.triangles >= 0]] = True
    return mask


def observed_vertices(triangles, observed_triangles) -> np.ndarray:
    """Sorted ids of vertices of the observed triangles, given as an (F,) bool mask or as
    triangle indices (for instance the closest triangle associated with each measurement)."""
    triangles = np.asarray(triangles)
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"triangles must have shape (F, 3), got {triangles.shape}")
    observed = np.asarray(observed_triangles)
    if observed.dtype == bool:
        if observed.shape != (len(triangles),):
            raise ValueError(
                f"observed triangle mask must have shape ({len(triangles)},), got {observed.shape}"
            )
    else:
        observed = _as_indices("observed_triangles", observed, len(triangles))
    return np.unique(triangles[observed]).astype(np.int64)


def unobserved_external_vertices(surface_vertex_ids, triangles, observed_triangles) -> np.ndarray:
    """Surface vertices not constrained by any measurement: not a corner of any observed
    triangle (the paper's "unobserved external vertices"). Sorted int64 ids."""
    surface_vertex_ids = _as_indices("surface_vertex_ids", surface_vertex_ids, np.inf)
    return np.setdiff1d(surface_vertex_ids, observed_vertices(triangles, observed_triangles))


def summarise(values) -> tuple[float, float]:
    """(mean, standard deviation) of per-step or per-trial values, as the paper's tables report
    (population standard deviation, numpy's default ddof=0)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0:
        raise ValueError("summarise needs at least one value")
    if not np.isfinite(values).all():
        raise ValueError("summarise got non-finite values")
    return float(values.mean()), float(values.std())


def _as_indices(name: str, indices, upper) -> np.ndarray:
    """Return a 1-D int64 index array with values in [0, upper) or raise ValueError."""
    array = np.asarray(indices)
    if array.size == 0:
        return np.zeros(0, dtype=np.int64)
    if array.ndim != 1 or array.dtype == bool or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"{name} must be a 1-D integer array, got {array.dtype} {array.shape}")
    if array.min() < 0 or array.max() >= upper:
        raise ValueError(f"{name} holds indices outside [0, {upper})")
    return array.astype(np.int64)
