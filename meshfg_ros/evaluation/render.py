"""Pictures of a replay: estimate vs truth, measurements, error per step, convergence.

matplotlib Figure objects drawn by Agg (no pyplot state, no display needed).

- estimate.png: the final estimate's surface (fixed faces left out), coloured per vertex by its
  error against the truth (factor graph beside the simulation alone, one colour scale), or by
  the posterior standard deviation when no truth is given.
- measurements.png: the final step's measured points over the estimated surface.
- error_per_step.png (needs the truth): Chamfer distance on the full and unobserved surface and
  vertex RMSE per step, factor graph vs simulation alone.
- convergence.png: Levenberg-Marquardt cost per iteration of every step (from the replay's
  cost history; initial and final cost from the status otherwise) and iterations per step.
Files are created exclusively: nothing existing is overwritten.
reliability_figure and calibration_figure draw reliability diagrams of the published std's
calibration (evaluation.metrics.Calibration), for `meshfg eval --calibration-plot` and the
accuracy suite.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from meshfg_ros.evaluation.evaluate import evaluate_recordings, evaluated_faces
from meshfg_ros.io.messages import MeshState, PointCloudRecord, StatusRecord
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.topics import (
    COST_HISTORY_TOPIC,
    ESTIMATED_MESH_TOPIC,
    GROUND_TRUTH_TOPIC,
    POINTS_TOPIC,
    SIMULATION_ONLY_MESH_TOPIC,
    STATUS_TOPIC,
)

_MM = 1e3
_DPI = 110


class OutputDirectoryError(ValueError):
    """The output directory exists and is not empty, or is not a directory."""


def prepare_output_directory(path: str | Path) -> Path:
    """Create `path` (parents too); an existing one must be an empty directory."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        if not path.is_dir():
            raise OutputDirectoryError(f"{path} exists and is not a directory")
        if any(path.iterdir()):
            raise OutputDirectoryError(f"{path} exists and is not empty; outputs are never overwritten")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _save(figure: Figure, path: Path) -> Path:
    with open(path, "xb") as stream:  # exclusive: never overwrite
        figure.savefig(stream, format="png", dpi=_DPI, bbox_inches="tight")
    return path


def _series(reader: RecordingReader, topic: str) -> list[MeshState]:
    return list(reader.records(topic, MeshState)) if topic in reader.topics else []


def _surface_axes(axes, positions: np.ndarray, triangles: np.ndarray, vertex_values: np.ndarray | None,
                  norm, cmap: str, title: str, extra_points: np.ndarray | None = None):
    """Draw triangles on 3D axes, face colour = mean of its vertex values (grey if None); the
    axes span the triangles and extra_points (mm)."""
    corners = positions[triangles] * _MM
    if vertex_values is None:
        faces = Poly3DCollection(corners, facecolors=(0.75, 0.75, 0.78, 0.35), edgecolors=(0.3, 0.3, 0.3, 0.3),
                                 linewidths=0.2)
    else:
        colours = matplotlib.colormaps[cmap](norm(vertex_values[triangles].mean(axis=1)))
        faces = Poly3DCollection(corners, facecolors=colours, edgecolors=(0.2, 0.2, 0.2, 0.25), linewidths=0.2)
    axes.add_collection3d(faces)
    spanned = corners.reshape(-1, 3) if extra_points is None else np.vstack([corners.reshape(-1, 3), extra_points])
    low, high = spanned.min(axis=0), spanned.max(axis=0)
    axes.set_xlim(low[0], high[0])
    axes.set_ylim(low[1], high[1])
    axes.set_zlim(low[2], high[2])
    axes.set_box_aspect(np.maximum(high - low, 1e-9))
    axes.set_xlabel("x (mm)")
    axes.set_ylabel("y (mm)")
    axes.set_zlabel("z (mm)")
    axes.set_title(title)


def _estimate_figure(estimates: dict[str, MeshState], truth: MeshState | None, faces: np.ndarray) -> Figure:
    figure = Figure(figsize=(6 * len(estimates), 5.2))
    if truth is not None:
        errors = {name: np.linalg.norm(state.positions - truth.positions, axis=1) * _MM
                  for name, state in estimates.items()}
        norm = Normalize(0.0, max(float(e.max()) for e in errors.values()) or 1.0)
        cmap, label = "viridis", "vertex error (mm)"
    else:
        errors = {name: (state.position_std * _MM if state.position_std.size else None)
                  for name, state in estimates.items()}
        known = [e for e in errors.values() if e is not None]
        norm = Normalize(0.0, max([float(e.max()) for e in known] + [1e-9]))
        cmap, label = "coolwarm", "posterior std (mm)"
    for index, (name, state) in enumerate(estimates.items(), start=1):
        axes = figure.add_subplot(1, len(estimates), index, projection="3d")
        values = errors[name]
        summary = "" if values is None or truth is None else \
            f"\nfree-vertex RMSE {np.sqrt(np.mean(np.delete(values, state.fixed_vertices) ** 2)):.2f} mm"
        _surface_axes(axes, state.positions, faces, values, norm, cmap, f"{name}, step {state.step}{summary}")
    figure.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=figure.axes, shrink=0.6, label=label)
    return figure


def _measurement_figure(estimate: MeshState, faces: np.ndarray, cloud: PointCloudRecord) -> Figure:
    figure = Figure(figsize=(7, 5.5))
    axes = figure.add_subplot(projection="3d", computed_zorder=False)  # points drawn over the surface
    points = cloud.points * _MM
    _surface_axes(axes, estimate.positions, faces, None, None, "",
                  f"measured points over the estimate, step {estimate.step} ({len(points)} points)", points)
    axes.scatter(points[:, 0], points[:, 1], points[:, 2], s=2.0, c="darkgreen", depthshade=False, zorder=3)
    return figure


def _error_figure(evaluation: dict) -> Figure:
    seconds = (np.asarray(evaluation["stamps_ns"]) - evaluation["stamps_ns"][0]) / 1e9
    panels = [("surface", "full", "chamfer", "d_CD, full surface"),
              ("surface", "unobserved", "chamfer", "d_CD, unobserved surface"),
              ("vertex_rmse", None, "all", "vertex RMSE, free vertices")]
    panels = [p for p in panels if any(_values(evaluation, p, m) is not None for m in ("factor_graph", "simulation"))]
    figure = Figure(figsize=(4.8 * len(panels), 3.8), layout="tight")
    axes_list = figure.subplots(1, len(panels), squeeze=False)
    for axes, panel in zip(axes_list[0], panels):
        for method, style in (("simulation", "--o"), ("factor_graph", "-o")):
            values = _values(evaluation, panel, method)
            if values is not None:
                axes.plot(seconds, values, style, label=method.replace("_", " "), markersize=3)
        axes.set_title(panel[3])
        axes.set_xlabel("time since first step (s)")
        axes.set_ylabel("mm")
        axes.grid(alpha=0.3)
        axes.legend()
    return figure


def _values(evaluation: dict, panel: tuple, method: str) -> np.ndarray | None:
    section, region, metric, _ = panel
    entry = evaluation[section].get(method, {})
    entry = entry.get(region, {}) if region is not None else entry
    if metric not in entry:
        return None
    return np.asarray([np.nan if v is None else v * _MM for v in entry[metric]["per_step"]])


def reliability_figure(panels: dict[str, dict[str, dict | None]]) -> Figure:
    """Reliability diagrams, one panel per title -> {label: reliability}: the share of vertices
    inside their ellipsoid of each nominal level against the level, one line per label, over the
    diagonal a calibrated uncertainty follows (below it: too small, above it: too large). A
    reliability is Calibration.summary()["reliability"]; a label without one (None) is left out."""
    figure = Figure(figsize=(4.6 * len(panels), 4.4), layout="tight")
    for axes, (title, curves) in zip(figure.subplots(1, len(panels), squeeze=False)[0], panels.items()):
        axes.plot([0.0, 1.0], [0.0, 1.0], color="k", lw=1, label="calibrated")
        for label, reliability in curves.items():
            if reliability is not None:
                empirical = [np.nan if value is None else value for value in reliability["empirical"]]
                axes.plot(reliability["nominal"], empirical, "-o", markersize=3, label=label)
        axes.set_xlim(0.0, 1.0)
        axes.set_ylim(0.0, 1.02)
        axes.set_aspect("equal")
        axes.set_xlabel("nominal level of the ellipsoid")
        axes.set_ylabel("share of vertices inside it")
        axes.set_title(title)
        axes.grid(alpha=0.3)
        axes.legend(fontsize=7)
    return figure


def calibration_figure(evaluation: dict) -> Figure:
    """Reliability diagrams of an evaluation's calibration section: one panel per vertex set,
    its final step and its pooled steps."""
    section = evaluation["calibration"]
    first, steps = section["pooled_from_step"], len(evaluation["stamps_ns"])
    panels = {
        f"{name.replace('_', ' ')} vertices": {
            "final step": None if sets["final"] is None else sets["final"]["reliability"],
            f"steps {first}-{steps} pooled": None if sets["pooled"] is None else sets["pooled"]["reliability"],
        }
        for name, sets in section["sets"].items()
    }
    figure = reliability_figure(panels)
    figure.suptitle(f"{evaluation['scenario']}: calibration of the factor graph's position_std")
    return figure


def write_calibration_plot(evaluation: dict, path: str | Path) -> Path:
    """calibration_figure as a new PNG file (never overwritten)."""
    return _save(calibration_figure(evaluation), Path(path))


def _convergence_figure(statuses: list[StatusRecord], histories: list[np.ndarray]) -> Figure:
    figure = Figure(figsize=(10, 3.8), layout="tight")
    cost_axes, iteration_axes = figure.subplots(1, 2)
    colours = matplotlib.colormaps["viridis"](np.linspace(0, 1, max(len(statuses), 1)))
    for status, history, colour in zip(statuses, histories, colours):
        costs = history if history.size else np.array([status.initial_cost, status.final_cost])
        cost_axes.semilogy(np.arange(len(costs)), np.maximum(costs, 1e-300), "-o", color=colour, markersize=2)
    cost_axes.set_xlabel("Levenberg-Marquardt iteration")
    cost_axes.set_ylabel("cost")
    cost_axes.set_title("cost per iteration (one line per step; light = late)")
    cost_axes.grid(alpha=0.3)
    steps = [s.step for s in statuses]
    iteration_axes.bar(steps, [s.iterations for s in statuses],
                       color=["tab:red" if not s.converged else "tab:blue" for s in statuses])
    iteration_axes.set_xlabel("step")
    iteration_axes.set_ylabel("iterations")
    iteration_axes.set_title("iterations per step (red: not converged)")
    return figure


def render(replay_path: str | Path, out_dir: str | Path, truth_path: str | Path | None = None,
           evaluation: dict | None = None) -> list[Path]:
    """Write the PNGs of a replay into the new (or empty) directory out_dir; returns their paths:
    the estimate, the last cloud on it, with a truth the error per step and the reliability
    diagrams of the published std (where the replay publishes it on the truth's mesh), and the
    convergence.

    evaluation: a result of evaluation.evaluate_recordings for the same pair (computed from
    truth_path when None and a truth is given).
    """
    with RecordingReader(replay_path) as reader:
        estimated = list(reader.records(ESTIMATED_MESH_TOPIC, MeshState))
        simulated = _series(reader, SIMULATION_ONLY_MESH_TOPIC)
        clouds = {c.stamp_ns: c for c in reader.records(POINTS_TOPIC, PointCloudRecord)} \
            if POINTS_TOPIC in reader.topics else {}
        statuses = list(reader.records(STATUS_TOPIC, StatusRecord)) if STATUS_TOPIC in reader.topics else []
        histories = ([np.asarray(m.data.data, dtype=np.float64) for m in reader.messages([COST_HISTORY_TOPIC])]
                     if COST_HISTORY_TOPIC in reader.topics else [np.zeros(0)] * len(statuses))
    final = estimated[-1]
    truth = None
    if truth_path is not None:
        with RecordingReader(truth_path) as reader:
            truth = {s.stamp_ns: s for s in reader.records(GROUND_TRUTH_TOPIC, MeshState)}.get(final.stamp_ns)
        if evaluation is None:
            evaluation = evaluate_recordings(replay_path, truth_path)
        if truth is not None and len(truth.positions) != len(final.positions):
            truth = None  # another mesh than the truth's: no per-vertex error
    out = prepare_output_directory(out_dir)
    faces = final.surface_triangles[evaluated_faces(final)]
    estimates = {"factor graph": final}
    final_simulated = [s for s in simulated if s.stamp_ns == final.stamp_ns]
    if final_simulated and truth is not None:
        estimates["simulation alone"] = final_simulated[0]
    written = [_save(_estimate_figure(estimates, truth, faces), out / "estimate.png")]
    if final.stamp_ns in clouds:
        written.append(_save(_measurement_figure(final, faces, clouds[final.stamp_ns]), out / "measurements.png"))
    if evaluation is not None:
        written.append(_save(_error_figure(evaluation), out / "error_per_step.png"))
        if "calibration" in evaluation:  # the published std against the truth (reliability diagrams)
            written.append(_save(calibration_figure(evaluation), out / "calibration.png"))
    if statuses:
        written.append(_save(_convergence_figure(statuses, histories), out / "convergence.png"))
    return written

