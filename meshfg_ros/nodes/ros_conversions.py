"""What the nodes need beyond meshfg_ros.io.messages: recordings -> rclpy messages, TetraMesh <->
core arrays (their parameters: nodes/ros_parameters.py).

`rclpy_message(data)` turns what RecordingReader yields (a meshfg record or any decoded
rosbags message) into the rclpy message to publish; `MeshMessages` builds the TetraMesh
messages of one mesh topology with its index arrays converted once.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.parameters import ParameterError, load_mesh_file
from meshfg_ros.io.messages import (
    TETRA_MESH,
    MeshState,
    MessageValidationError,
    RclpyMessageFactory,
    covariance_from_upper_triangles,
    covariance_upper_triangles,
    header_msg,
    mesh_state_from_msg,
)
from meshfg_ros.io.recording import RECORD_TYPES

RCLPY_FACTORY = RclpyMessageFactory()
# QoS of the nodes' topics. Meshes are latched (a late-joining planner gets the newest one);
# predictions and failure reports keep their last ten for a reader that matches late (DDS
# discovery can finish after the first prediction); requests are reliable, as every one is a step.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
PREDICTION_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
REQUEST_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
STREAM_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# tool_pose with tool_pose_reliable false: matches best-effort and reliable publishers alike.
BEST_EFFORT_POSE_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
# What to do about a tool_pose publisher the subscription cannot match (nodes/publisher_qos.py).
TOOL_POSE_QOS_FIX = "publish it reliable, or set tool_pose_reliable:=false"


def tool_pose_qos(params: dict) -> QoSProfile:
    """The tool_pose subscription's QoS that parameter tool_pose_reliable asks for."""
    return STREAM_QOS if params["tool_pose_reliable"] else BEST_EFFORT_POSE_QOS


# numpy dtype -> array.array type code of the same item size (Linux), for primitive sequences.
_TYPECODES = {
    np.dtype(np.float64): "d", np.dtype(np.float32): "f",
    np.dtype(np.int8): "b", np.dtype(np.uint8): "B",
    np.dtype(np.int16): "h", np.dtype(np.uint16): "H",
    np.dtype(np.int32): "i", np.dtype(np.uint32): "I",
    np.dtype(np.int64): "q", np.dtype(np.uint64): "Q",
}


def rclpy_message(data: Any) -> Any:
    """The rclpy message for a meshfg record or a rosbags message (converted field by field)."""
    if type(data) in RECORD_TYPES:
        _, to_msg, _ = RECORD_TYPES[type(data)]
        return to_msg(data, RCLPY_FACTORY)
    return _from_rosbags(data)


def _from_rosbags(message: Any) -> Any:
    message_class = RCLPY_FACTORY.message_class(type(message).__msgtype__)
    fields = {}
    for name, kind in message_class.get_fields_and_field_types().items():
        fields[name] = _field_value(getattr(message, name), kind)
    return message_class(**fields)


def _field_value(value: Any, kind: str) -> Any:
    if hasattr(value, "__msgtype__"):
        return _from_rosbags(value)
    if isinstance(value, np.ndarray):
        if kind.startswith("sequence<") and value.dtype in _TYPECODES:
            return array.array(_TYPECODES[value.dtype], np.ascontiguousarray(value).tobytes())
        return value  # fixed-size arrays are numpy arrays in rclpy too
    if isinstance(value, list):
        return [_field_value(item, kind) for item in value]
    return value


class MeshMessages:
    """TetraMesh messages of one topology: the index arrays are converted once, not per message."""

    def __init__(self, state: MeshState) -> None:
        self._tetrahedra = RCLPY_FACTORY.sequence(state.tetrahedra, np.uint32)
        self._surface_triangles = RCLPY_FACTORY.sequence(state.surface_triangles, np.uint32)
        self._fixed_vertices = RCLPY_FACTORY.sequence(state.fixed_vertices, np.uint32)
        self._invalid_vertices = RCLPY_FACTORY.sequence(state.invalid_vertices, np.uint32)
        self._removed_elements = RCLPY_FACTORY.sequence(state.removed_elements, np.uint32)

    def message(self, stamp_ns: int, frame_id: str, step: int, positions: np.ndarray,
                position_std: np.ndarray | None = None, degraded: bool = False,
                position_covariance: np.ndarray | None = None) -> Any:
        """TetraMesh of `positions` (N, 3) (finite: checked by the caller), optional std (N,) and
        covariance blocks (N, 3, 3, symmetric: sent as their upper triangles), and whether it is
        an estimate made without a simulator prediction."""
        std = np.zeros(0) if position_std is None else position_std
        covariance = np.zeros((0, 3, 3)) if position_covariance is None else position_covariance
        return RCLPY_FACTORY.make(
            TETRA_MESH,
            header=header_msg(stamp_ns, frame_id, RCLPY_FACTORY),
            step=int(step),
            positions=RCLPY_FACTORY.sequence(positions, np.float64),
            tetrahedra=self._tetrahedra,
            surface_triangles=self._surface_triangles,
            fixed_vertices=self._fixed_vertices,
            position_std=RCLPY_FACTORY.sequence(std, np.float32),
            degraded=bool(degraded),
            position_covariance=RCLPY_FACTORY.sequence(covariance_upper_triangles(covariance), np.float32),
            invalid_vertices=self._invalid_vertices,
            removed_elements=self._removed_elements,
        )


def positions_from_msg(msg: Any, vertex_count: int) -> np.ndarray | None:
    """Vertex positions (N, 3) of a TetraMesh, or None unless N == vertex_count and all finite."""
    positions = np.asarray(msg.positions, dtype=np.float64)
    if positions.size != 3 * vertex_count or not np.isfinite(positions).all():
        return None
    return positions.reshape(vertex_count, 3)


def position_std_from_msg(msg: Any, vertex_count: int) -> np.ndarray | None:
    """Posterior std (N,) of a TetraMesh, or None when it has none (empty) or is malformed (a
    wrong count, entries NaN or negative). An infinite entry is taken: a vertex the estimate knows
    nothing of, which the model's fit weighs by zero (core/physics/model_fit.py)."""
    std = np.asarray(msg.position_std, dtype=np.float64)
    return std if std.shape == (vertex_count,) and np.all(std >= 0.0) else None  # NaN fails >= too


def position_covariance_from_msg(msg: Any) -> np.ndarray | None:
    """Posterior covariance blocks (N, 3, 3), m^2, of a TetraMesh's vertices (symmetric, zero on
    fixed vertices), or None when it has none (an empty field). N is the message's vertex count.

    Raises MessageValidationError (a ValueError naming the first bad vertex) when the field is
    malformed: a count other than 6N, an entry NaN or infinite, a negative variance. A planner
    that reads estimated_mesh counts such a message and warns, as the simulation node does for
    a malformed position_std, and keeps the estimate's positions.
    """
    covariance = covariance_from_upper_triangles(msg.position_covariance, len(msg.positions) // 3)
    return covariance if len(covariance) else None


def same_mesh(a: MeshState, b: MeshState) -> bool:
    """Whether two mesh states have equal positions, tetrahedra and fixed vertices."""
    return (np.array_equal(a.positions, b.positions) and np.array_equal(a.tetrahedra, b.tetrahedra)
            and np.array_equal(a.fixed_vertices, b.fixed_vertices))


class InitialMeshSource:
    """The initial mesh of a node: from parameter mesh_file (read at start-up; an unreadable file
    is a ParameterError, which stops the program) or from the latched `initial_mesh` topic.
    Calls on_mesh(TetMesh, MeshState) for each new mesh (a repeated message is ignored; a
    ValueError from it refuses the mesh), then on_installed() once the mesh is in place (the
    nodes hand on what they held until then, nodes/held_inputs.py). A refused initial_mesh
    message is logged as an error and handed to on_rejected(reason) (the nodes count it and name
    it in their diagnostics)."""

    def __init__(self, node: Node, frame: str, on_mesh, on_installed=None, on_rejected=None) -> None:
        self._node, self._frame, self._on_mesh, self._on_installed = node, frame, on_mesh, on_installed
        self._on_rejected = on_rejected
        self._state: MeshState | None = None
        self.from_file = False  # whether the mesh being installed or in place is mesh_file's
        node.create_subscription(RCLPY_FACTORY.message_class(TETRA_MESH), "initial_mesh", self._on_message,
                                 LATCHED_QOS)

    def load_file(self, params: dict) -> None:
        """Load mesh_file as the parameters place it ("" : none, wait for the topic)."""
        if not params["mesh_file"]:
            return
        mesh = load_mesh_file(params)  # ParameterError: the node stops at start-up
        self.from_file = True
        try:
            self._install(MeshState(0, self._frame, 0, mesh.vertices, mesh.tetrahedra, mesh.surface_triangles,
                                    mesh.fixed_vertices), mesh)
        except ValueError as error:  # a mesh the schedulers refuse (far from the world origin, ...)
            raise ParameterError(f"mesh_file {params['mesh_file']}: {error}") from None
        self._installed()

    def _on_message(self, msg: Any) -> None:
        try:
            state = mesh_state_from_msg(msg)
        except MessageValidationError as error:
            return self._rejected(f"initial_mesh rejected: {error}")
        if state.frame_id != self._frame:
            return self._rejected(f"initial_mesh in frame {state.frame_id!r}, expected {self._frame!r}: rejected")
        if self._state is not None and same_mesh(self._state, state):
            return  # the latched message again (e.g. a reconnection)
        from_file, self.from_file = self.from_file, False
        try:
            self._install(state, state.tet_mesh())
        except ValueError as error:
            self.from_file = from_file
            return self._rejected(f"initial_mesh rejected: {error}")
        self._installed()

    def _rejected(self, reason: str) -> None:
        self._node.get_logger().error(reason)
        if self._on_rejected is not None:
            self._on_rejected(reason)

    def _installed(self) -> None:
        if self._on_installed is not None:
            self._on_installed()

    def _install(self, state: MeshState, mesh: TetMesh) -> None:
        restart = self._state is not None
        self._on_mesh(mesh, state)
        self._state = state
        if restart:
            self._node.get_logger().warning("new initial mesh: restarting from it")
        self._node.get_logger().info(f"initial mesh: {mesh.vertex_count} vertices, {mesh.tetrahedron_count} "
                                     f"tetrahedra, {mesh.fixed_vertices.size} fixed vertices")
