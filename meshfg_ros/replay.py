"""Offline replay: the simulator and the estimator run over a recording as the live nodes run.

Semantics shared with meshfg_ros.nodes (the loop below is the reference the nodes' end-to-end
test compares against):
- the initial mesh is the first /meshfg/initial_mesh (or a mesh file);
- tool poses in stamp order: the first resets the simulator (no prediction); each later pose
  gives predicted = simulator.predict(latest estimate, pose, dt = stamp difference in s);
- a cloud at stamp t pairs with the prediction stamped t (at equal stamps the pose comes
  first); estimate = estimator.update(t, points in world_frame, predicted or None);
  the estimate is the state the next prediction starts from.
Besides the live outputs, the replay runs the simulator open loop from the initial mesh
through the same tool poses (/meshfg/simulation_only_mesh): the "simulation alone" baseline of
the evaluation. Parameters: the table of core.parameters; a recording's /meshfg/scenario
metadata gives defaults (model, tool, grasped vertices, noise, estimator overrides), a config
mapping and the factor configuration override them.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.highlevel import AnyReader

from meshfg_ros.core.estimator import SlidingWindowEstimator, StepResult
from meshfg_ros.core.mesh import TetMesh, load_mesh
from meshfg_ros.core.parameters import (
    cloud_to_world,
    estimator_config,
    load_parameters,
    read_parameters_file,
    simulator_config,
)
from meshfg_ros.core.simulator import SimulatorConfig, XpbdSimulator
from meshfg_ros.io.messages import (
    MeshState,
    PointCloudRecord,
    PoseRecord,
    RosbagsMessageFactory,
    StatusRecord,
    meshfg_typestore,
)
from meshfg_ros.io.recording import (
    CorruptRecordingError,
    RecordingExistsError,
    RecordingReader,
    RecordingWriter,
)
from meshfg_ros.markers import mesh_markers, surface_edges
from meshfg_ros.synth import ScenarioMetadata, read_metadata
from meshfg_ros.topics import (
    CAMERA_POSE_TOPIC,
    COST_HISTORY_TOPIC,
    ESTIMATED_MESH_TOPIC,
    INITIAL_MESH_TOPIC,
    MARKERS_TOPIC,
    POINTS_TOPIC,
    PREDICTED_MESH_TOPIC,
    SCENARIO_TOPIC,
    SIMULATION_ONLY_MESH_TOPIC,
    STATUS_TOPIC,
    TOOL_POSE_TOPIC,
)

FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
# SimulatorConfig fields that are parameters of the nodes, by parameter name.
SIMULATOR_PARAMETERS = {
    "youngs_modulus": "youngs_modulus",
    "poisson_ratio": "poisson_ratio",
    "density": "density",
    "tool_radius": "tool_radius",
    "tool_mode": "tool_mode",
    "substeps": "simulator_substeps",
    "solver_iterations": "simulator_iterations",
    "solver": "simulator",
}
# Input topics copied verbatim into a replay's output, so that it is self-contained (the
# initial mesh is written as used: the recording's or the --mesh file's).
COPIED_TOPICS = (SCENARIO_TOPIC, CAMERA_POSE_TOPIC, TOOL_POSE_TOPIC, POINTS_TOPIC)
_NS_PER_S = 1e9


class ReplayError(ValueError):
    """Recorded inputs the replay cannot run on (one-line message)."""


@dataclass(frozen=True)
class ReplayInputs:
    """What the nodes would receive from a recording: initial mesh, tool poses, clouds."""

    initial_mesh: TetMesh
    initial_state: MeshState
    poses: tuple[PoseRecord, ...]
    clouds: tuple[PointCloudRecord, ...]
    metadata: ScenarioMetadata | None
    camera_pose: PoseRecord | None


@dataclass(frozen=True)
class ReplayStep:
    """One estimator update: its cloud (world frame), prediction, open-loop simulation, result."""

    stamp_ns: int
    points: np.ndarray
    predicted: np.ndarray | None
    simulation_only: np.ndarray | None
    result: StepResult


@dataclass(frozen=True)
class ReplayResult:
    """All steps of a replay, with the parameters it ran with."""

    parameters: dict
    initial_mesh: TetMesh
    steps: tuple[ReplayStep, ...]

    @property
    def final_estimate(self) -> np.ndarray:
        """(N, 3) positions of the last estimate (the initial mesh if no cloud was replayed)."""
        return self.steps[-1].result.positions if self.steps else self.initial_mesh.vertices


def load_inputs(path: str | Path, mesh_path: str | Path | None = None) -> ReplayInputs:
    """Read the replay's inputs; the initial mesh comes from `mesh_path` if given."""
    with RecordingReader(path) as reader:
        reader.require(TOOL_POSE_TOPIC, PoseRecord)
        reader.require(POINTS_TOPIC, PointCloudRecord)
        metadata = read_metadata(reader)
        camera_pose = None
        if CAMERA_POSE_TOPIC in reader.topics:
            camera_pose = next(iter(reader.records(CAMERA_POSE_TOPIC, PoseRecord)))
        if mesh_path is None:
            initial_state = next(iter(reader.records(INITIAL_MESH_TOPIC, MeshState)))
        poses = tuple(sorted(reader.records(TOOL_POSE_TOPIC, PoseRecord), key=lambda p: p.stamp_ns))
        clouds = tuple(sorted(reader.records(POINTS_TOPIC, PointCloudRecord), key=lambda c: c.stamp_ns))
    if mesh_path is None:
        mesh = TetMesh(initial_state.positions, initial_state.tetrahedra, initial_state.fixed_vertices)
        if mesh.flipped_count:
            raise ReplayError(f"{INITIAL_MESH_TOPIC}: {mesh.flipped_count} tetrahedra have negative volume")
    else:
        mesh = load_mesh(mesh_path)
        initial_state = MeshState(poses[0].stamp_ns if poses else 0, clouds[0].frame_id if clouds else "world", 0,
                                  mesh.vertices, mesh.tetrahedra, mesh.surface_triangles, mesh.fixed_vertices)
    stamps = [pose.stamp_ns for pose in poses]
    repeated = [a for a, b in zip(stamps, stamps[1:]) if a == b]
    if repeated:
        raise ReplayError(f"{TOOL_POSE_TOPIC} has two poses at stamp {repeated[0]} ns")
    return ReplayInputs(mesh, initial_state, poses, clouds, metadata, camera_pose)


def scenario_parameters(metadata: ScenarioMetadata | None, camera_pose: PoseRecord | None = None) -> dict[str, Any]:
    """Parameter defaults a recording implies: its nominal model, tool, noise and overrides.

    Raises ReplayError when the nominal model sets a simulator field that no parameter of the
    nodes expresses (e.g. gravity) to a non-default value: the replay could not honour it.
    """
    mapping: dict[str, Any] = {}
    if camera_pose is not None:
        mapping["camera_pose"] = list(camera_pose.pose)
    if metadata is None:
        return mapping
    defaults = asdict(SimulatorConfig())
    for field_name, value in metadata.simulator.items():
        if field_name in SIMULATOR_PARAMETERS:
            mapping[SIMULATOR_PARAMETERS[field_name]] = value
        elif field_name not in defaults or not np.array_equal(np.asarray(value), np.asarray(defaults[field_name])):
            raise ReplayError(f"{SCENARIO_TOPIC}: the nominal model sets {field_name} = {value!r}, "
                              "which no parameter of the nodes expresses")
    mapping["measurement_sigma"] = metadata.noise_sigma_m
    if metadata.grasped_vertices:
        mapping["grasped_vertices"] = list(metadata.grasped_vertices)
    mapping.update(metadata.estimator_overrides)
    return mapping


def config_overrides(path: str | Path) -> dict[str, Any]:
    """The parameters a YAML file sets (validated): a flat mapping, or the `/**` section of a
    ROS 2 parameters file."""
    validated = read_parameters_file(path)
    document = yaml.safe_load(Path(path).read_text()) or {}
    section = document.get("/**")
    if isinstance(section, Mapping) and "ros__parameters" in section:
        document = section["ros__parameters"] or {}
    return {key: validated[key] for key in document if key in validated}


def replay_parameters(inputs: ReplayInputs, overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Validated parameters: defaults < the recording's scenario metadata < `overrides`."""
    return load_parameters({**scenario_parameters(inputs.metadata, inputs.camera_pose), **(overrides or {})})


def iterate_replay(inputs: ReplayInputs, params: Mapping[str, Any]) -> Iterator[ReplayStep]:
    """Run the nodes' loop over the recorded poses and clouds; yields one step per used cloud.

    As the nodes do: a failed or non-finite prediction resets the simulator to its pose and
    the cloud's step runs degraded without one; clouds without points, and clouds whose stamp
    is not newer than the previous cloud's, are skipped.
    """
    mesh = inputs.initial_mesh
    grasped = np.asarray(params["grasped_vertices"], dtype=np.int64) if params["grasped_vertices"] else None
    model = simulator_config(params)
    simulator = XpbdSimulator(mesh, model, grasped_vertices=grasped)
    open_loop = XpbdSimulator(mesh, model, grasped_vertices=grasped)
    estimator = SlidingWindowEstimator(mesh, estimator_config(params))
    estimate = mesh.vertices
    simulation_only = mesh.vertices
    predictions: dict[int, np.ndarray] = {}
    tool_poses: dict[int, np.ndarray] = {}
    open_loop_states: dict[int, np.ndarray] = {}
    previous_pose_stamp: int | None = None
    previous_cloud_stamp: int | None = None
    # Pose events (kind 0) sort before cloud events (kind 1) of the same stamp.
    events = sorted([(pose.stamp_ns, 0, pose) for pose in inputs.poses]
                    + [(cloud.stamp_ns, 1, cloud) for cloud in inputs.clouds], key=lambda e: e[:2])
    for stamp, kind, record in events:
        if kind == 0:
            if previous_pose_stamp is None:
                simulator.reset(record.pose)
                open_loop.reset(record.pose)
            else:
                dt = (stamp - previous_pose_stamp) / _NS_PER_S
                predicted = _predict(simulator, estimate, record.pose, dt)
                if predicted is not None:
                    predictions[stamp] = predicted
                advanced = _predict(open_loop, simulation_only, record.pose, dt)
                if advanced is not None:  # a failed open-loop step leaves the baseline where it was
                    simulation_only = advanced
                open_loop_states[stamp] = simulation_only
            previous_pose_stamp = stamp
            tool_poses[stamp] = record.pose
            continue
        if len(record.points) == 0 or (previous_cloud_stamp is not None and stamp <= previous_cloud_stamp):
            continue
        previous_cloud_stamp = stamp
        points = cloud_to_world(record.points, record.frame_id, params)
        predicted = predictions.pop(stamp, None)
        for older in [s for s in predictions if s < stamp]:
            del predictions[older]
        result = estimator.update(stamp, points, predicted, tool_poses.pop(stamp, None))
        for older in [s for s in tool_poses if s < stamp]:
            del tool_poses[older]
        estimate = result.positions
        yield ReplayStep(stamp, points, predicted, open_loop_states.get(stamp), result)


def _predict(simulator: XpbdSimulator, state: np.ndarray, pose: np.ndarray, dt: float) -> np.ndarray | None:
    """simulator.predict, or None (with the simulator reset to `pose`) when it fails, as the node does."""
    try:
        predicted = simulator.predict(state, pose, dt)
    except (ValueError, RuntimeError):
        simulator.reset(pose)
        return None
    if not np.isfinite(predicted).all():
        simulator.reset(pose)
        return None
    return predicted


def replay_recording(
    path: str | Path,
    params: Mapping[str, Any] | None = None,
    mesh_path: str | Path | None = None,
) -> ReplayResult:
    """Replay a recording in memory. params: overrides of the recording's defaults."""
    inputs = load_inputs(path, mesh_path)
    parameters = replay_parameters(inputs, params)
    return ReplayResult(parameters, inputs.initial_mesh, tuple(iterate_replay(inputs, parameters)))


def _raw_messages(path: Path, topics: tuple[str, ...]) -> list[tuple[str, int, Any]]:
    """(topic, log time, decoded rosbags message) of `topics`, in time order, unconverted."""
    try:
        with AnyReader([path], default_typestore=meshfg_typestore()) as reader:
            connections = [c for c in reader.connections if c.topic in topics]
            return [(c.topic, log_time, reader.deserialize(raw, c.msgtype))
                    for c, log_time, raw in reader.messages(connections=connections)]
    except Exception as error:  # anything a parser raises on these bytes means a bad file
        raise CorruptRecordingError(f"{path} is corrupt: {' '.join(str(error).split())}") from None


def _mesh_state(template: MeshState, positions: np.ndarray, stamp_ns: int, step: int,
                position_std: np.ndarray | None = None) -> MeshState:
    return MeshState(stamp_ns, template.frame_id, step, positions, template.tetrahedra,
                     template.surface_triangles, template.fixed_vertices,
                     np.zeros(0) if position_std is None else position_std)


def status_record(result: StepResult, frame_id: str) -> StatusRecord:
    """The EstimatorStatus record of one update (shared by the replay and the estimator node)."""
    return StatusRecord(
        stamp_ns=result.stamp_ns, frame_id=frame_id, step=result.step, iterations=result.iterations,
        initial_cost=result.initial_cost, final_cost=result.final_cost, solve_time_ms=result.solve_time_ms,
        num_points=result.num_points, num_points_rejected=result.num_points_rejected,
        window_size=result.window_size, converged=result.converged, degraded=result.degraded,
        message=result.message,
    )


def _cost_history(writer: RecordingWriter, history: np.ndarray, stamp_ns: int) -> None:
    factory = RosbagsMessageFactory()
    layout = factory.make("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    message = factory.make(FLOAT64_MULTI_ARRAY, layout=layout, data=factory.sequence(history, np.float64))
    writer.write(COST_HISTORY_TOPIC, message, stamp_ns)


def write_replay(
    path: str | Path,
    out: str | Path,
    params: Mapping[str, Any] | None = None,
    mesh_path: str | Path | None = None,
    progress: Callable[[Iterator, int], Iterator] | None = None,
) -> dict[str, int]:
    """Replay recording `path` and write the outputs to the new recording `out`.

    Writes the estimate, prediction, open-loop simulation, markers, status and LM cost history
    of every step, and copies the input topics (COPIED_TOPICS) verbatim. Returns the message
    count per topic. progress(iterator, total) may wrap the step iterator (a progress bar).
    The output is finalised also when a step fails, so finished steps stay readable.
    """
    path, out = Path(path), Path(out)
    if out.exists() or out.is_symlink():
        raise RecordingExistsError(f"{out} exists already; recordings are never overwritten")
    inputs = load_inputs(path, mesh_path)
    parameters = replay_parameters(inputs, params)
    frame = parameters["world_frame"]
    template = inputs.initial_state
    edges = surface_edges(template.surface_triangles)
    steps = iterate_replay(inputs, parameters)
    if progress is not None:
        steps = progress(steps, len(inputs.clouds))
    copied = deque(_raw_messages(path, COPIED_TOPICS))
    with RecordingWriter(out, compress=True) as writer:

        def copy_until(stamp_ns: float) -> None:
            """Write the copied messages logged up to stamp_ns (keeps the output in time order)."""
            while copied and copied[0][1] <= stamp_ns:
                topic, log_time, message = copied.popleft()
                writer.write(topic, message, log_time)

        copy_until(template.stamp_ns)
        writer.write(INITIAL_MESH_TOPIC, template)

        for index, step in enumerate(steps, start=1):
            copy_until(step.stamp_ns)
            result = step.result
            if step.predicted is not None:
                writer.write(PREDICTED_MESH_TOPIC, _mesh_state(template, step.predicted, step.stamp_ns, index))
            if step.simulation_only is not None:
                writer.write(SIMULATION_ONLY_MESH_TOPIC,
                             _mesh_state(template, step.simulation_only, step.stamp_ns, index))
            writer.write(ESTIMATED_MESH_TOPIC,
                         _mesh_state(template, result.positions, step.stamp_ns, result.step, result.position_std))
            writer.write(STATUS_TOPIC, status_record(result, frame))
            _cost_history(writer, np.asarray(result.cost_history, dtype=np.float64), step.stamp_ns)
            writer.write(MARKERS_TOPIC, mesh_markers(
                result.positions, template.surface_triangles, result.position_std, step.points, frame,
                step.stamp_ns, parameters["marker_std_max"], edges), step.stamp_ns)
        copy_until(float("inf"))
        return dict(writer.counts)
