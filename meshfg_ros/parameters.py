"""The parameters of meshfg_ros, derived from the configuration dataclasses' fields.

A field made with core.settings.setting is a parameter: its default, description, range,
choices, name and whether it is dynamic are written once, on the field. The core's
SimulatorConfig and EstimatorConfig hold the model's settings; the small dataclasses below hold
the nodes' own (frames, the initial mesh file, timeouts, markers, playback). Each node declares
the parameters of the configurations it reads (NODE_CONFIGURATIONS): simulator settings go to
the simulation node, estimator settings to the estimator node, and a parameter of both (the
tissue model, the tool) to both. sim_bridge_server declares only what its open-loop simulator
reads: the simulator's settings but the learning switches (OpenLoopSimulatorConfig), the grasp,
the initial mesh and the tool_pose QoS. `simulator_config` / `estimator_config` build the core
configurations from parameter values by the same fields.

`load_parameters` checks a mapping (unknown key, wrong type, out of range -> ParameterError
naming the key) and fills in defaults, for the whole pipeline (the offline replay's --config) or
for one node. config/meshfg.yaml lists every parameter of the pipeline with its default (a test
keeps the two in sync).

`world_frame_inputs` builds the placement of clouds and tool poses into world_frame
(core/inputs/world_frame.py) the nodes and the replay share: /tf, with the static `camera_pose` as the
fallback for `camera_frame`; `placed_mesh_file` loads mesh_file as the mesh parameters place it.
"""

from __future__ import annotations

import difflib
import functools
import re
import textwrap
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from meshfg_ros.core.estimation.estimator import EstimatorConfig
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.inputs.patient_mesh import Box, FixedSelection, Plane, prepare_mesh
from meshfg_ros.core.inputs.pose_history import InvalidPoseError, as_pose, pose_matrix
from meshfg_ros.core.inputs.frames import TransformBuffer
from meshfg_ros.core.inputs.input_checks import DEFAULT_CLOCK_JUMP_THRESHOLD_S
from meshfg_ros.core.scheduler import (
    MAX_PREDICTION_WAIT_S,
    PREDICTION_TIMES_KEPT,
    PREDICTION_WAIT_MARGIN,
    SchedulingTimeouts,
)
from meshfg_ros.core.inputs.world_frame import DEFAULT_TRANSFORM_WAIT_S, WorldFrameInputs
from meshfg_ros.core.settings import (
    SETTING_TYPES,
    Setting,
    bound_text,
    checked_value,
    setting,
    setting_type,
    settings_of,
)
from meshfg_ros.core.physics.simulator import SimulatorConfig
from meshfg_ros.core.inputs.tool_poses import DEFAULT_EXTRAPOLATION_HORIZON_S

__all__ = [
    "NODE_CONFIGURATIONS",
    "PARAMETERS",
    "EstimatorNodeConfig",
    "GraspConfig",
    "InitialMeshConfig",
    "OpenLoopSimulatorConfig",
    "Parameter",
    "ParameterError",
    "PlaybackConfig",
    "SharedNodeConfig",
    "SimulationNodeConfig",
    "ToolClearanceConfig",
    "ToolPoseSubscriptionConfig",
    "check_parameter_names",
    "config_changes",
    "config_from_parameters",
    "default_parameters",
    "estimator_changes",
    "estimator_config",
    "load_mesh_file",
    "placed_mesh_file",
    "load_parameters",
    "node_parameters",
    "parameter_names",
    "parameters_help",
    "parameters_yaml",
    "read_parameters_file",
    "shared_settings",
    "simulator_config",
]

# Parameters every rclpy node declares itself: accepted in a parameters file and ignored.
_ROS_OWN_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})
_PARAMS_KEY = "ros__parameters"
# A ROS 2 topic or service name (rcl's rules): relative, absolute or private (~), tokens of
# alphanumerics and '_' not starting with a digit, {substitutions} allowed.
_ROS_NAME = re.compile(r"(~/?|/)?[A-Za-z_{][A-Za-z0-9_{}]*(/[A-Za-z_{][A-Za-z0-9_{}]*)*")


class ParameterError(ValueError):
    """A parameter that is unknown, of the wrong type or out of range (names the key)."""


@dataclass(frozen=True)
class Parameter:
    """One parameter: name, default, description, type (core.settings.SETTING_TYPES) and valid range.

    range: inclusive (low, high) of the value (of each element for arrays); None = unbounded
    (either bound may be None). choices: the allowed strings. length: required array length.
    dynamic: may change while the node runs (else read once at start-up).
    """

    name: str
    default: Any
    description: str
    type: str
    range: tuple[float | None, float | None] | None = None
    choices: tuple[str, ...] | None = None
    length: int | None = None
    dynamic: bool = False

    def __post_init__(self) -> None:
        if self.type not in SETTING_TYPES:
            raise ParameterError(f"{self.name}: unknown parameter type {self.type!r}")

    def validate(self, value: Any) -> Any:
        """`value` converted to this parameter's canonical Python type, or ParameterError: the
        settings' validator (core.settings.checked_value), which the configurations use too.

        An integer is accepted for a double (also in arrays): `-p measurement_sigma:=1` means 1.0.
        """
        return checked_value(self.name, value, self.type, self.range, self.choices, self.length, ParameterError)

    def summary(self) -> str:
        """Type, default, range or choices, and whether dynamic, for --help."""
        default = list(self.default) if isinstance(self.default, tuple) else self.default
        parts = [self.type, f"default {default!r}" if self.type == "string" else f"default {default}"]
        if self.range is not None:
            low, high = self.range
            parts.append(f"range [{bound_text(low, '-inf')}, {bound_text(high, 'inf')}]")
        if self.choices is not None:
            parts.append(f"one of: {', '.join(self.choices)}")
        if self.length is not None:
            parts.append(f"{self.length} values")
        parts.append("dynamic" if self.dynamic else "read-only")
        return ", ".join(parts)


def _check_quaternion(name: str, pose: tuple[float, ...]) -> None:
    """A pose [x, y, z, qx, qy, qz, qw] that is not one (pose_history.as_pose) is refused."""
    try:
        as_pose(pose)
    except InvalidPoseError as error:
        raise ParameterError(f"{name}: {error}") from None


# ------------------------------------------------------------------ the nodes' own settings
@dataclass(frozen=True)
class OpenLoopSimulatorConfig(SimulatorConfig):
    """The simulator settings of sim_bridge_server. Its simulator runs open loop from its own
    state, as the authors' simulator does: no estimate reaches it, so it learns neither a body
    load nor the Poisson ratio, and those switches are plain fields here, off, not parameters."""

    estimate_body_load: bool = False
    estimate_poisson_ratio: bool = False


@dataclass(frozen=True)
class GraspConfig:
    """The vertices the tool holds in grasp mode: a setting of each node that runs the simulator
    (the simulation node, sim_bridge_server), checked against tool_mode by load_parameters."""

    grasped_vertices: tuple[int, ...] = setting(
        (), "Mesh vertex indices held by the tool (grasp mode only).", type="integer_array", range=(0, None))


@dataclass(frozen=True)
class SimulationNodeConfig:
    """Settings of the simulation node beyond the simulator's and the grasp."""

    estimate_timeout: float = setting(
        SchedulingTimeouts.estimate_timeout, "Seconds (wall time) a prediction request waits for the estimate of the previous request before it "
        "is predicted from the newest state the node has.", range=(0.0, 60.0))
    newest_first: bool = setting(
        True, "When the pipeline falls behind the clouds, predict the newest cloud from the newest estimate and "
        "skip the clouds between (counted as clouds_skipped_behind); false: predict every cloud in order, "
        "however late (the offline replay's estimates, for recordings played faster than real time).")
    blade_half_extents: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), "Half extents [x, y, z] in metres of the tool's blade, a box in the tool frame about "
        "blade_offset: at each tool pose the elements reaching into it, and the pieces that leaves hanging, are "
        "cut away (core/geometry/topology.py); zeros: the tool does not cut.", range=(0.0, 1.0), length=3)
    blade_offset: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), "Centre [x, y, z] of the blade box in the tool frame, metres.", range=(-1.0, 1.0), length=3)
    tool_pose_timeout: float = setting(
        SchedulingTimeouts.tool_pose_timeout, "Seconds (wall time) a prediction request waits for a tool pose stamped at or after its cloud; "
        "then the pose is extrapolated within tool_pose_horizon, or the step runs without a prediction.",
        range=(0.0, 60.0))


@dataclass(frozen=True)
class EstimatorNodeConfig:
    """Settings of the estimator node beyond the estimator's: the camera, input QoS and timing, markers."""

    camera_frame: str = setting(
        "camera", "The depth camera's frame, placed in world_frame by the static camera_pose when /tf does not "
        "know it (clouds in every other frame are placed through /tf and /tf_static). Its origin is the "
        "viewpoint of every cloud: points against faces turned away from it are dropped as leaks, and each "
        "point's noise is weighted by its ray's incidence on the surface.")
    camera_pose: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), "Static pose of camera_frame in world_frame: [x, y, z, qx, qy, qz, qw] "
        "(the fallback when /tf does not know camera_frame).", range=(-1e3, 1e3), length=7)
    points_reliable: bool = setting(
        False, "Subscribe to points with reliable QoS (depth 100): for recordings played back by bag_player, "
        "where every cloud counts; false: the sensor-data profile of live cameras (best effort, depth 5), which "
        "drops clouds the transport loses when the CPU is saturated.")
    prediction_timeout: float = setting(
        SchedulingTimeouts.prediction_timeout, "Seconds (wall time) a cloud waits at least for its simulator prediction "
        "before the step runs degraded without it; longer while the simulator's recent predictions took longer "
        f"({PREDICTION_WAIT_MARGIN:g}x the longest of the last {PREDICTION_TIMES_KEPT}, at most "
        f"{MAX_PREDICTION_WAIT_S:g} s); up to {MAX_PREDICTION_WAIT_S:g} s while a simulation node publishes and "
        f"fewer than {PREDICTION_TIMES_KEPT} of its prediction times are known (its set-up on the mesh).",
        range=(0.0, 60.0))
    prediction_source: str = setting(
        "simulation_node", "Where each cloud's prediction comes from: simulation_node (this project's, on "
        "prediction_request / predicted_mesh) or sim_bridge (the XPBD tissue simulator's sim_bridge service "
        "sim_bridge_service, called when the cloud is accepted; its state in frame sim/world is placed through /tf).",
        choices=("simulation_node", "sim_bridge"))
    sim_bridge_service: str = setting(
        "/sim/factor_graph_state", "Name of the sim_bridge/srv/FactorGraphState service (prediction_source "
        "sim_bridge).")
    sim_bridge_stiffness: bool = setting(
        True, "Ask the sim_bridge service for its stiffness matrix (compute_stiffness_matrix) and use it, made "
        "positive definite, as the physics prior's information; false: the estimator's own FEM stiffness.")
    marker_std_max: float = setting(
        0.0, "Posterior std (metres) drawn in full red in the markers; 0: the largest std of each estimate.",
        range=(0.0, 10.0), dynamic=True)

    def __post_init__(self) -> None:
        _check_quaternion("camera_pose", self.camera_pose)
        if not _ROS_NAME.fullmatch(self.sim_bridge_service):
            raise ParameterError(f"sim_bridge_service must be a ROS service name (letters, digits, '_' and '/', no "
                                 f"token starting with a digit), got {self.sim_bridge_service!r}")


@dataclass(frozen=True)
class InitialMeshConfig:
    """The world frame and the initial mesh file, scaled, placed and with its fixed vertices: the
    settings of each node that runs on a mesh (both pipeline nodes, sim_bridge_server)."""

    world_frame: str = setting("world", "Frame of meshes, tool poses and estimates.")
    mesh_file: str = setting(
        "", "Initial mesh file (.msh, .vtu, .vtk) used when no initial_mesh message arrives; empty: wait for "
        "initial_mesh. A file that cannot be read stops the node at start-up.")
    mesh_scale: float = setting(
        1.0, "Metres per unit of mesh_file: 0.001 for a mesh in millimetres.", range=(1e-9, 1e9))
    mesh_pose: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), "Pose of mesh_file's frame in world_frame, [x, y, z, qx, qy, qz, qw]: "
        "the registration of a CT mesh (applied after mesh_scale).", range=(-1e3, 1e3), length=7)
    fixed_vertices: tuple[int, ...] = setting(
        (), "Indices of mesh_file's vertices held fixed (the boundary), besides its 'fixed' point data.",
        type="integer_array", range=(0, None))
    fixed_plane: tuple[float, ...] = setting(
        (), "Hold fixed the vertices of mesh_file within a distance of a plane (world frame, metres): "
        "[x, y, z, nx, ny, nz, distance], a point on it, its normal, the distance; empty: none.",
        type="double_array")
    fixed_box: tuple[float, ...] = setting(
        (), "Hold fixed the vertices of mesh_file inside a box (world frame, metres): "
        "[xmin, ymin, zmin, xmax, ymax, zmax]; empty: none.", type="double_array")
    fixed_groups: str = setting(
        "", "Hold fixed the vertices of mesh_file's named groups (gmsh physical groups, cell or point sets), "
        "comma-separated; empty: none.")

    def __post_init__(self) -> None:
        if len(self.fixed_plane) not in (0, 7):
            raise ParameterError(f"fixed_plane needs 0 or 7 values, got {len(self.fixed_plane)}")
        if len(self.fixed_box) not in (0, 6):
            raise ParameterError(f"fixed_box needs 0 or 6 values, got {len(self.fixed_box)}")
        _check_quaternion("mesh_pose", self.mesh_pose)


@dataclass(frozen=True)
class SharedNodeConfig:
    """Settings of both pipeline nodes: the stamp rule, the wait for /tf and the tool poses'
    extrapolation to a cloud's stamp."""

    clock_jump_threshold: float = setting(
        DEFAULT_CLOCK_JUMP_THRESHOLD_S, "A stamp this many seconds older than the newest one (a looped recording) restarts from the "
        "initial mesh (a /tf transform: its frame's history); smaller steps back are dropped.", range=(0.0, 1e6))
    transform_timeout: float = setting(
        DEFAULT_TRANSFORM_WAIT_S, "Seconds (wall time) a cloud or tool pose in another frame than world_frame waits for /tf to place "
        "it at its stamp; then it is rejected with the reason.", range=(0.0, 60.0))
    tool_pose_horizon: float = setting(
        DEFAULT_EXTRAPOLATION_HORIZON_S, "Seconds past the newest tool pose within which the pose at a cloud's stamp is extrapolated "
        "(tool poses are interpolated at each cloud's stamp); beyond it the step has no tool pose.",
        range=(0.0, 10.0))


@dataclass(frozen=True)
class ToolPoseSubscriptionConfig:
    """The QoS of the tool_pose subscription, of each node that takes tool poses (both pipeline
    nodes, sim_bridge_server)."""

    tool_pose_reliable: bool = setting(
        True, "Subscribe to tool_pose with reliable QoS (depth 10), which every pose published reliably reaches "
        "and a best-effort publisher does not match; false: best effort (depth 100), which matches any publisher, "
        "for robot drivers that publish poses best effort (a pose the transport loses is missed: the pipeline "
        "nodes interpolate over it, sim_bridge_server's next step spans it).")


@dataclass(frozen=True)
class PlaybackConfig:
    """Settings of bag_player (its command-line options override rate, wait_for_subscribers and loop)."""

    rate: float = setting(1.0, "Playback speed: 1 is the recorded rate, 2 twice as fast.", range=(1e-3, 1e3))
    wait_for_subscribers: float = setting(
        10.0, "At most this many seconds to wait, before playing, until the played topics are matched: those "
        "named with --topics, or, when the whole recording plays, those some node subscribes to.",
        range=(0.0, 3600.0))
    subscribers: int = setting(
        1, "Matched subscribers each waited-for topic needs before playing: set it to the number of nodes that "
        "take a topic, so that none of them misses the start when it joins later than the others.",
        range=(1, 1000))
    clock_frequency: float = setting(100.0, "Rate of /clock messages between recorded ones (Hz).", range=(1.0, 1e4))
    delay: float = setting(
        0.5, "Seconds between finding the subscribers and playing: best-effort readers drop messages of a "
        "writer they have not matched yet.", range=(0.0, 3600.0))
    loop: bool = setting(False, "Start again at the end of the recording.")


@dataclass(frozen=True)
class ToolClearanceConfig:
    """Settings of tool_clearance_node, the example planner (nodes/tool_clearance_node.py)."""

    clearance_sigmas: float = setting(
        3.0, "Standard deviations of the tissue surface's position (along its normal, from the estimate's "
        "covariance) that the tool tip keeps from it: a desired tip nearer than that, or inside, is moved out "
        "along the surface normal.", range=(0.0, 100.0), dynamic=True)
    min_clearance: float = setting(
        0.001, "Least distance (metres) the tool tip keeps from the tissue surface, however certain the "
        "estimate is.", range=(0.0, 1.0), dynamic=True)


# The configurations each node reads: it declares the parameters of their fields.
NODE_CONFIGURATIONS: dict[str, tuple[type, ...]] = {
    "simulation_node": (SimulatorConfig, GraspConfig, SimulationNodeConfig, InitialMeshConfig, SharedNodeConfig,
                        ToolPoseSubscriptionConfig),
    "estimator_node": (EstimatorConfig, EstimatorNodeConfig, InitialMeshConfig, SharedNodeConfig,
                       ToolPoseSubscriptionConfig),
    "sim_bridge_server": (OpenLoopSimulatorConfig, GraspConfig, InitialMeshConfig, ToolPoseSubscriptionConfig),
    "bag_player": (PlaybackConfig,),
    "tool_clearance_node": (ToolClearanceConfig,),
}
# The pipeline (both nodes, and the offline replay that reproduces them), in the order of config/meshfg.yaml.
_PIPELINE_CONFIGURATIONS = (SimulatorConfig, GraspConfig, SimulationNodeConfig, EstimatorConfig, EstimatorNodeConfig,
                            InitialMeshConfig, SharedNodeConfig, ToolPoseSubscriptionConfig)

@functools.cache
def _fields_and_parameters(config_class: type) -> tuple[tuple[str, Setting, Parameter], ...]:
    """(field name, its Setting, parameter) of each field of `config_class` that is a parameter."""
    return tuple(
        (field_name, spec, Parameter(
            name=spec.parameter or field_name, default=default, description=spec.description,
            type=setting_type(field_name, default, spec.type), range=spec.range, choices=spec.choices,
            length=spec.length, dynamic=spec.dynamic))
        for field_name, default, spec in settings_of(config_class))


def _merged(configurations: Iterable[type]) -> tuple[Parameter, ...]:
    """The parameters of `configurations`, each once. A parameter of several configurations is one
    field they inherit (the tissue model and the tool: core/physics/tissue_and_tool.py), never a
    field declared again: one declaration, one default, one description."""
    by_name: dict[str, tuple[Setting, Parameter]] = {}
    for config_class in configurations:
        for _, spec, parameter in _fields_and_parameters(config_class):
            declared, _ = by_name.setdefault(parameter.name, (spec, parameter))
            if declared is not spec:
                raise ParameterError(f"parameter {parameter.name} is declared again in {config_class.__name__}: "
                                     "declare it once, on a configuration that both inherit")
    return tuple(parameter for _, parameter in by_name.values())


PARAMETERS: tuple[Parameter, ...] = _merged(_PIPELINE_CONFIGURATIONS)
_NODE_PARAMETERS = {node: _merged(configurations) for node, configurations in NODE_CONFIGURATIONS.items()}
_PACKAGE_PARAMETER_NAMES = frozenset(parameter.name for parameters in _NODE_PARAMETERS.values()
                                     for parameter in parameters) | _ROS_OWN_PARAMETERS


def node_parameters(node: str | None = None) -> tuple[Parameter, ...]:
    """The parameters `node` declares (None: the whole pipeline's, PARAMETERS)."""
    if node is None:
        return PARAMETERS
    if node not in _NODE_PARAMETERS:
        raise ParameterError(f"unknown node {node!r} (known: {', '.join(_NODE_PARAMETERS)})")
    return _NODE_PARAMETERS[node]


def check_parameter_names(names: Iterable[str], node: str) -> None:
    """ParameterError for the first of `names` that no node of the package knows, with the closest
    of `node`'s parameters. The parameters of the other nodes are accepted (and ignored by `node`):
    a `/**` section of a parameters file sets them for every node."""
    for name in names:
        if name not in _PACKAGE_PARAMETER_NAMES:
            known = [parameter.name for parameter in node_parameters(node)] + sorted(_ROS_OWN_PARAMETERS)
            raise ParameterError(_unknown(name, known))


def _unknown(name: str, known: list[str]) -> str:
    closest = difflib.get_close_matches(name, known, n=1)
    if closest:
        return f"unknown parameter {name} (did you mean {closest[0]}?)"
    return f"unknown parameter {name} (known: {', '.join(known)})"


def default_parameters(node: str | None = None) -> dict[str, Any]:
    """Every parameter of `node` (None: of the pipeline) at its default."""
    return {parameter.name: parameter.default for parameter in node_parameters(node)}


def load_parameters(mapping: Mapping[str, Any] | None = None, node: str | None = None) -> dict[str, Any]:
    """Validated parameters of `node` (None: of the whole pipeline): `mapping` (name -> value) over
    the defaults.

    Values are converted to float / int / str / bool / tuple; the configurations they make must
    accept them, and grasped_vertices must suit tool_mode.
    """
    mapping = {} if mapping is None else mapping
    if not isinstance(mapping, Mapping):
        raise ParameterError(f"parameters must be a mapping of name to value, got {type(mapping).__name__}")
    by_name = {parameter.name: parameter for parameter in node_parameters(node)}
    for name in mapping:
        if name not in by_name:
            raise ParameterError(_unknown(name, list(by_name)))
    values = default_parameters(node)
    for name, value in mapping.items():
        values[name] = by_name[name].validate(value)
    if {"tool_mode", "grasped_vertices"} <= values.keys():
        if values["grasped_vertices"] and values["tool_mode"] != "grasp":
            raise ParameterError("grasped_vertices is set but tool_mode is not 'grasp'")
        if values["tool_mode"] == "grasp" and not values["grasped_vertices"]:
            raise ParameterError("tool_mode 'grasp' needs grasped_vertices")
    for config_class in _PIPELINE_CONFIGURATIONS if node is None else NODE_CONFIGURATIONS[node]:
        try:
            config_from_parameters(config_class, values)
        except ValueError as error:
            raise ParameterError(str(error)) from None
    return values


def read_parameters_file(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """Validated parameters of the pipeline from a YAML file: a flat mapping or a ROS 2 parameters file.

    In a ROS 2 parameters file (`<node>: {ros__parameters: {...}}`) the `/**` section applies,
    then the section of `node_name` (if given) on top; use_sim_time is ignored.
    """
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise ParameterError(f"cannot read parameters file {path}: {' '.join(str(error).split())}") from None
    document = {} if document is None else document
    if not isinstance(document, Mapping):
        raise ParameterError(f"{path} must hold a mapping of parameters")
    sections = {key: value for key, value in document.items() if isinstance(value, Mapping) and _PARAMS_KEY in value}
    if sections:
        merged: dict[str, Any] = {}
        for key in ("/**", node_name):
            if key in sections:
                merged.update(sections[key][_PARAMS_KEY] or {})
        document = merged
    return load_parameters({key: value for key, value in document.items() if key not in _ROS_OWN_PARAMETERS})


def parameters_yaml(params: Mapping[str, Any]) -> str:
    """A ROS 2 parameters file (`/**: ros__parameters:`) setting `params` for every node."""
    values = {name: list(value) if isinstance(value, tuple) else value
              for name, value in load_parameters(params).items()}
    return yaml.safe_dump({"/**": {_PARAMS_KEY: values}}, sort_keys=False, default_flow_style=None)


# ------------------------------------------------------------------ configurations <-> parameters
def parameter_names(config_class: type) -> dict[str, str]:
    """Field name -> parameter name of each field of `config_class` that is a parameter."""
    return {field_name: parameter.name for field_name, _, parameter in _fields_and_parameters(config_class)}


def config_from_parameters(config_class: type, params: Mapping[str, Any]):
    """`config_class` with its parameter fields from validated parameters (the others at their defaults)."""
    return config_class(**{field_name: params[name] for field_name, name in parameter_names(config_class).items()})


def config_changes(config_class: type, changes: Mapping[str, Any]) -> dict[str, Any]:
    """Field name -> value of the fields of `config_class` that the parameter `changes` set."""
    return {field_name: changes[name] for field_name, name in parameter_names(config_class).items() if name in changes}


def simulator_config(params: Mapping[str, Any]) -> SimulatorConfig:
    """The simulator settings of validated parameters (grasped_vertices go to ElasticSimulator)."""
    return config_from_parameters(SimulatorConfig, params)


def estimator_config(params: Mapping[str, Any]) -> EstimatorConfig:
    """The estimator settings of validated parameters."""
    return config_from_parameters(EstimatorConfig, params)


def estimator_changes(changes: Mapping[str, Any]) -> dict[str, Any]:
    """The estimator's settings among parameter `changes`: the arguments of SlidingWindowEstimator.reconfigure."""
    return config_changes(EstimatorConfig, changes)


def shared_settings(config, config_class: type) -> dict[str, Any]:
    """Field name -> value of the parameter fields `config` shares with `config_class` (the same
    parameter in both, e.g. the tissue model of a SimulatorConfig for an EstimatorConfig)."""
    own = parameter_names(type(config))
    wanted = {name: field_name for field_name, name in parameter_names(config_class).items()}
    return {wanted[name]: getattr(config, field_name) for field_name, name in own.items() if name in wanted}


# ------------------------------------------------------------------ the nodes' inputs and help
def placed_mesh_file(params: Mapping[str, Any]) -> TetMesh:
    """The mesh of parameter mesh_file, scaled, placed and with the fixed vertices the parameters
    select (core/inputs/patient_mesh.py); the errors of core.geometry.mesh and core.inputs.patient_mesh."""
    plane, box = params["fixed_plane"], params["fixed_box"]
    selection = FixedSelection(
        indices=tuple(params["fixed_vertices"]),
        planes=(Plane(tuple(plane[:3]), tuple(plane[3:6]), plane[6]),) if plane else (),
        boxes=(Box(tuple(box[:3]), tuple(box[3:])),) if box else (),
        groups=tuple(name.strip() for name in params["fixed_groups"].split(",") if name.strip()),
    )
    return prepare_mesh(params["mesh_file"], selection, params["mesh_scale"], params["mesh_pose"])


def load_mesh_file(params: Mapping[str, Any]) -> TetMesh:
    """The nodes' initial mesh from mesh_file (`placed_mesh_file`), or ParameterError (one line)
    when it cannot be read or simulated."""
    try:
        return placed_mesh_file(params)
    except (OSError, ValueError) as error:
        raise ParameterError(f"cannot load mesh_file {params['mesh_file']}: {' '.join(str(error).split())}") from None


def world_frame_inputs(params: Mapping[str, Any]) -> WorldFrameInputs:
    """The placement of inputs into world_frame (core/inputs/world_frame.py) of the nodes and the replay:
    /tf and /tf_static, with the static camera_pose as the fallback for camera_frame where the
    parameters have it (the estimator's); camera_frame's origin is then each cloud's viewpoint
    (the estimator's back-face test)."""
    fallback, camera_frame = {}, params.get("camera_frame")
    if camera_frame is not None:
        fallback[camera_frame] = pose_matrix(np.asarray(params["camera_pose"], dtype=np.float64))
    return WorldFrameInputs(params["world_frame"], TransformBuffer(jump_back_s=params["clock_jump_threshold"]),
                            fallback=fallback, wait_s=params["transform_timeout"], viewpoint_frame=camera_frame)


def parameters_help(nodes: Iterable[str]) -> str:
    """The parameters of `nodes`, each with its type, default, range or choices and description."""
    lines = []
    for node in nodes:
        lines += ["", f"Parameters of {node} (--ros-args -p NAME:=VALUE or --params-file FILE; "
                      "dynamic ones also while it runs):"]
        for parameter in node_parameters(node):
            lines.append(f"  {parameter.name} ({parameter.summary()})")
            lines += textwrap.wrap(parameter.description, width=96, initial_indent=" " * 6,
                                   subsequent_indent=" " * 6)
    return "\n".join(lines[1:])
