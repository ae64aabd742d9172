"""ROS message types of meshfg_ros and their conversion to plain-array records.

The records (`MeshState`, `StatusRecord`, `PoseRecord`, `PointCloudRecord`) hold numpy arrays
and integer-nanosecond stamps and know nothing of any message class. The converters read
messages by field name only, so they accept both the classes that `rosbags` generates and the
rosidl-generated classes used by rclpy; to build a message they take a `MessageFactory`
(`RosbagsMessageFactory` for recordings, `RclpyMessageFactory` for the ROS nodes). Nothing here
imports rclpy.
"""

from __future__ import annotations

import array
import functools
import importlib
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from meshfg_ros.core.inputs.input_checks import NS_PER_S
from meshfg_ros.core.geometry.mesh import TetMesh

TETRA_MESH = "meshfg_msgs/msg/TetraMesh"
ESTIMATOR_STATUS = "meshfg_msgs/msg/EstimatorStatus"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

# Verbatim copies of meshfg_msgs/msg/*.msg, so that a pip install of meshfg_ros (without the
# colcon-built meshfg_msgs) can still read and write recordings; test_recording.py checks
# that they stay identical to the files in meshfg_msgs/msg/.
MSG_DEFINITIONS: dict[str, str] = {
    TETRA_MESH: """\
# A tetrahedral mesh state, metres, in header.frame_id.
std_msgs/Header header
uint32 step                 # estimation step (0 for an initial mesh)
float64[] positions         # 3N: x0 y0 z0 x1 y1 z1 ...
uint32[] tetrahedra         # 4M vertex indices, positive signed volume
uint32[] surface_triangles  # 3F vertex indices, counter-clockwise seen from outside
uint32[] fixed_vertices     # vertices held fixed (boundary condition)
float32[] position_std      # N per-vertex posterior standard deviation (m), or empty
bool degraded               # an estimate whose update ran without a simulator prediction (as EstimatorStatus.degraded)
float32[] position_covariance  # 6N: per vertex the upper triangle xx xy xz yy yz zz of its 3x3 posterior covariance (m^2), or empty
uint32[] invalid_vertices   # vertices no remaining element uses (removed by a cut): neither estimated nor drawn; empty when none
uint32[] removed_elements   # slots of the uncut mesh's elements a cut removed (tetrahedra lists the others in slot order); empty when none
""",
    ESTIMATOR_STATUS: """\
# Outcome of one estimator update (one step of the sliding-window Levenberg-Marquardt).
std_msgs/Header header
uint32 step
uint32 iterations
float64 initial_cost
float64 final_cost
float64 solve_time_ms
uint32 num_points
uint32 num_points_rejected
uint32 window_size
bool converged
bool degraded               # true when the step ran without a simulator prediction
string message
""",
}

_TETRA_MESH_COVARIANCE_LINE = (
    "float32[] position_covariance  # 6N: per vertex the upper triangle xx xy xz yy yz zz of its 3x3 posterior "
    "covariance (m^2), or empty\n")
_TETRA_MESH_CUT_LINES = (
    "uint32[] invalid_vertices   # vertices no remaining element uses (removed by a cut): neither estimated nor "
    "drawn; empty when none\n"
    "uint32[] removed_elements   # slots of the uncut mesh's elements a cut removed (tetrahedra lists the others "
    "in slot order); empty when none\n")
_TETRA_MESH_DEGRADED_LINE = (
    "bool degraded               # an estimate whose update ran without a simulator prediction "
    "(as EstimatorStatus.degraded)\n")
# Shorter TetraMesh definitions a recording may hold, each read with its own definition (the
# fields it lacks take their defaults): without `invalid_vertices` and `removed_elements`;
# without `position_covariance` too; and without `degraded` too (the bundled recordings').
_TETRA_MESH_UNCUT = MSG_DEFINITIONS[TETRA_MESH].replace(_TETRA_MESH_CUT_LINES, "")
_TETRA_MESH_NO_COVARIANCE = _TETRA_MESH_UNCUT.replace(_TETRA_MESH_COVARIANCE_LINE, "")
SHORTER_MSG_DEFINITIONS: dict[str, tuple[str, ...]] = {
    TETRA_MESH: (
        _TETRA_MESH_UNCUT,
        _TETRA_MESH_NO_COVARIANCE,
        _TETRA_MESH_NO_COVARIANCE.replace(_TETRA_MESH_DEGRADED_LINE, ""),
    ),
}
# Row and column of each entry of a vertex's 3x3 covariance in TetraMesh.position_covariance:
# the upper triangle, xx xy xz yy yz zz.
_UPPER_ROWS, _UPPER_COLUMNS = np.triu_indices(3)

_UINT32_MAX = 2**32 - 1
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


class MessageValidationError(ValueError):
    """A record or message holds inconsistent or invalid data (names the field)."""


class UnknownMessageTypeError(LookupError):
    """A message factory cannot find the message class for a ROS type name."""


@functools.lru_cache(maxsize=1)
def meshfg_typestore() -> Typestore:
    """ROS 2 Jazzy typestore with meshfg_msgs registered (shared instance: do not register into it)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for typename, text in MSG_DEFINITIONS.items():
        store.register(get_types_from_msg(text, typename))
    return store


@functools.lru_cache(maxsize=1)
def readable_definition_hashes() -> dict[str, frozenset[str]]:
    """RIHS01 hashes of the definitions of each meshfg_msgs type that recordings may hold: the
    package's own and the shorter ones it reads (SHORTER_MSG_DEFINITIONS)."""
    hashes = {}
    for typename in MSG_DEFINITIONS:
        known = {meshfg_typestore().hash_rihs01(typename)}
        for text in SHORTER_MSG_DEFINITIONS.get(typename, ()):
            store = get_typestore(Stores.ROS2_JAZZY)
            store.register(get_types_from_msg(text, typename))
            known.add(store.hash_rihs01(typename))
        hashes[typename] = frozenset(known)
    return hashes


class MessageFactory(Protocol):
    """Builds messages of one Python message flavour (rosbags or rclpy) by ROS type name."""

    def make(self, typename: str, **fields: Any) -> Any:
        """Construct a `typename` message (e.g. 'std_msgs/msg/Header') from all its fields."""

    def sequence(self, values: np.ndarray, dtype: np.dtype | type) -> Any:
        """Wrap a 1-D array as this flavour's value for a primitive sequence field of `dtype`."""


class RosbagsMessageFactory:
    """Messages as `rosbags` dataclasses; primitive sequences are numpy arrays of the exact dtype."""

    def __init__(self, typestore: Typestore | None = None) -> None:
        self.typestore = meshfg_typestore() if typestore is None else typestore

    def make(self, typename: str, **fields: Any) -> Any:
        try:
            cls = self.typestore.types[typename]
        except KeyError:
            raise UnknownMessageTypeError(
                f"message type {typename!r} is not in the rosbags typestore"
            ) from None
        return cls(**fields)

    def sequence(self, values: np.ndarray, dtype: np.dtype | type) -> np.ndarray:
        # rosbags serialises by viewing the buffer as bytes: the dtype must match exactly.
        return np.ascontiguousarray(values, dtype=dtype).reshape(-1)


class RclpyMessageFactory:
    """Messages as rosidl-generated Python classes (the ones rclpy publishes).

    Classes are imported by name from `<package>.msg`; rclpy itself is not imported here.
    Primitive sequences are `array.array`, which the generated setters take without a
    per-element check.
    """

    _TYPECODES = {
        np.dtype(np.float64): "d",
        np.dtype(np.float32): "f",
        np.dtype(np.int32): "i",
        np.dtype(np.uint32): "I",
        np.dtype(np.uint8): "B",
    }

    def __init__(self) -> None:
        self._classes: dict[str, type] = {}

    def message_class(self, typename: str) -> type:
        """The generated class for `typename` ('pkg/msg/Name'), imported on first use."""
        if typename not in self._classes:
            package, kind, name = typename.split("/")
            try:
                self._classes[typename] = getattr(importlib.import_module(f"{package}.{kind}"), name)
            except (ImportError, AttributeError) as error:
                raise UnknownMessageTypeError(
                    f"cannot import message class {typename!r}: {error}"
                ) from None
        return self._classes[typename]

    def make(self, typename: str, **fields: Any) -> Any:
        return self.message_class(typename)(**fields)

    def sequence(self, values: np.ndarray, dtype: np.dtype | type) -> array.array:
        dtype = np.dtype(dtype)
        if dtype not in self._TYPECODES:
            raise UnknownMessageTypeError(f"no array.array type code for dtype {dtype}")
        return array.array(self._TYPECODES[dtype], np.ascontiguousarray(values, dtype=dtype).tobytes())


def _default_factory(factory: MessageFactory | None) -> MessageFactory:
    return RosbagsMessageFactory() if factory is None else factory


def stamp_ns_from_msg(time_msg: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time message."""
    return int(time_msg.sec) * NS_PER_S + int(time_msg.nanosec)


def header_msg(stamp_ns: int, frame_id: str, factory: MessageFactory | None = None) -> Any:
    """A std_msgs/Header for `stamp_ns` (nanoseconds; negative allowed within int32 seconds)."""
    factory = _default_factory(factory)
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise MessageValidationError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    stamp = factory.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
    return factory.make("std_msgs/msg/Header", stamp=stamp, frame_id=str(frame_id))


def _check_uint32(name: str, value: int) -> int:
    value = int(value)
    if not 0 <= value <= _UINT32_MAX:
        raise MessageValidationError(f"{name} = {value} is outside the uint32 range")
    return value


def _frozen(values: np.ndarray) -> np.ndarray:
    values.setflags(write=False)
    return values


def covariance_upper_triangles(covariance: np.ndarray) -> np.ndarray:
    """(N, 6) upper triangles xx xy xz yy yz zz of (N, 3, 3) covariance blocks: the layout of
    TetraMesh.position_covariance (a symmetric block is whole in its upper triangle)."""
    return np.asarray(covariance, dtype=np.float64).reshape(-1, 3, 3)[:, _UPPER_ROWS, _UPPER_COLUMNS]


def covariance_from_upper_triangles(values: Any, vertex_count: int) -> np.ndarray:
    """(N, 3, 3) symmetric covariance blocks (m^2) of a TetraMesh.position_covariance field: 6N
    values, per vertex xx xy xz yy yz zz; (0, 3, 3) when the field is empty (no covariance).

    Raises MessageValidationError (naming the first bad vertex) for a count other than 6N or 0,
    a non-finite entry or a negative variance. Positive semi-definiteness is not required: a
    block's float32 entries keep its eigenvalues to about 1e-7 of its largest one, so a nearly
    singular block may come with a slightly negative one (clip at zero where it matters).
    """
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if flat.size == 0:
        return np.zeros((0, 3, 3))
    if flat.size != 6 * vertex_count:
        raise MessageValidationError(
            f"position_covariance has {flat.size} values, expected 6 per vertex ({6 * vertex_count}) or 0")
    upper = flat.reshape(vertex_count, 6)
    covariance = np.empty((vertex_count, 3, 3))
    covariance[:, _UPPER_ROWS, _UPPER_COLUMNS] = upper
    covariance[:, _UPPER_COLUMNS, _UPPER_ROWS] = upper
    _check_covariance(covariance)
    return covariance


def _check_covariance(covariance: np.ndarray) -> None:
    """MessageValidationError unless every (3, 3) block is finite with non-negative variances."""
    finite = np.isfinite(covariance).all(axis=(1, 2))
    if not finite.all():
        raise MessageValidationError(f"position_covariance of vertex {int(np.argmin(finite))} is not finite")
    negative = (np.einsum("vii->vi", covariance) < 0.0).any(axis=1)
    if negative.any():
        raise MessageValidationError(
            f"position_covariance of vertex {int(np.argmax(negative))} has a negative variance")


def _as_index_array(name: str, values: Any, width: int | None, num_vertices: int) -> np.ndarray:
    """Copy `values` to int64 of shape (n, width) (or (n,) if width is None), indices in range."""
    raw = np.asarray(values)
    if raw.size and not (np.issubdtype(raw.dtype, np.integer) or np.all(np.mod(raw, 1) == 0)):
        raise MessageValidationError(f"{name} holds non-integer vertex indices")
    flat = raw.astype(np.int64).reshape(-1)
    if width is not None and flat.size % width:
        raise MessageValidationError(f"{name} has {flat.size} indices, not a multiple of {width}")
    if flat.size and (flat.min() < 0 or flat.max() >= num_vertices):
        bad = flat[(flat < 0) | (flat >= num_vertices)]
        raise MessageValidationError(
            f"{name} index {int(bad[0])} is out of range for {num_vertices} vertices"
        )
    return _frozen(flat.reshape(-1, width) if width is not None else flat)


@dataclass(frozen=True, eq=False)
class MeshState:
    """One tetrahedral mesh state (meshfg_msgs/TetraMesh as arrays), validated on construction.

    positions (N, 3) float64 metres (a flat 3N array is reshaped); tetrahedra (M, 4), surface_triangles (F, 3),
    fixed_vertices (K,) int64 vertex indices; position_std (N,) float64 or (0,) when unknown;
    position_covariance (N, 3, 3) float64 symmetric blocks (m^2) or (0, 3, 3) when unknown (the
    message's 6N upper-triangle values are unpacked); after a cut, invalid_vertices (V,) (no
    remaining element uses them; not part of the body) and removed_elements (R,) (slots of the
    uncut mesh's elements, `tetrahedra` holding the others), both empty otherwise. Arrays are
    copied and read-only.
    """

    stamp_ns: int
    frame_id: str
    step: int
    positions: np.ndarray
    tetrahedra: np.ndarray
    surface_triangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    fixed_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    position_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    degraded: bool = False  # an estimate made without a simulator prediction
    position_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    invalid_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    removed_elements: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        positions = np.array(self.positions, dtype=np.float64)
        if positions.ndim == 1:
            if positions.size % 3:
                raise MessageValidationError(
                    f"positions has {positions.size} values, not a multiple of 3"
                )
            positions = positions.reshape(-1, 3)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise MessageValidationError(f"positions must be (N, 3), got shape {positions.shape}")
        if not np.isfinite(positions).all():
            rows = np.flatnonzero(~np.isfinite(positions).all(axis=1))
            raise MessageValidationError(f"positions of vertex {int(rows[0])} are not finite")
        num_vertices = positions.shape[0]
        position_std = np.array(self.position_std, dtype=np.float64).reshape(-1)
        if position_std.size not in (0, num_vertices):
            raise MessageValidationError(
                f"position_std has {position_std.size} values, expected {num_vertices} or 0"
            )
        if not (np.isfinite(position_std) & (position_std >= 0)).all():
            raise MessageValidationError("position_std must be finite and non-negative")
        set_field = functools.partial(object.__setattr__, self)
        set_field("stamp_ns", int(self.stamp_ns))
        set_field("frame_id", str(self.frame_id))
        set_field("step", _check_uint32("step", self.step))
        set_field("positions", _frozen(positions))
        set_field("tetrahedra", _as_index_array("tetrahedra", self.tetrahedra, 4, num_vertices))
        set_field(
            "surface_triangles",
            _as_index_array("surface_triangles", self.surface_triangles, 3, num_vertices),
        )
        set_field("fixed_vertices", _as_index_array("fixed_vertices", self.fixed_vertices, None, num_vertices))
        set_field("position_std", _frozen(position_std))
        set_field("degraded", bool(self.degraded))
        set_field("position_covariance", _frozen(_mesh_covariance(self.position_covariance, num_vertices)))
        set_field("invalid_vertices", _as_index_array("invalid_vertices", self.invalid_vertices, None, num_vertices))
        removed = np.asarray(self.removed_elements)
        set_field("removed_elements", _as_index_array("removed_elements", removed, None,
                                                      len(self.tetrahedra) + removed.size))
        if self.invalid_vertices.size and np.isin(self.tetrahedra, self.invalid_vertices).any():
            raise MessageValidationError("tetrahedra use an invalid vertex")

    @classmethod
    def of_mesh(cls, mesh: TetMesh, stamp_ns: int, frame_id: str, step: int, positions=None, **fields) -> MeshState:
        """The state of `mesh`'s topology (remaining elements, surface, boundary-fixed, invalid
        vertices and removed elements of a cut mesh) at `positions` (default: the mesh's)."""
        return cls(stamp_ns, frame_id, step, mesh.vertices if positions is None else positions, mesh.tetrahedra,
                   mesh.surface_triangles, mesh.boundary_vertices, invalid_vertices=mesh.invalid_vertices,
                   removed_elements=mesh.removed_elements, **fields)

    @property
    def free_vertices(self) -> np.ndarray:
        """Sorted vertices that are neither fixed nor invalid: the ones an estimate is judged on."""
        return np.setdiff1d(np.arange(len(self.positions)), np.union1d(self.fixed_vertices, self.invalid_vertices))

    def tet_mesh(self, name: str = "") -> TetMesh:
        """The core mesh (vertices, tetrahedra, fixed vertices) of this state."""
        return TetMesh(self.positions, self.tetrahedra, self.fixed_vertices, name=name)


def _mesh_covariance(values: Any, num_vertices: int) -> np.ndarray:
    """MeshState.position_covariance as (N, 3, 3) or (0, 3, 3): blocks checked (finite, symmetric,
    variances non-negative), or the message's 6N values unpacked."""
    covariance = np.array(values, dtype=np.float64)
    if covariance.ndim <= 1:
        return covariance_from_upper_triangles(covariance, num_vertices)
    if covariance.size == 0:
        return np.zeros((0, 3, 3))
    if covariance.shape != (num_vertices, 3, 3):
        raise MessageValidationError(
            f"position_covariance must be ({num_vertices}, 3, 3) or empty, got shape {covariance.shape}")
    _check_covariance(covariance)
    # The message carries the upper triangle: a block that is not symmetric would arrive changed.
    scale = np.abs(covariance).max(axis=(1, 2))
    asymmetric = np.abs(covariance - covariance.transpose(0, 2, 1)).max(axis=(1, 2)) > 1e-9 * scale
    if asymmetric.any():
        raise MessageValidationError(f"position_covariance of vertex {int(np.argmax(asymmetric))} is not symmetric")
    return covariance


@dataclass(frozen=True)
class StatusRecord:
    """One estimator update outcome (meshfg_msgs/EstimatorStatus as plain values)."""

    stamp_ns: int
    frame_id: str
    step: int
    iterations: int
    initial_cost: float
    final_cost: float
    solve_time_ms: float
    num_points: int
    num_points_rejected: int
    window_size: int
    converged: bool
    degraded: bool
    message: str = ""

    def __post_init__(self) -> None:
        set_field = functools.partial(object.__setattr__, self)
        set_field("stamp_ns", int(self.stamp_ns))
        set_field("frame_id", str(self.frame_id))
        for name in ("step", "iterations", "num_points", "num_points_rejected", "window_size"):
            set_field(name, _check_uint32(name, getattr(self, name)))
        for name in ("initial_cost", "final_cost", "solve_time_ms"):
            set_field(name, float(getattr(self, name)))
        set_field("converged", bool(self.converged))
        set_field("degraded", bool(self.degraded))
        set_field("message", str(self.message))


@dataclass(frozen=True, eq=False)
class PoseRecord:
    """A stamped pose: (7,) float64 [x, y, z, qx, qy, qz, qw] in frame_id (ROS order)."""

    stamp_ns: int
    frame_id: str
    pose: np.ndarray

    def __post_init__(self) -> None:
        pose = np.array(self.pose, dtype=np.float64)
        if pose.shape != (7,):
            raise MessageValidationError(f"pose must have shape (7,), got {pose.shape}")
        if not np.isfinite(pose).all():
            raise MessageValidationError("pose has non-finite values")
        if np.linalg.norm(pose[3:]) == 0.0:
            raise MessageValidationError("pose quaternion is zero")
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "frame_id", str(self.frame_id))
        object.__setattr__(self, "pose", _frozen(pose))


@dataclass(frozen=True, eq=False)
class PointCloudRecord:
    """A stamped point cloud: finite points (K, 3) float64 in frame_id.

    dropped_nonfinite counts the NaN/inf points removed when decoding the message.
    """

    stamp_ns: int
    frame_id: str
    points: np.ndarray
    dropped_nonfinite: int = 0

    def __post_init__(self) -> None:
        points = np.array(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise MessageValidationError(f"points must be (K, 3), got shape {points.shape}")
        if not np.isfinite(points).all():
            raise MessageValidationError("points has non-finite values")
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))
        object.__setattr__(self, "frame_id", str(self.frame_id))
        object.__setattr__(self, "points", _frozen(points))
        object.__setattr__(self, "dropped_nonfinite", int(self.dropped_nonfinite))


def mesh_state_to_msg(state: MeshState, factory: MessageFactory | None = None) -> Any:
    """meshfg_msgs/TetraMesh message for `state` (factory: rosbags by default, or rclpy)."""
    factory = _default_factory(factory)
    return factory.make(
        TETRA_MESH,
        header=header_msg(state.stamp_ns, state.frame_id, factory),
        step=state.step,
        positions=factory.sequence(state.positions, np.float64),
        tetrahedra=factory.sequence(state.tetrahedra, np.uint32),
        surface_triangles=factory.sequence(state.surface_triangles, np.uint32),
        fixed_vertices=factory.sequence(state.fixed_vertices, np.uint32),
        position_std=factory.sequence(state.position_std, np.float32),
        degraded=bool(state.degraded),
        position_covariance=factory.sequence(covariance_upper_triangles(state.position_covariance), np.float32),
        invalid_vertices=factory.sequence(state.invalid_vertices, np.uint32),
        removed_elements=factory.sequence(state.removed_elements, np.uint32),
    )


def mesh_state_from_msg(msg: Any) -> MeshState:
    """MeshState from a TetraMesh message of either flavour (validated)."""
    return MeshState(
        stamp_ns=stamp_ns_from_msg(msg.header.stamp),
        frame_id=msg.header.frame_id,
        step=msg.step,
        positions=np.asarray(msg.positions, dtype=np.float64),
        tetrahedra=np.asarray(msg.tetrahedra, dtype=np.int64),
        surface_triangles=np.asarray(msg.surface_triangles, dtype=np.int64),
        fixed_vertices=np.asarray(msg.fixed_vertices, dtype=np.int64),
        position_std=np.asarray(msg.position_std, dtype=np.float64),
        # Recordings made before these fields have none.
        degraded=bool(getattr(msg, "degraded", False)),
        position_covariance=np.asarray(getattr(msg, "position_covariance", ()), dtype=np.float64),
        invalid_vertices=np.asarray(getattr(msg, "invalid_vertices", ()), dtype=np.int64),
        removed_elements=np.asarray(getattr(msg, "removed_elements", ()), dtype=np.int64),
    )


def status_record(result: Any, frame_id: str) -> StatusRecord:
    """The EstimatorStatus record of one update (a core.estimation.estimator.StepResult; shared by the
    replay and the estimator node)."""
    return StatusRecord(
        stamp_ns=result.stamp_ns, frame_id=frame_id, step=result.step, iterations=result.iterations,
        initial_cost=result.initial_cost, final_cost=result.final_cost, solve_time_ms=result.solve_time_ms,
        num_points=result.num_points, num_points_rejected=result.num_points_rejected,
        window_size=result.window_size, converged=result.converged, degraded=result.degraded,
        message=result.message,
    )


def status_to_msg(record: StatusRecord, factory: MessageFactory | None = None) -> Any:
    """meshfg_msgs/EstimatorStatus message for `record`."""
    factory = _default_factory(factory)
    return factory.make(
        ESTIMATOR_STATUS,
        header=header_msg(record.stamp_ns, record.frame_id, factory),
        step=record.step,
        iterations=record.iterations,
        initial_cost=record.initial_cost,
        final_cost=record.final_cost,
        solve_time_ms=record.solve_time_ms,
        num_points=record.num_points,
        num_points_rejected=record.num_points_rejected,
        window_size=record.window_size,
        converged=record.converged,
        degraded=record.degraded,
        message=record.message,
    )


def status_from_msg(msg: Any) -> StatusRecord:
    """StatusRecord from an EstimatorStatus message of either flavour."""
    return StatusRecord(
        stamp_ns=stamp_ns_from_msg(msg.header.stamp),
        frame_id=msg.header.frame_id,
        step=msg.step,
        iterations=msg.iterations,
        initial_cost=msg.initial_cost,
        final_cost=msg.final_cost,
        solve_time_ms=msg.solve_time_ms,
        num_points=msg.num_points,
        num_points_rejected=msg.num_points_rejected,
        window_size=msg.window_size,
        converged=msg.converged,
        degraded=msg.degraded,
        message=msg.message,
    )


def pose_to_msg(record: PoseRecord, factory: MessageFactory | None = None) -> Any:
    """geometry_msgs/PoseStamped message for `record`."""
    factory = _default_factory(factory)
    x, y, z, qx, qy, qz, qw = (float(v) for v in record.pose)
    pose = factory.make(
        "geometry_msgs/msg/Pose",
        position=factory.make("geometry_msgs/msg/Point", x=x, y=y, z=z),
        orientation=factory.make("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
    )
    return factory.make(POSE_STAMPED, header=header_msg(record.stamp_ns, record.frame_id, factory), pose=pose)


def vector_msg(stamp_ns: int, frame_id: str, vector: np.ndarray, factory: MessageFactory | None = None) -> Any:
    """geometry_msgs/Vector3Stamped of `vector` (3,), e.g. the learnt body acceleration."""
    factory = _default_factory(factory)
    x, y, z = (float(v) for v in vector)
    return factory.make("geometry_msgs/msg/Vector3Stamped", header=header_msg(stamp_ns, frame_id, factory),
                        vector=factory.make("geometry_msgs/msg/Vector3", x=x, y=y, z=z))


def pose_from_msg(msg: Any) -> PoseRecord:
    """PoseRecord from a PoseStamped message of either flavour."""
    position, orientation = msg.pose.position, msg.pose.orientation
    return PoseRecord(
        stamp_ns=stamp_ns_from_msg(msg.header.stamp),
        frame_id=msg.header.frame_id,
        pose=[position.x, position.y, position.z, orientation.x, orientation.y, orientation.z, orientation.w],
    )
