"""Offline replay: the simulator and the estimator run over a recording exactly as the live nodes run.

Both run the same step loop (core/scheduler.py, connected synchronously by OfflinePipeline):
- the initial mesh is the first /meshfg/initial_mesh, or a mesh file (--mesh) placed by the
  parameters mesh_scale, mesh_pose and fixed_* as the nodes place mesh_file;
- transforms (/tf, /tf_static), tool poses and clouds are taken in the order they were logged
  (the order the nodes receive them; at equal log times transforms, then poses, then clouds);
  clouds and tool poses are moved into world_frame at their stamps (core/inputs/world_frame.py, with
  the log time as the clock);
- a cut (/meshfg/remove_elements, element slots) goes to both simulators when it was logged,
  and the estimator follows it with the next prediction (core/scheduler.py);
- the first tool pose of a timeline starts the simulator; each cloud at stamp t is predicted
  from the estimate of the previous cloud with the tool pose interpolated at t, and estimated
  with that prediction and tool pose (the stamp rule, waits and failures are the scheduler's).
Besides the live outputs, the replay runs the simulator open loop from the initial mesh through
the same tool poses (/meshfg/simulation_only_mesh): the "simulation alone" baseline of the
evaluation. Parameters: meshfg_ros/parameters.py; a recording's /meshfg/scenario metadata gives
defaults (model, tool, grasped vertices, noise, estimator overrides), a config mapping and the
factor configuration override them.
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

from meshfg_ros.core.inputs.input_checks import NS_PER_S, SceneError, check_initial_mesh
from meshfg_ros.core.inputs.frames import StampedTransform
from meshfg_ros.core.scheduler import OfflinePipeline, PipelineStep, run_offline
from meshfg_ros.core.inputs.world_frame import CLOUD, POSE, FramedInput
from meshfg_ros.io.tf_messages import TF_STATIC_TOPIC, TF_TOPIC, tf_message_to_transforms
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.parameters import (
    estimator_config,
    load_parameters,
    parameter_names,
    placed_mesh_file,
    read_parameters_file,
    simulator_config,
    world_frame_inputs,
)
from meshfg_ros.core.physics.simulator import SimulatorConfig
from meshfg_ros.io.messages import (
    MeshState,
    PointCloudRecord,
    PoseRecord,
    RosbagsMessageFactory,
    status_record,
    meshfg_typestore,
    vector_msg,
)
from meshfg_ros.io.recording import (
    CorruptRecordingError,
    RecordingExistsError,
    RecordingReader,
    RecordingWriter,
)
from meshfg_ros.markers import mesh_markers, spread_surface_sample, surface_edges
from meshfg_ros.io.scenario_metadata import ScenarioMetadata, read_metadata
from meshfg_ros.topics import (
    BODY_ACCELERATION_TOPIC,
    CAMERA_POSE_TOPIC,
    COST_HISTORY_TOPIC,
    ESTIMATED_MESH_TOPIC,
    INITIAL_MESH_TOPIC,
    MARKERS_TOPIC,
    POINTS_TOPIC,
    PREDICTED_MESH_TOPIC,
    REMOVE_ELEMENTS_TOPIC,
    SCENARIO_TOPIC,
    SIMULATION_ONLY_MESH_TOPIC,
    STATUS_TOPIC,
    TOOL_POSE_TOPIC,
)

FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
# SimulatorConfig fields that are parameters of the nodes -> their parameter names.
SIMULATOR_PARAMETERS = parameter_names(SimulatorConfig)
# Input topics copied verbatim into a replay's output, so that it is self-contained (the
# initial mesh is written as used: the recording's or the --mesh file's).
COPIED_TOPICS = (SCENARIO_TOPIC, CAMERA_POSE_TOPIC, TOOL_POSE_TOPIC, REMOVE_ELEMENTS_TOPIC, POINTS_TOPIC)
# Event kinds: at equal log times transforms first, then poses, then cuts, then clouds.
_TF, _POSE, _CUT, _CLOUD = 0, 1, 2, 3


class ReplayError(ValueError):
    """Recorded inputs the replay cannot run on (one-line message)."""


@dataclass(frozen=True)
class ReplayInputs:
    """What the nodes would receive from a recording: initial mesh, tool poses, clouds (each in
    log-time order, with their log times; empty log times: the stamps)."""

    initial_mesh: TetMesh
    initial_state: MeshState
    poses: tuple[PoseRecord, ...]
    clouds: tuple[PointCloudRecord, ...]
    metadata: ScenarioMetadata | None
    camera_pose: PoseRecord | None
    pose_log_ns: tuple[int, ...] = ()
    cloud_log_ns: tuple[int, ...] = ()
    transforms: tuple[tuple[int, bool, tuple[StampedTransform, ...]], ...] = ()  # (log time, static, /tf content)
    cuts: tuple[tuple[int, np.ndarray], ...] = ()  # (log time, element slots removed)

    def events(self) -> list[tuple[int, int, Any]]:
        """(log time, kind, record) of every transform message, pose and cloud in arrival order:
        by log time, at equal log times transforms, then poses, then clouds, each topic in its
        logged order. A transform message's record is (static, transforms)."""
        poses = self.pose_log_ns or [pose.stamp_ns for pose in self.poses]
        clouds = self.cloud_log_ns or [cloud.stamp_ns for cloud in self.clouds]
        events = [(log_ns, _TF, index) for index, (log_ns, _, _) in enumerate(self.transforms)]
        events += [(log_ns, _POSE, index) for index, log_ns in enumerate(poses)]
        events += [(log_ns, _CUT, index) for index, (log_ns, _) in enumerate(self.cuts)]
        events += [(log_ns, _CLOUD, index) for index, log_ns in enumerate(clouds)]
        records = ([(static, transforms) for _, static, transforms in self.transforms], self.poses,
                   [slots for _, slots in self.cuts], self.clouds)
        return [(log_ns, kind, records[kind][index]) for log_ns, kind, index in sorted(events)]


@dataclass(frozen=True)
class ReplayResult:
    """All steps of a replay, with the parameters it ran with."""

    parameters: dict
    initial_mesh: TetMesh
    steps: tuple[PipelineStep, ...]  # one per estimate

    @property
    def final_estimate(self) -> np.ndarray:
        """(N, 3) positions of the last estimate (the initial mesh if no cloud was replayed)."""
        return self.steps[-1].result.positions if self.steps else self.initial_mesh.vertices


def load_inputs(path: str | Path, mesh_path: str | Path | None = None,
                overrides: Mapping[str, Any] | None = None) -> ReplayInputs:
    """Read the replay's inputs; the initial mesh comes from `mesh_path`, else from the mesh_file
    of `overrides`, if either is given, scaled, placed and with the fixed vertices that the
    replay's parameters select (mesh_scale, mesh_pose, fixed_*, from the recording's defaults
    and `overrides`), as the nodes load mesh_file."""
    mesh_path = mesh_path or (overrides or {}).get("mesh_file") or None
    with RecordingReader(path) as reader:
        reader.require(TOOL_POSE_TOPIC, PoseRecord)
        reader.require(POINTS_TOPIC, PointCloudRecord)
        metadata, camera_pose = _metadata_and_camera(reader)
        if mesh_path is None:
            initial_state = next(iter(reader.records(INITIAL_MESH_TOPIC, MeshState)))
        logged_poses = [(m.log_time_ns, m.data) for m in reader.messages([TOOL_POSE_TOPIC])]
        logged_clouds = [(m.log_time_ns, m.data) for m in reader.messages([POINTS_TOPIC])]
        tf_topics = [topic for topic in (TF_TOPIC, TF_STATIC_TOPIC) if topic in reader.topics]
        transforms = tuple((m.log_time_ns, m.topic == TF_STATIC_TOPIC, tuple(tf_message_to_transforms(m.data)))
                           for m in reader.messages(tf_topics)) if tf_topics else ()
        cuts = ()
        if REMOVE_ELEMENTS_TOPIC in reader.topics:
            cuts = tuple((m.log_time_ns, np.asarray(m.data.data, dtype=np.int64))
                         for m in reader.messages([REMOVE_ELEMENTS_TOPIC]))
    poses = tuple(pose for _, pose in logged_poses)
    clouds = tuple(cloud for _, cloud in logged_clouds)
    if mesh_path is None:
        mesh = initial_state.tet_mesh()
        if mesh.flipped_count:
            raise ReplayError(f"{INITIAL_MESH_TOPIC}: {mesh.flipped_count} tetrahedra have negative volume")
    else:
        placement = _parameters(metadata, camera_pose, overrides)
        mesh = placed_mesh_file({**placement, "mesh_file": str(mesh_path)})
        initial_state = MeshState(poses[0].stamp_ns if poses else 0, placement["world_frame"], 0,
                                  mesh.vertices, mesh.tetrahedra, mesh.surface_triangles, mesh.fixed_vertices)
    try:
        check_initial_mesh(mesh.vertices)
    except SceneError as error:
        raise ReplayError(str(error)) from None
    return ReplayInputs(mesh, initial_state, poses, clouds, metadata, camera_pose,
                        tuple(log_ns for log_ns, _ in logged_poses), tuple(log_ns for log_ns, _ in logged_clouds),
                        transforms, cuts)


def _metadata_and_camera(reader: RecordingReader) -> tuple[ScenarioMetadata | None, PoseRecord | None]:
    """A recording's scenario metadata and camera pose, each None when it has none."""
    camera_pose = None
    if CAMERA_POSE_TOPIC in reader.topics:
        camera_pose = next(iter(reader.records(CAMERA_POSE_TOPIC, PoseRecord)), None)
    return read_metadata(reader), camera_pose


def recording_parameters(path: str | Path) -> dict[str, Any]:
    """The parameter defaults the recording at `path` implies (scenario_parameters), unvalidated."""
    with RecordingReader(path) as reader:
        return scenario_parameters(*_metadata_and_camera(reader))


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
    return _parameters(inputs.metadata, inputs.camera_pose, overrides)


def _parameters(metadata, camera_pose, overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    return load_parameters({**scenario_parameters(metadata, camera_pose), **(overrides or {})})


def iterate_replay(inputs: ReplayInputs, params: Mapping[str, Any],
                   alter_prediction: Callable[[int, np.ndarray], np.ndarray] | None = None) -> Iterator[PipelineStep]:
    """Run the nodes' step loop (core/scheduler.py) over the recorded poses and clouds; yields one
    step per estimate. alter_prediction(stamp, predicted) (fault injection, `meshfg fuzz`) replaces
    each prediction the estimator gets, as a faulty simulation node's message would.

    As the nodes do, inputs go in arrival order into world_frame (a cloud without points, or an
    input /tf cannot place, is dropped); everything else is the schedulers' rule.
    """
    grasped = np.asarray(params["grasped_vertices"], dtype=np.int64) if params["grasped_vertices"] else None
    pipeline = OfflinePipeline(inputs.initial_mesh, simulator_config(params), estimator_config(params), grasped,
                               clock_jump_threshold=params["clock_jump_threshold"],
                               tool_pose_extrapolation=params["tool_pose_horizon"], alter_prediction=alter_prediction)
    yield from run_offline(pipeline, _world_frame_events(inputs, params))


def _world_frame_events(inputs: ReplayInputs, params: Mapping[str, Any]) -> Iterator[tuple]:
    """("pose" | "cloud", stamp, world-frame array, cloud viewpoint or None) of the inputs the nodes would take, in arrival
    order: moved into world_frame through the recorded /tf and /tf_static (or camera_pose) as
    the nodes do (core/inputs/world_frame.py, with the log time as the clock); clouds without points and
    inputs that cannot be placed are dropped."""
    placer = world_frame_inputs(params)
    for log_ns, kind, record in inputs.events():
        now_s = log_ns / NS_PER_S
        if kind == _TF:
            static, transforms = record
            placer.transforms.set_transforms(transforms, static=static)
            placed, _ = placer.release(now_s)
        elif kind == _POSE:
            placed, _ = placer.add(FramedInput(POSE, record.stamp_ns, record.frame_id, record.pose, now_s), now_s)
        elif kind == _CUT:
            placed = []
            yield "cut", log_ns, record, None
        elif len(record.points):
            placed, _ = placer.add(FramedInput(CLOUD, record.stamp_ns, record.frame_id, record.points, now_s), now_s)
        else:
            placed = []
        yield from ((item.kind, item.stamp_ns, item.data, item.viewpoint) for item in placed)
    placed, _ = placer.release(flush=True)
    yield from ((item.kind, item.stamp_ns, item.data, item.viewpoint) for item in placed)


def replay_recording(
    path: str | Path,
    params: Mapping[str, Any] | None = None,
    mesh_path: str | Path | None = None,
) -> ReplayResult:
    """Replay a recording in memory. params: overrides of the recording's defaults."""
    inputs = load_inputs(path, mesh_path, params)
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
                position_std: np.ndarray | None = None, degraded: bool = False,
                position_covariance: np.ndarray | None = None) -> MeshState:
    """A state on `template`'s topology (the initial mesh's, or the cut one's: _cut_template)."""
    return MeshState(stamp_ns, template.frame_id, step, positions, template.tetrahedra,
                     template.surface_triangles, template.fixed_vertices,
                     np.zeros(0) if position_std is None else position_std, degraded,
                     np.zeros((0, 3, 3)) if position_covariance is None else position_covariance,
                     template.invalid_vertices, template.removed_elements)


def _cut_template(initial: MeshState, mesh: TetMesh | None) -> MeshState:
    """The template of a step on `mesh`: the initial state's, or, after a cut, the cut mesh's
    topology (MeshState.of_mesh) in its frame."""
    if mesh is None or not mesh.removed_elements.size:
        return initial
    return MeshState.of_mesh(mesh, initial.stamp_ns, initial.frame_id, 0, initial.positions)


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

    Writes the estimate (with its std and covariance), prediction, open-loop simulation, markers,
    status and LM cost history of every step, and copies the input topics (COPIED_TOPICS)
    verbatim. Returns the message count per topic. progress(iterator, total) may wrap the step iterator (a progress bar).
    The output is finalised also when a step fails, so finished steps stay readable.
    """
    path, out = Path(path), Path(out)
    if out.exists() or out.is_symlink():
        raise RecordingExistsError(f"{out} exists already; recordings are never overwritten")
    inputs = load_inputs(path, mesh_path, params)
    parameters = replay_parameters(inputs, params)
    frame = parameters["world_frame"]
    template = inputs.initial_state
    edges = surface_edges(template.surface_triangles)
    ellipsoid_vertices = spread_surface_sample(template.positions, template.surface_triangles, template.fixed_vertices)
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
            if step.mesh is not None and not np.array_equal(step.mesh.removed_elements, template.removed_elements):
                template = _cut_template(inputs.initial_state, step.mesh)
                edges = surface_edges(template.surface_triangles)
                ellipsoid_vertices = spread_surface_sample(template.positions, template.surface_triangles,
                                                           template.fixed_vertices)
            if step.predicted is not None:
                writer.write(PREDICTED_MESH_TOPIC, _mesh_state(template, step.predicted, step.stamp_ns, index))
            if step.simulation_only is not None:
                writer.write(SIMULATION_ONLY_MESH_TOPIC,
                             _mesh_state(template, step.simulation_only, step.stamp_ns, index))
            writer.write(ESTIMATED_MESH_TOPIC,
                         _mesh_state(template, result.positions, step.stamp_ns, result.step, result.position_std,
                                     result.degraded, result.position_covariance))
            writer.write(STATUS_TOPIC, status_record(result, frame))
            if step.body_acceleration is not None:
                writer.write(BODY_ACCELERATION_TOPIC, vector_msg(step.stamp_ns, frame, step.body_acceleration))
            _cost_history(writer, np.asarray(result.cost_history, dtype=np.float64), step.stamp_ns)
            writer.write(MARKERS_TOPIC, mesh_markers(
                result.positions, template.surface_triangles, result.position_std, step.points, frame,
                step.stamp_ns, parameters["marker_std_max"], edges, position_covariance=result.position_covariance,
                ellipsoid_vertices=ellipsoid_vertices), step.stamp_ns)
        copy_until(float("inf"))
        return dict(writer.counts)
