"""The parameters of meshfg_ros: one table shared by the ROS nodes and the offline replay.

Each `Parameter` carries its default, a description, a ROS-style type name and its valid
range, so the nodes declare ROS parameters (with ParameterDescriptors) from it and the replay
validates its --config YAML against it. `load_parameters` checks a mapping (unknown key,
wrong type, out of range -> ParameterError naming the key) and fills in defaults;
`simulator_config` / `estimator_config` turn the result into the core configurations.
config/meshfg.yaml lists every parameter with its default (a test keeps the two in sync).

Clouds may come in `world_frame` or in `camera_frame`; `cloud_to_world` moves the latter into
the world frame with the static transform `camera_pose` and rejects every other frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from meshfg_ros.core.estimator import FACTOR_CONFIGURATIONS, EstimatorConfig
from meshfg_ros.core.fem import STIFFNESS_KINDS
from meshfg_ros.core.linear_solvers import LINEAR_SOLVERS
from meshfg_ros.core.robust import ROBUST_KERNELS
from meshfg_ros.core.simulator import SOLVERS as SIMULATOR_SOLVERS
from meshfg_ros.core.simulator import TOOL_CONTACTS, TOOL_MODES, SimulatorConfig

__all__ = [
    "PARAMETERS",
    "PARAMETER_TYPES",
    "FrameError",
    "Parameter",
    "ParameterError",
    "cloud_to_world",
    "default_parameters",
    "estimator_config",
    "load_parameters",
    "parameters_yaml",
    "read_parameters_file",
    "simulator_config",
]

# ROS parameter type names (rcl_interfaces/ParameterType without the PARAMETER_ prefix).
PARAMETER_TYPES = ("double", "integer", "string", "bool", "double_array", "integer_array")
# Parameters every rclpy node declares itself: accepted in a parameters file and ignored.
_ROS_OWN_PARAMETERS = frozenset({"use_sim_time"})
_PARAMS_KEY = "ros__parameters"


class ParameterError(ValueError):
    """A parameter that is unknown, of the wrong type or out of range (names the key)."""


class FrameError(ValueError):
    """A point cloud in a frame that is neither world_frame nor camera_frame."""


@dataclass(frozen=True)
class Parameter:
    """One parameter: name, default, description, type (see PARAMETER_TYPES) and valid range.

    range: inclusive (low, high) of the value (of each element for arrays); None = unbounded
    (either bound may be None). choices: the allowed strings. length: required array length.
    """

    name: str
    default: Any
    description: str
    type: str
    range: tuple[float | None, float | None] | None = None
    choices: tuple[str, ...] | None = None
    length: int | None = None

    def __post_init__(self) -> None:
        if self.type not in PARAMETER_TYPES:
            raise ParameterError(f"{self.name}: unknown parameter type {self.type!r}")

    def validate(self, value: Any) -> Any:
        """`value` converted to this parameter's canonical Python type, or ParameterError."""
        if self.type.endswith("_array"):
            return self._validate_array(value)
        return self._validate_scalar(value, self.type, self.name)

    def _validate_scalar(self, value: Any, kind: str, label: str) -> Any:
        if kind == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise ParameterError(f"{label} must be a bool, got {value!r}")
            return bool(value)
        if kind == "string":
            if not isinstance(value, str):
                raise ParameterError(f"{label} must be a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise ParameterError(f"{label} must be one of {', '.join(self.choices)}; got {value!r}")
            return value
        is_integer = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
        if kind == "integer":
            if not is_integer:
                raise ParameterError(f"{label} must be an integer, got {value!r}")
            number = int(value)
        else:
            if not (is_integer or isinstance(value, (float, np.floating))):
                raise ParameterError(f"{label} must be a number, got {value!r}")
            number = float(value)
            if not np.isfinite(number):
                raise ParameterError(f"{label} must be finite, got {value!r}")
        if self.range is not None:
            low, high = self.range
            if (low is not None and number < low) or (high is not None and number > high):
                raise ParameterError(f"{label} = {number} is outside [{_bound(low, '-inf')}, {_bound(high, 'inf')}]")
        return number

    def _validate_array(self, value: Any) -> tuple:
        if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
            raise ParameterError(f"{self.name} must be a list, got {value!r}")
        items = list(value)
        if self.length is not None and len(items) != self.length:
            raise ParameterError(f"{self.name} must have {self.length} values, got {len(items)}")
        element_type = self.type.removesuffix("_array")
        return tuple(
            self._validate_scalar(item, element_type, f"{self.name}[{index}]") for index, item in enumerate(items)
        )


def _bound(value: float | None, unbounded: str) -> str:
    return unbounded if value is None else f"{value:g}"


_POSITIVE_LENGTH = (1e-9, 10.0)  # metres: from a nanometre to a room-sized workspace
# The core's own defaults are the parameters' defaults (config/meshfg.yaml repeats them).
_SIMULATOR = SimulatorConfig()
_ESTIMATOR = EstimatorConfig()

PARAMETERS: tuple[Parameter, ...] = (
    # Simulator (the physics prior's predictor).
    Parameter("tool_mode", _SIMULATOR.tool_mode,
              "How the tool drives the tissue: 'sphere' pushes it with a rigid sphere, 'grasp' moves "
              "grasped_vertices rigidly with the tool.", "string", choices=TOOL_MODES),
    Parameter("tool_contact", _SIMULATOR.tool_contact,
              "Sphere contact: 'stick' (the tissue does not slip while pushed) or 'slide' (frictionless).",
              "string", choices=TOOL_CONTACTS),
    Parameter("tool_radius", _SIMULATOR.tool_radius,
              "Radius of the tool sphere in metres (sphere mode).", "double", (1e-6, 1.0)),
    Parameter("grasped_vertices", (),
              "Mesh vertex indices held by the tool (grasp mode only).", "integer_array", (0, None)),
    Parameter("youngs_modulus", _SIMULATOR.youngs_modulus,
              "Young's modulus of the tissue model in pascals.", "double", (1.0, 1e9)),
    Parameter("poisson_ratio", _SIMULATOR.poisson_ratio,
              "Poisson's ratio of the tissue model.", "double", (0.001, 0.499)),
    Parameter("density", _SIMULATOR.density,
              "Tissue density in kg/m^3.", "double", (1.0, 1e5)),
    Parameter("simulator", _SIMULATOR.solver,
              "Simulator solver: 'vbd' (vertex block descent) or 'xpbd'.", "string", choices=SIMULATOR_SOLVERS),
    Parameter("simulator_substeps", _SIMULATOR.substeps,
              "Tool increments per prediction.", "integer", (1, 1000)),
    Parameter("simulator_iterations", _SIMULATOR.solver_iterations,
              "Solver iterations per sub-step.", "integer", (1, 1000)),
    # Factor graph.
    Parameter("factors", _ESTIMATOR.factors,
              "Factor configuration of the estimator, by name.", "string", choices=tuple(FACTOR_CONFIGURATIONS)),
    Parameter("measurement_sigma", _ESTIMATOR.measurement_sigma,
              "Nominal standard deviation of a depth point along the surface normal, metres (the sensor's "
              "datasheet value; with estimate_weights the estimator starts from it and estimates the real spread "
              "from the residuals).",
              "double", _POSITIVE_LENGTH),
    Parameter("simulation_sigma", _ESTIMATOR.simulation_sigma,
              "Expected simulator error per vertex in metres; scales the FEM-stiffness information of the "
              "physics prior. Used with estimate_weights false; with estimate_weights the prior follows the "
              "estimated measurement sigma (a tenth of it, core/weights.py).", "double", _POSITIVE_LENGTH),
    Parameter("estimate_weights", _ESTIMATOR.estimate_weights,
              "Estimate the measurement noise online from the residuals and weight the physics prior with a "
              "tenth of it (core/weights.py); false: use measurement_sigma and simulation_sigma as given.",
              "bool"),
    Parameter("temporal_sigma", _ESTIMATOR.temporal_sigma,
              "Standard deviation of a vertex's motion between two steps beyond the simulator's prediction, "
              "metres.", "double", _POSITIVE_LENGTH),
    Parameter("window_size", _ESTIMATOR.window_size,
              "Number of states in the sliding window.", "integer", (1, 100)),
    Parameter("stiffness_kind", _ESTIMATOR.stiffness_kind,
              "FEM stiffness used as the prior's information matrix.", "string", choices=STIFFNESS_KINDS),
    Parameter("spd_projection", _ESTIMATOR.spd_projection,
              "Clamp negative eigenvalues of the element stiffness matrices.", "bool"),
    Parameter("robust_kernel", _ESTIMATOR.robust_kernel or "none",
              "Robust kernel on the point-to-surface residuals.", "string", choices=tuple(ROBUST_KERNELS)),
    Parameter("robust_scale", _ESTIMATOR.robust_scale,
              "Scale of the robust kernel in metres; 0: 2.4 times the (estimated) measurement sigma.", "double",
              (0.0, 10.0)),
    Parameter("gating_distance", _ESTIMATOR.gating_distance,
              "Points farther than this from the predicted surface are rejected (metres); 0: five times the "
              "cloud's robust spread about the predicted surface (at least the measurement sigma).", "double",
              (0.0, 10.0)),
    Parameter("max_iterations", _ESTIMATOR.max_iterations,
              "Levenberg-Marquardt iterations per step (at most).", "integer", (1, 1000)),
    Parameter("update_time_budget", _ESTIMATOR.update_time_budget,
              "Seconds (wall time) Levenberg-Marquardt may take per update: it then stops between iterations "
              "and returns its best state, 'time budget' in the status message.", "double", (1e-3, 3600.0)),
    Parameter("linear_solver", _ESTIMATOR.linear_solver,
              "Sparse solver of the normal equations.", "string", choices=tuple(LINEAR_SOLVERS)),
    # Frames and the live pipeline.
    Parameter("world_frame", "world",
              "Frame of meshes, tool poses and estimates.", "string"),
    Parameter("camera_frame", "camera",
              "Frame of clouds that are moved to world_frame with camera_pose; clouds in any other frame are "
              "rejected.", "string"),
    Parameter("camera_pose", (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
              "Static pose of camera_frame in world_frame: [x, y, z, qx, qy, qz, qw].", "double_array",
              (-1e3, 1e3), length=7),
    Parameter("mesh_file", "",
              "Initial mesh file (.msh, .vtu, .vtk) used when no initial_mesh message arrives; empty: wait for "
              "initial_mesh.", "string"),
    Parameter("points_reliable", False,
              "Subscribe to points with reliable QoS (depth 100): for recordings played back by bag_player, where "
              "every cloud counts; false: the sensor-data profile of live cameras (best effort, depth 5), which "
              "drops clouds the transport loses when the CPU is saturated.", "bool"),
    Parameter("prediction_timeout", 0.5,
              "Seconds (wall time) a cloud waits for its simulator prediction before the step runs degraded "
              "without it.", "double", (0.0, 60.0)),
    Parameter("estimate_timeout", 2.0,
              "Seconds (wall time) a tool pose waits for the estimate of the previous tool pose before it is "
              "predicted from an older state (tool poses and clouds share stamps, as in the recordings); 0 when "
              "tool poses come faster than clouds.", "double", (0.0, 60.0)),
    Parameter("clock_jump_threshold", 1.0,
              "A stamp this many seconds older than the newest one (a looped recording) restarts from the "
              "initial mesh; smaller steps back are dropped.", "double", (0.0, 1e6)),
    Parameter("marker_std_max", 0.0,
              "Posterior std (metres) drawn in full red in the markers; 0: the largest std of each estimate.",
              "double", (0.0, 10.0)),
)

_BY_NAME: dict[str, Parameter] = {parameter.name: parameter for parameter in PARAMETERS}


def default_parameters() -> dict[str, Any]:
    """Every parameter at its default."""
    return {parameter.name: parameter.default for parameter in PARAMETERS}


def load_parameters(mapping: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Validated parameters: `mapping` (name -> value) over the defaults.

    Values are converted to float / int / str / bool / tuple; grasped_vertices must suit tool_mode.
    """
    mapping = {} if mapping is None else mapping
    if not isinstance(mapping, Mapping):
        raise ParameterError(f"parameters must be a mapping of name to value, got {type(mapping).__name__}")
    unknown = sorted(set(mapping) - set(_BY_NAME))
    if unknown:
        raise ParameterError(f"unknown parameter {unknown[0]!r} (known: {', '.join(_BY_NAME)})")
    values = default_parameters()
    for name, value in mapping.items():
        values[name] = _BY_NAME[name].validate(value)
    if values["grasped_vertices"] and values["tool_mode"] != "grasp":
        raise ParameterError("grasped_vertices is set but tool_mode is not 'grasp'")
    if values["tool_mode"] == "grasp" and not values["grasped_vertices"]:
        raise ParameterError("tool_mode 'grasp' needs grasped_vertices")
    if np.linalg.norm(values["camera_pose"][3:]) < 1e-9:
        raise ParameterError("camera_pose quaternion has zero norm")
    return values


def read_parameters_file(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """Validated parameters from a YAML file: a flat mapping or a ROS 2 parameters file.

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


def simulator_config(params: Mapping[str, Any]) -> SimulatorConfig:
    """The simulator settings of validated parameters (grasped_vertices go to ElasticSimulator)."""
    return SimulatorConfig(
        youngs_modulus=params["youngs_modulus"],
        poisson_ratio=params["poisson_ratio"],
        density=params["density"],
        tool_radius=params["tool_radius"],
        tool_mode=params["tool_mode"],
        tool_contact=params["tool_contact"],
        solver=params["simulator"],
        substeps=params["simulator_substeps"],
        solver_iterations=params["simulator_iterations"],
    )


def estimator_config(params: Mapping[str, Any]) -> EstimatorConfig:
    """The estimator settings of validated parameters."""
    return EstimatorConfig(
        factors=params["factors"],
        measurement_sigma=params["measurement_sigma"],
        simulation_sigma=params["simulation_sigma"],
        temporal_sigma=params["temporal_sigma"],
        window_size=params["window_size"],
        stiffness_kind=params["stiffness_kind"],
        spd_projection=params["spd_projection"],
        robust_kernel=None if params["robust_kernel"] == "none" else params["robust_kernel"],
        robust_scale=params["robust_scale"],
        gating_distance=params["gating_distance"],
        estimate_weights=params["estimate_weights"],
        tool_radius=params["tool_radius"] if params["tool_mode"] == "sphere" else 0.0,
        max_iterations=params["max_iterations"],
        update_time_budget=params["update_time_budget"],
        linear_solver=params["linear_solver"],
        youngs_modulus=params["youngs_modulus"],
        poisson_ratio=params["poisson_ratio"],
    )


def cloud_to_world(points: np.ndarray, frame_id: str, params: Mapping[str, Any]) -> np.ndarray:
    """Points (K, 3) of a cloud in `frame_id`, expressed in world_frame.

    world_frame clouds pass unchanged; camera_frame clouds get the static camera_pose.
    """
    if frame_id == params["world_frame"]:
        return points
    if frame_id == params["camera_frame"]:
        pose = np.asarray(params["camera_pose"], dtype=np.float64)
        return points @ Rotation.from_quat(pose[3:]).as_matrix().T + pose[:3]
    raise FrameError(
        f"cloud frame {frame_id!r} is neither world_frame {params['world_frame']!r} "
        f"nor camera_frame {params['camera_frame']!r}"
    )
