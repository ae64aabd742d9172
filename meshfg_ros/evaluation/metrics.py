"""Evaluation metrics of the paper: vertex RMSE, surface distances, observable split; and the
calibration of a published per-vertex uncertainty against the truth.

Surface metrics compare point clouds sampled from meshes: d_RMSE is one-sided (estimate to
reference), d_CD the mean of the two one-sided mean nearest-neighbour distances, d_H95 the
larger of the two one-sided 95th percentiles. The observable split follows the paper's
ex vivo study: rays from the camera centre through the measured (depth) points are cast onto
a surface; the triangles they first hit form the region the depth sensor could observe.
All lengths are in the units of the inputs (metres in this project).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.stats import chi2

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
    ellipsoid (NEES <= chi2.ppf(p, 3)) with probability p. For an anisotropic Sigma_ii the mean
    is still 3 and the coverage approximate. Mean NEES above 3 and coverage below the level:
    the uncertainty is too small (overconfident); below 3 and above it: too large.

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
        bounds = chi2.ppf(levels, _POSITION_DOF)
        return np.count_nonzero(self.nees[:, None] <= bounds[None, :], axis=0) / self.vertices

    @property
    def coverage_95(self) -> float:
        """Share of judged vertices inside their 95 % ellipsoid (0.95 when calibrated)."""
        return float(self.coverage((0.95,))[0])

    @property
    def median_std(self) -> float:
        """Median published std of the judged vertices (metres); NaN without any."""
        return float(np.median(self.std)) if self.vertices else float("nan")

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
        median std (metres) and the reliability curve (empirical coverage at the nominal levels)."""
        def number(value):
            return float(value) if np.isfinite(value) else None

        return {
            "vertices": self.vertices,
            "left_out": self.left_out,
            "zero_std_vertices": self.zero_std_vertices,
            "mean_nees": number(self.mean_nees),
            "coverage_95": number(self.coverage_95),
            "median_std_m": number(self.median_std),
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


@dataclass(frozen=True)
class SurfaceDistances:
    """Nearest-neighbour distances between an estimated and a reference point cloud."""

    estimate_to_reference_mean: float
    reference_to_estimate_mean: float
    chamfer: float  # d_CD: mean of the two one-sided means
    rmse: float  # d_RMSE: one-sided, estimate to reference
    h95: float  # d_H95: max of the two one-sided 95th percentiles


def surface_distances(estimate_points, reference_points) -> SurfaceDistances:
    """The paper's d_CD, d_RMSE and d_H95 between two point clouds (KD-tree nearest neighbours)."""
    estimate_points = as_point_array("estimate_points", estimate_points)
    reference_points = as_point_array("reference_points", reference_points)
    if len(estimate_points) == 0 or len(reference_points) == 0:
        raise ValueError(
            f"surface_distances needs non-empty clouds, got {len(estimate_points)} estimate "
            f"and {len(reference_points)} reference points"
        )
    forward = cKDTree(reference_points).query(estimate_points)[0]
    backward = cKDTree(estimate_points).query(reference_points)[0]
    forward_mean, backward_mean = float(forward.mean()), float(backward.mean())
    return SurfaceDistances(
        estimate_to_reference_mean=forward_mean,
        reference_to_estimate_mean=backward_mean,
        chamfer=0.5 * (forward_mean + backward_mean),
        rmse=float(np.sqrt(np.mean(forward**2))),
        h95=float(max(np.percentile(forward, 95), np.percentile(backward, 95))),
    )


def _measurement_rays(camera_center, measured_points, surface_vertices, surface_triangles):
    """First hits on the surface of rays from the camera centre through each measured point."""
    camera_center = np.asarray(camera_center, dtype=np.float64)
    if camera_center.shape != (3,):
        raise ValueError(f"camera_center must have shape (3,), got {camera_center.shape}")
    measured_points = as_point_array("measured_points", measured_points)
    if len(measured_points) == 0:
        raise ValueError("measured_points is empty; no observable region can be defined")
    directions = measured_points - camera_center
    lengths = np.linalg.norm(directions, axis=1)
    if (lengths == 0).any():
        raise ValueError("a measured point coincides with the camera centre")
    hits = first_ray_hits(camera_center, directions, surface_vertices, surface_triangles)
    unit = directions / lengths[:, None]
    hit = hits.triangles >= 0
    locations = camera_center + unit[hit] * hits.distances[hit, None]
    return hits.triangles[hit], locations


def observable_triangles(
    camera_center, measured_points, surface_vertices, surface_triangles
) -> np.ndarray:
    """(F,) bool: triangles first hit by a ray from the camera centre through a measured point.

    Noise along a pixel ray does not change which triangle its ray hits, so noisy depth points
    define the same region as clean ones."""
    hit_triangles, _ = _measurement_rays(
        camera_center, measured_points, surface_vertices, surface_triangles
    )
    mask = np.zeros(len(surface_triangles), dtype=bool)
    mask[hit_triangles] = True
    return mask


def observable_mask(
    points,
    camera_center,
    measured_points,
    surface_vertices,
    surface_triangles,
    point_faces=None,
    dilation_radius: float = 0.0,
) -> np.ndarray:
    """(P,) bool: which surface sample points lie in the region observable by the camera.

    A point is observable if its triangle (`point_faces`, from sample_surface(...,
    return_faces=True)) was first hit by a measurement ray, or if it lies within
    `dilation_radius` of a ray hit point. Triangle membership is exact for the discretised
    surface but overshoots the seen region by up to one triangle at its rim and leaves holes
    where rays are sparser than triangles; the dilation radius (about the ray spacing on the
    surface) fills such holes. At least one criterion must be given.
    """
    points = as_point_array("points", points)
    if not (np.isfinite(dilation_radius) and dilation_radius >= 0):
        raise ValueError(f"dilation_radius must be finite and non-negative, got {dilation_radius}")
    if point_faces is None and dilation_radius == 0:
        raise ValueError("observable_mask needs point_faces or a positive dilation_radius")
    hit_triangles, hit_locations = _measurement_rays(
        camera_center, measured_points, surface_vertices, surface_triangles
    )
    mask = np.zeros(len(points), dtype=bool)
    if point_faces is not None:
        point_faces = _as_indices("point_faces", point_faces, len(surface_triangles))
        if point_faces.shape != (len(points),):
            raise ValueError(f"point_faces must match points, got shape {point_faces.shape}")
        seen = np.zeros(len(surface_triangles), dtype=bool)
        seen[hit_triangles] = True
        mask |= seen[point_faces]
    if dilation_radius > 0 and len(hit_locations):
        gaps = cKDTree(hit_locations).query(points, distance_upper_bound=dilation_radius)[0]
        mask |= gaps <= dilation_radius
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
