"""The paper's evaluation of a replay against the ground truth of a synthetic recording.

Methods compared, per step and at the final step (the paper evaluates "the final step output"):
- factor_graph: /meshfg/estimated_mesh of the replay.
- simulation: /meshfg/simulation_only_mesh of the replay, the simulator run open loop from
  the initial mesh through the tool poses (the "tissue simulation" alone; not the one-step
  predictions, which restart from each estimate).
- measurements: the measured cloud itself as the reconstruction (the paper's "MDE" row), on
  the observable region only.

Surface metrics are the paper's d_CD, d_RMSE and d_H95 with one refinement: `samples` points
drawn by area on each surface are measured against the *other surface* (exact closest point on
its triangles, core.geometry.closest_point) instead of against the other surface's samples: the
dense-cloud limit of the paper's nearest-neighbour definition, without its sampling floor
(between two 10 000-point clouds, about 0.1 mm on the 2 cm tumour and 1 cm on the 1 m cube).
The measured cloud, not being a surface, is the target of nearest-point queries in the
measurements row. Faces whose three vertices are all fixed are left out: they are boundary
conditions, exact by construction (the paper excludes the tumour-airway interface for this
reason). The observable region is split as in the paper: rays from the camera centre through
the step's measured points, cast onto each surface; the faces they first hit are observable.
Scenes without a camera (the cubes) use the faces the measurements were drawn from.
Vertex RMSE (the paper's Table I) needs vertex correspondence, so it is computed only when the
replay used the recording's mesh; fixed vertices are left out of every set for the same reason
as fixed faces. "Unobserved external" vertices are free surface vertices on no observed face.
With vertex correspondence and a published position_std, the calibration of the factor graph's
uncertainty (metrics.calibration: NEES, coverage of its ellipsoids, median std) over all free
vertices and the observed and unobserved external ones, per step, at the final step and pooled
over the steps from CALIBRATION_POOLED_FROM_STEP on.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from meshfg_ros.core.geometry.closest_point import ClosestPointIndex
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.evaluation.metrics import (
    Calibration,
    calibration,
    correction_alignment,
    observable_triangles,
    sample_surface,
    unobserved_external_vertices,
    vertex_rmse,
)
from meshfg_ros.io.messages import MeshState, PointCloudRecord, PoseRecord
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.io.scenario_metadata import read_metadata
from meshfg_ros.topics import (
    CAMERA_POSE_TOPIC,
    ESTIMATED_MESH_TOPIC,
    GROUND_TRUTH_TOPIC,
    POINTS_TOPIC,
    PREDICTED_MESH_TOPIC,
    SIMULATION_ONLY_MESH_TOPIC,
)

METHOD_TITLES = {"factor_graph": "Factor Graph", "simulation": "Simulation", "measurements": "Measurements"}
REGIONS = ("full", "unobserved", "observable")
SURFACE_METRICS = ("chamfer", "rmse", "h95")
VERTEX_SETS = ("all", "external", "unobserved_external")
# Where the factor graph's correction of each prediction is compared with the truth's
# (metrics.correction_alignment): observed external vertices along their normal (what the
# measurements see) and across it, and the unobserved external ones (the prior's extrapolation).
CORRECTION_SETS = ("observed_normal", "observed_tangential", "unobserved_external")
CORRECTION_QUANTITIES = ("alignment", "gain")  # the keys of metrics.correction_alignment
# Where the factor graph's published position_std is compared with its actual errors
# (metrics.calibration): all free vertices, the external ones the measurements constrain, and
# the unobserved external ones (the uncertainty should be larger there than where it is seen).
CALIBRATION_SETS = ("all", "observed_external", "unobserved_external")
# The pooled calibration starts at this step (the first evaluated step is 1): it leaves out the
# start-up, where the window fills from the initial mesh.
CALIBRATION_POOLED_FROM_STEP = 3
DEFAULT_SAMPLES = 10_000
_UNDEFINED = {metric: float("nan") for metric in SURFACE_METRICS}  # a region empty at some step


class EvaluationError(ValueError):
    """Recordings that cannot be evaluated against each other (one-line message)."""


@dataclass(frozen=True)
class EvaluationInputs:
    """Everything the evaluation reads from a replay output and a ground-truth recording.

    stamps: evaluated steps (stamps present in the estimate and the truth, step > 0).
    estimates: method -> stamp -> (N', 3) positions on the estimate's topology `estimate_mesh`.
    predictions: stamp -> (N', 3) the prediction each estimate started from (the replay's
    /meshfg/predicted_mesh; empty when the replay has none).
    observed_faces: (F,) bool on the truth's surface for camera-less scenes, else None.
    position_std: stamp -> (N',) the factor graph's published per-vertex std (metres), for the
    stamps whose estimate carries one.
    truth_meshes, estimate_meshes (method -> stamp -> MeshState): each step's topology, which a
    cut changes (removed elements, invalid vertices, the surface with the wound); the invalid
    vertices of the truth's step are left out of every vertex set.
    """

    scenario: str
    stamps: tuple[int, ...]
    truth_mesh: MeshState
    truth: dict[int, np.ndarray]
    estimate_mesh: MeshState
    estimates: dict[str, dict[int, np.ndarray]]
    predictions: dict[int, np.ndarray]
    clouds: dict[int, np.ndarray]
    camera_center: np.ndarray | None
    observed_faces: np.ndarray | None
    position_std: dict[int, np.ndarray] = field(default_factory=dict)
    truth_meshes: dict[int, MeshState] = field(default_factory=dict)
    estimate_meshes: dict[str, dict[int, MeshState]] = field(default_factory=dict)

    def truth_at(self, stamp: int) -> MeshState:
        """The truth's mesh state at `stamp` (its topology: the first one's when not recorded)."""
        return self.truth_meshes.get(stamp, self.truth_mesh)

    def estimate_at(self, method: str, stamp: int) -> MeshState:
        """The estimate's mesh state of `method` at `stamp` (the first one's topology when not recorded)."""
        return self.estimate_meshes.get(method, {}).get(stamp, self.estimate_mesh)

    @functools.cached_property
    def truth_tet_mesh(self) -> TetMesh:
        """The truth's topology as a core mesh (its vertex normals), made once."""
        return self.truth_mesh.tet_mesh()

    @property
    def same_topology(self) -> bool:
        """Whether estimate and truth share vertices one to one (vertex RMSE is defined)."""
        a, b = self.estimate_mesh, self.truth_mesh
        return a.tetrahedra.shape == b.tetrahedra.shape and bool(np.array_equal(a.tetrahedra, b.tetrahedra))


def mesh_states(reader: RecordingReader, topic: str) -> list[MeshState]:
    """Every mesh of a topic, in log order (EvaluationError when it holds none)."""
    states = list(reader.records(topic, MeshState))
    if not states:
        raise EvaluationError(f"{reader.path}: topic {topic} holds no meshes")
    return states


def mesh_series(reader: RecordingReader, topic: str) -> tuple[MeshState, dict[int, np.ndarray]]:
    """The first mesh of a topic and stamp -> positions of every mesh on it."""
    states = mesh_states(reader, topic)
    return states[0], _positions(states)


def _positions(states: list[MeshState]) -> dict[int, np.ndarray]:
    """stamp -> positions of the states."""
    return {state.stamp_ns: state.positions for state in states}


def _cut_states(states: list[MeshState]) -> dict[int, MeshState]:
    """stamp -> state of the states whose topology a cut changed."""
    return {state.stamp_ns: state for state in states if state.removed_elements.size}


def load_inputs(replay_path: str | Path, truth_path: str | Path) -> EvaluationInputs:
    """Read the replay output and the ground truth; check that they belong together."""
    with RecordingReader(truth_path) as truth_reader:
        truth_states = mesh_states(truth_reader, GROUND_TRUTH_TOPIC)
        truth_mesh, truth = truth_states[0], _positions(truth_states)
        metadata = read_metadata(truth_reader)
        camera_center = None
        if CAMERA_POSE_TOPIC in truth_reader.topics:
            camera_center = next(iter(truth_reader.records(CAMERA_POSE_TOPIC, PoseRecord))).pose[:3].copy()
    with RecordingReader(replay_path) as replay_reader:
        estimated_states = mesh_states(replay_reader, ESTIMATED_MESH_TOPIC)
        estimate_mesh, estimated = estimated_states[0], _positions(estimated_states)
        position_std = {state.stamp_ns: state.position_std for state in estimated_states if state.position_std.size}
        estimates = {"factor_graph": estimated}
        estimate_meshes = {"factor_graph": _cut_states(estimated_states)}
        if SIMULATION_ONLY_MESH_TOPIC in replay_reader.topics:
            simulated_states = mesh_states(replay_reader, SIMULATION_ONLY_MESH_TOPIC)
            estimates["simulation"] = _positions(simulated_states)
            estimate_meshes["simulation"] = _cut_states(simulated_states)
        predictions = {}
        if PREDICTED_MESH_TOPIC in replay_reader.topics:
            predictions = mesh_series(replay_reader, PREDICTED_MESH_TOPIC)[1]
        clouds = {cloud.stamp_ns: cloud.points for cloud in replay_reader.records(POINTS_TOPIC, PointCloudRecord)}
    stamps = tuple(sorted(
        stamp for stamp in set(estimated) & set(truth) & set(clouds)
        if stamp != truth_mesh.stamp_ns and all(stamp in series for series in estimates.values())
    ))
    if not stamps:
        raise EvaluationError(
            f"no step of {replay_path} has an estimate, a cloud and a ground truth of {truth_path} at the same stamp"
        )
    observed_faces = None
    truth_meshes = _cut_states(truth_states)
    if camera_center is None and metadata is not None and metadata.observed_triangles is not None and not truth_meshes:
        observed_faces = np.zeros(len(truth_mesh.surface_triangles), bool)
        observed_faces[list(metadata.observed_triangles)] = True
    return EvaluationInputs(
        scenario=metadata.scenario if metadata is not None else Path(truth_path).name,
        stamps=stamps,
        truth_mesh=truth_mesh,
        truth=truth,
        estimate_mesh=estimate_mesh,
        estimates=estimates,
        predictions=predictions,
        clouds=clouds,
        camera_center=camera_center,
        observed_faces=observed_faces,
        position_std=position_std,
        truth_meshes=truth_meshes,
        estimate_meshes=estimate_meshes,
    )


def evaluated_faces(mesh: MeshState) -> np.ndarray:
    """(F,) bool: surface faces with at least one free vertex (all-fixed faces are excluded)."""
    fixed = np.zeros(len(mesh.positions), bool)
    fixed[mesh.fixed_vertices] = True
    return ~fixed[mesh.surface_triangles].all(axis=1)


class _Surface:
    """One surface state for the metrics: its evaluated faces, split by observability, and
    area-uniform samples on them.

    observed: (F,) bool over all surface faces (None when no split is known). With a camera
    it is recomputed on this very surface (rays through the step's measured points).
    """

    def __init__(self, mesh: MeshState, positions: np.ndarray, samples: int, seed: int,
                 camera_center: np.ndarray | None, cloud: np.ndarray, observed_faces: np.ndarray | None):
        self.positions = positions
        self.triangles = mesh.surface_triangles
        self.evaluated = evaluated_faces(mesh)
        faces = np.flatnonzero(self.evaluated)
        self.points, local_faces = sample_surface(positions, self.triangles[faces], samples, seed=seed,
                                                  return_faces=True)
        self.point_faces = faces[local_faces]
        if camera_center is not None:
            observed_faces = observable_triangles(camera_center, cloud, positions, self.triangles)
        self.observed = observed_faces

    def faces(self, region: str) -> np.ndarray:
        """(F,) bool: the evaluated faces of `region` (full, observable or unobserved)."""
        if region == "full":
            return self.evaluated
        return self.evaluated & (self.observed if region == "observable" else ~self.observed)

    def in_region(self, region: str) -> np.ndarray:
        """(P,) bool: which samples lie on the region's faces."""
        return self.faces(region)[self.point_faces]

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest evaluated face (index into all surface faces) and exact distance per point."""
        evaluated = np.flatnonzero(self.evaluated)
        association = ClosestPointIndex(self.positions, self.triangles[evaluated]).associate(points)
        return evaluated[association.triangle], association.distance

    def distances_to(self, points: np.ndarray, region: str, nearest: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Exact distance from each point to the region's faces, given nearest(points): only points
        whose closest evaluated face lies outside the region need a new query."""
        faces = self.faces(region)
        closest_face, distances = nearest
        outside = ~faces[closest_face]
        if outside.any():
            distances = distances.copy()
            index = ClosestPointIndex(self.positions, self.triangles[faces])
            distances[outside] = index.associate(points[outside]).distance
        return distances


def _statistics(forward: np.ndarray, backward: np.ndarray) -> dict[str, float]:
    """d_CD, d_RMSE, d_H95 of one-sided distances (forward: estimate -> reference)."""
    return {
        "chamfer": 0.5 * float(forward.mean() + backward.mean()),
        "rmse": float(np.sqrt(np.mean(forward**2))),
        "h95": float(max(np.percentile(forward, 95), np.percentile(backward, 95))),
    }


def _surface_metrics(estimate: _Surface, reference: _Surface, regions: list[str]) -> dict[str, dict]:
    """Per region: the estimate's samples against the reference's faces and vice versa, exactly."""
    forward_nearest = reference.nearest(estimate.points)
    backward_nearest = estimate.nearest(reference.points)
    metrics = {}
    for region in regions:
        forward, backward = estimate.in_region(region), reference.in_region(region)
        if not forward.any() or not backward.any() or not reference.faces(region).any() \
                or not estimate.faces(region).any():
            metrics[region] = dict(_UNDEFINED)
            continue
        metrics[region] = _statistics(
            reference.distances_to(estimate.points[forward], region, tuple(a[forward] for a in forward_nearest)),
            estimate.distances_to(reference.points[backward], region, tuple(a[backward] for a in backward_nearest)),
        )
    return metrics


def _cloud_metrics(cloud: np.ndarray, reference: _Surface) -> dict[str, float]:
    """The measured cloud as the reconstruction of the observable region: the cloud to the true
    surface exactly, the true surface's samples to their nearest measured point."""
    backward_points = reference.points[reference.in_region("observable")]
    if len(cloud) == 0 or len(backward_points) == 0:
        return dict(_UNDEFINED)
    forward = reference.distances_to(cloud, "observable", reference.nearest(cloud))
    return _statistics(forward, cKDTree(cloud).query(backward_points)[0])


def evaluate_step(inputs: EvaluationInputs, stamp: int, samples: int = DEFAULT_SAMPLES, seed: int = 0) -> dict:
    """Metrics of one step: {'surface': {method: {region: {metric: m}}}, 'vertex_rmse': {method: {set: m}}},
    and, where vertices and the observed region are defined and the replay has predictions,
    'correction': {set: {quantity: value}} (CORRECTION_SETS; NaN for a step without a prediction,
    so that every step keeps its place in the per-step lists); where vertices are defined and the
    replay publishes a position_std, 'calibration': {set: metrics.Calibration} of the factor
    graph (CALIBRATION_SETS, the external ones where the observed region is known; None for a
    step whose estimate has no std)."""
    cloud = inputs.clouds[stamp]
    truth_mesh = inputs.truth_at(stamp)
    reference = _Surface(truth_mesh, inputs.truth[stamp], samples, seed, inputs.camera_center, cloud,
                         inputs.observed_faces)
    regions = REGIONS if reference.observed is not None else ("full",)
    surface: dict[str, dict] = {}
    for index, (method, series) in enumerate(inputs.estimates.items(), start=1):
        estimate = _Surface(inputs.estimate_at(method, stamp), series[stamp], samples, seed + index,
                            inputs.camera_center, cloud,
                            inputs.observed_faces if inputs.same_topology else None)
        usable = [r for r in regions if r == "full" or estimate.observed is not None]
        surface[method] = _surface_metrics(estimate, reference, usable)
    if "observable" in regions:
        surface["measurements"] = {"observable": _cloud_metrics(cloud, reference)}
    vertex: dict[str, dict] = {}
    if inputs.same_topology:
        mesh = truth_mesh
        free = mesh.free_vertices
        external = np.intersect1d(np.unique(mesh.surface_triangles), free)
        sets = {"all": free, "external": external}
        if reference.observed is not None:
            sets["unobserved_external"] = np.intersect1d(
                unobserved_external_vertices(external, mesh.surface_triangles, reference.observed), free)
        for method, series in inputs.estimates.items():
            vertex[method] = {
                name: (vertex_rmse(series[stamp], inputs.truth[stamp], ids) if len(ids) else float("nan"))
                for name, ids in sets.items()
            }
    step = {"surface": surface, "vertex_rmse": vertex}
    if inputs.same_topology and inputs.position_std:
        step["calibration"] = _calibration(inputs, stamp, sets)
    if inputs.same_topology and reference.observed is not None and inputs.predictions:
        step["correction"] = (_correction(inputs, stamp, external, sets["unobserved_external"])
                              if stamp in inputs.predictions else
                              {name: dict.fromkeys(CORRECTION_QUANTITIES, float("nan")) for name in CORRECTION_SETS})
    return step


def _correction(inputs: EvaluationInputs, stamp: int, external: np.ndarray, unobserved: np.ndarray) -> dict:
    """The factor graph's correction of the step's prediction against the truth's, per CORRECTION_SETS."""
    prediction, estimate, truth = inputs.predictions[stamp], inputs.estimates["factor_graph"][stamp], inputs.truth[stamp]
    normals = inputs.truth_tet_mesh.without_elements(inputs.truth_at(stamp).removed_elements).vertex_normals(prediction)
    observed = np.setdiff1d(external, unobserved)
    return {  # NaN for an empty set (correction_alignment)
        "observed_normal": correction_alignment(prediction, estimate, truth, observed, normals),
        "observed_tangential": correction_alignment(prediction, estimate, truth, observed, normals, across=True),
        "unobserved_external": correction_alignment(prediction, estimate, truth, unobserved),
    }


def _calibration(inputs: EvaluationInputs, stamp: int, sets: dict[str, np.ndarray]) -> dict:
    """The factor graph's calibration on CALIBRATION_SETS at one step (None each without a std)."""
    named = {"all": sets["all"]}
    if "unobserved_external" in sets:
        named["observed_external"] = np.setdiff1d(sets["external"], sets["unobserved_external"])
        named["unobserved_external"] = sets["unobserved_external"]
    std = inputs.position_std.get(stamp)
    return {name: None if std is None else calibration(inputs.estimates["factor_graph"][stamp], inputs.truth[stamp],
                                                        std, ids)
            for name, ids in named.items()}


def _calibration_summary(per_step: list[Calibration | None]) -> dict:
    """final / pooled (the per-vertex NEES of steps CALIBRATION_POOLED_FROM_STEP..last together;
    None with fewer steps) / per_step, each a Calibration.summary() or None."""
    pooled = [c for c in per_step[CALIBRATION_POOLED_FROM_STEP - 1:] if c is not None]
    return {
        "final": None if per_step[-1] is None else per_step[-1].summary(),
        "pooled": Calibration.pooled(pooled).summary() if pooled else None,
        "per_step": [None if c is None else c.summary() for c in per_step],
    }


def _unobserved_over_observed(sets: dict, when: str, figure: str) -> float | None:
    """A Calibration.summary() figure (median std or median error) of the unobserved external
    vertices over that of the observed ones."""
    unobserved, observed = (sets[name][when] for name in ("unobserved_external", "observed_external"))
    if unobserved is None or observed is None or unobserved[figure] is None or not observed[figure]:
        return None
    return unobserved[figure] / observed[figure]


def _summary(values: list[float]) -> dict:
    """final / mean / std (population, as the paper) over steps, ignoring steps without a value."""
    finite = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
    return {
        "final": values[-1] if np.isfinite(values[-1]) else None,
        "mean": float(finite.mean()) if finite.size else None,
        "std": float(finite.std()) if finite.size else None,
        "per_step": [v if np.isfinite(v) else None for v in values],
    }


def evaluate(inputs: EvaluationInputs, samples: int = DEFAULT_SAMPLES, seed: int = 0, progress=None) -> dict:
    """Evaluate every step; JSON-ready dict of summaries (metres) keyed like evaluate_step.

    progress: optional callable wrapping the iterable of stamps (e.g. tqdm).
    """
    stamps = inputs.stamps if progress is None else progress(inputs.stamps)
    steps = [evaluate_step(inputs, stamp, samples, seed) for stamp in stamps]

    surface = {
        method: {region: {metric: _summary([s["surface"][method][region][metric] for s in steps])
                          for metric in SURFACE_METRICS}
                 for region in regions}
        for method, regions in steps[0]["surface"].items()
    }
    vertex = {
        method: {name: _summary([s["vertex_rmse"][method][name] for s in steps]) for name in sets}
        for method, sets in steps[0]["vertex_rmse"].items()
    }
    result = {
        "scenario": inputs.scenario,
        "units": "m",
        "samples_per_surface": samples,
        "stamps_ns": list(inputs.stamps),
        "surface": surface,
        "vertex_rmse": vertex,
    }
    if "calibration" in steps[0]:
        sets = {name: _calibration_summary([s["calibration"][name] for s in steps])
                for name in CALIBRATION_SETS if name in steps[0]["calibration"]}
        result["calibration"] = {"method": "factor_graph", "pooled_from_step": CALIBRATION_POOLED_FROM_STEP,
                                 "sets": sets}
        if "unobserved_external" in sets:
            for ratio, figure in (("std_ratio_unobserved_observed", "median_std_m"),
                                  ("error_ratio_unobserved_observed", "median_error_m")):
                result["calibration"][ratio] = {
                    when: _unobserved_over_observed(sets, when, figure) for when in ("final", "pooled")}
    corrected = [s["correction"] for s in steps if "correction" in s]
    if corrected:
        result["correction"] = {
            name: {quantity: _summary([c[name][quantity] for c in corrected]) for quantity in CORRECTION_QUANTITIES}
            for name in CORRECTION_SETS
        }
    return result


def evaluate_recordings(replay_path: str | Path, truth_path: str | Path, samples: int = DEFAULT_SAMPLES,
                        progress=None) -> dict:
    """load_inputs + evaluate, with the recordings' paths in the result."""
    result = evaluate(load_inputs(replay_path, truth_path), samples, progress=progress)
    return {"replay": str(replay_path), "truth": str(truth_path), **result}


def _cell(summary: dict | None) -> str:
    """'final (mean ± std)' in millimetres, or n/a."""
    if summary is None or summary["final"] is None:
        return "n/a"
    return f"{summary['final'] * 1e3:.2f} ({summary['mean'] * 1e3:.2f}±{summary['std'] * 1e3:.2f})"


def _table(title: str, columns: list[tuple[str, str]], rows: list[tuple[str, list[dict | None]]]) -> str:
    """Fixed-width text table: a title line, a two-level header (group, name), one row per method."""
    cells = [[_cell(value) for value in values] for _, values in rows]
    width = max([len(c) for row in cells for c in row] + [len(f"{g} {n}") for g, n in columns])
    label_width = max(len(label) for label, _ in rows)
    lines = [title, " " * label_width + "  " + "  ".join(f"{g} {n}".rjust(width) for g, n in columns)]
    for (label, _), row in zip(rows, cells):
        lines.append(label.ljust(label_width) + "  " + "  ".join(c.rjust(width) for c in row))
    return "\n".join(lines)


def format_tables(evaluation: dict) -> str:
    """The paper's Tables II and III (and Table I's vertex RMSE) as text, in millimetres, and
    the calibration of the factor graph's published std.

    Each cell is the final-step value, then mean ± std over the evaluated steps (calibration:
    then the value pooled over the steps from CALIBRATION_POOLED_FROM_STEP on).
    """
    surface, vertex = evaluation["surface"], evaluation["vertex_rmse"]
    names = {"chamfer": "d_CD", "rmse": "d_RMSE", "h95": "d_H95"}
    steps = len(evaluation["stamps_ns"])
    note = f"mm; final step ({steps} steps: mean ± std)"
    blocks = [f"Scenario {evaluation['scenario']}: {note}"]
    estimated = [m for m in ("simulation", "factor_graph") if m in surface]
    split = [r for r in ("full", "unobserved") if all(r in surface[m] for m in estimated)]
    columns = [(region.capitalize(), names[metric]) for region in split for metric in SURFACE_METRICS]
    blocks.append(_table(
        "Table II: full and unobserved surface",
        columns,
        [(METHOD_TITLES[m], [surface[m][r][k] for r in split for k in SURFACE_METRICS]) for m in estimated],
    ))
    observable = [m for m in ("simulation", "factor_graph", "measurements") if "observable" in surface.get(m, {})]
    if observable:
        blocks.append(_table(
            "Table III: observable region",
            [("Observable", names[metric]) for metric in SURFACE_METRICS],
            [(METHOD_TITLES[m], [surface[m]["observable"][k] for k in SURFACE_METRICS]) for m in observable],
        ))
    if vertex:
        sets = [s for s in VERTEX_SETS if all(s in vertex[m] for m in vertex)]
        blocks.append(_table(
            "Vertex RMSE (free vertices)",
            [("Vertices", name.replace("_", " ")) for name in sets],
            [(METHOD_TITLES[m], [vertex[m][s] for s in sets]) for m in ("simulation", "factor_graph") if m in vertex],
        ))
    if "correction" in evaluation:
        lines = ["Correction of each prediction by the factor graph against the truth's "
                 "(alignment 1: towards the truth, -1: away; gain: share made): final step (mean over steps)"]
        for name, quantities in evaluation["correction"].items():
            lines.append(f"  {name.replace('_', ' ')}: " + ", ".join(
                f"{quantity} {_ratio_cell(summary)}" for quantity, summary in quantities.items()))
        blocks.append("\n".join(lines))
    if "calibration" in evaluation:
        blocks.append(format_calibration(evaluation["calibration"], steps))
    return "\n\n".join(blocks)


def format_calibration(calibration_: dict, steps: int) -> str:
    """The calibration block of format_tables: per vertex set, final step (pooled over the steps
    from the section's pooled_from_step to `steps`), and the unobserved / observed ratios of the
    median std and of the median error."""
    first = calibration_["pooled_from_step"]
    pooled = f"steps {first}-{steps}" if steps >= first else f"needs {first} steps"
    columns = (("vertices", lambda c: f"{c['vertices']}"), ("mean NEES", lambda c: _number(c["mean_nees"], 2)),
               ("95 % coverage", lambda c: _number(c["coverage_95"], 3)),
               ("median std (mm)", lambda c: _number(c["median_std_m"], 4, 1e3)),
               ("median error (mm)", lambda c: _number(c["median_error_m"], 4, 1e3)),
               ("zero std", lambda c: f"{c['zero_std_vertices']}"), ("left out", lambda c: f"{c['left_out']}"))
    rows = [(name.replace("_", " "), [f"{_figure(sets['final'], cell)} ({_figure(sets['pooled'], cell)})"
                                      for _, cell in columns])
            for name, sets in calibration_["sets"].items()]
    width = max([len(c) for _, cells in rows for c in cells] + [len(title) for title, _ in columns])
    label_width = max(len(label) for label, _ in rows)
    lines = [f"Calibration of the factor graph's position_std (NEES = |error|^2 / std^2; calibrated: mean NEES 3, "
             f"95 % coverage 0.95): final step ({pooled} pooled)",
             " " * label_width + "  " + "  ".join(title.rjust(width) for title, _ in columns)]
    lines += [label.ljust(label_width) + "  " + "  ".join(c.rjust(width) for c in cells) for label, cells in rows]
    if "std_ratio_unobserved_observed" in calibration_:
        ratio = calibration_["std_ratio_unobserved_observed"]
        errors = calibration_["error_ratio_unobserved_observed"]
        lines.append(f"median std, unobserved external over observed external: {_number(ratio['final'], 2)} "
                     f"({_number(ratio['pooled'], 2)}) (above 1: less certain where unobserved); median error: "
                     f"{_number(errors['final'], 2)} ({_number(errors['pooled'], 2)})")
    return "\n".join(lines)


def _figure(summary: dict | None, cell) -> str:
    """One calibration figure of a Calibration.summary(), or n/a."""
    return "n/a" if summary is None else cell(summary)


def _number(value: float | None, digits: int, scale: float = 1.0) -> str:
    return "n/a" if value is None else f"{value * scale:.{digits}f}"


def _ratio_cell(summary: dict) -> str:
    final = "n/a" if summary["final"] is None else f"{summary['final']:.2f}"
    mean = "n/a" if summary["mean"] is None else f"{summary['mean']:.2f}"
    return f"{final} ({mean})"


def write_json(evaluation: dict, path: str | Path) -> None:
    """Write the evaluation as JSON to a new file (never overwrites: FileExistsError)."""
    with open(path, "x", encoding="utf-8") as stream:
        json.dump(evaluation, stream, indent=2)
        stream.write("\n")
