"""sim_bridge_server: this project's elastic simulator behind the XPBD simulator's sim_bridge
service, to try and test the estimator's prediction_source sim_bridge without the C++ simulator.

Like the authors' simulator it runs on its own, driven by the tool: each `tool_pose`
(geometry_msgs/PoseStamped in its world_frame, QoS per tool_pose_reliable) moves its state
(core.physics.simulator.ElasticSimulator, the simulation node's model and parameters but the
learning switches, open loop, from the initial mesh of mesh_file or `initial_mesh`; in grasp
mode grasped_vertices follow the tool), and the service `/sim/factor_graph_state`
(sim_bridge/srv/FactorGraphState; remap it with -r) answers with its current state in
world_frame (run it with -p world_frame:=sim/world for the authors' frame) and, when asked,
the corotational FEM stiffness at that state as a full symmetric COO matrix in float32 with the
fixed vertices' dofs at HELD_DOF_STIFFNESS on the diagonal, as the authors' bridge sends them.
It cuts on `remove_elements` (std_msgs/UInt32MultiArray: element slots, as the simulation node
takes them; core/geometry/topology.py): the answers then keep every slot, list the removed elements and
the vertices left without one in `invalid_indices`, and the stiffness is the remaining
elements'. Its counters and health go to `/diagnostics` every second (nodes/diagnostics.py,
BridgeServerCounters): tool poses rejected as malformed, in another frame than world_frame (it
places nothing through /tf) or before the mesh, and tool poses stamped back, each with its own
counter and warning; failed steps; cuts it could not take; and first, as the pipeline's nodes
do, input publishers whose QoS cannot match.

`factor_graph_state_response` builds an answer from arrays; `SimBridgeService` serves answers
from any function of the request (the tests serve scripted states with it).
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np
import scipy.sparse
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import UInt32MultiArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sim_bridge.srv import FactorGraphState

from meshfg_ros.core.physics.external_prior import held_dof_stiffness
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.geometry.mesh import InvalidMeshError, TetMesh
from meshfg_ros.core.inputs.pose_history import InvalidPoseError, as_pose
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorInputError
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError
from meshfg_ros.io.messages import MessageValidationError, header_msg, pose_from_msg
from meshfg_ros.nodes.diagnostics import (
    BridgeServerCounters,
    BridgeServerHealth,
    diagnostic_array,
    with_setup_problems,
)
from meshfg_ros.nodes.publisher_qos import TOPIC_TABLE_FIX, IncompatiblePublishers
from meshfg_ros.nodes.ros_conversions import (
    LATCHED_QOS,
    RCLPY_FACTORY,
    REQUEST_QOS,
    STREAM_QOS,
    TOOL_POSE_QOS_FIX,
    InitialMeshSource,
    tool_pose_qos,
)
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.parameters import OpenLoopSimulatorConfig, config_from_parameters

__all__ = ["SERVICE", "SimBridgeServer", "SimBridgeService", "factor_graph_state_response"]

SERVICE = "/sim/factor_graph_state"
_MAX_STEP_S = 0.1  # a pause in the tool poses is not simulated as one long step
_REPORT_PERIOD_S = 1.0


def factor_graph_state_response(positions: np.ndarray, mesh: TetMesh, frame_id: str, stamp_ns: int,
                                stiffness: scipy.sparse.spmatrix | None = None) -> FactorGraphState.Response:
    """The service's answer: `positions` (N, 3) of `mesh`'s vertices, its surface triangles, its
    element slots (`all_tetrahedra`, those a cut removed and the vertices left without an
    element listed as invalid) and `stiffness` (3N, 3N) as float32 COO with the fixed vertices'
    rows and columns cleared and HELD_DOF_STIFFNESS on their diagonal (external_prior.held_dof_stiffness)."""
    header = header_msg(stamp_ns, frame_id, RCLPY_FACTORY)
    response = FactorGraphState.Response()
    state = response.fg_state.sim_mesh
    response.fg_state.header = state.header = state.vertices.header = header
    state.faces.header = state.elements.header = header
    state.vertices.size = mesh.vertex_count - len(mesh.invalid_vertices)
    state.vertices.invalid_indices = RCLPY_FACTORY.sequence(mesh.invalid_vertices, np.int32)
    state.vertices.data = RCLPY_FACTORY.sequence(positions, np.float64)
    state.faces.size = len(mesh.surface_triangles)
    state.faces.data = RCLPY_FACTORY.sequence(mesh.surface_triangles, np.int32)
    state.elements.size = len(mesh.tetrahedra)
    state.elements.data = RCLPY_FACTORY.sequence(mesh.all_tetrahedra, np.int32)
    state.elements.invalid_indices = RCLPY_FACTORY.sequence(mesh.removed_elements, np.int32)
    if stiffness is not None:
        rows, cols, values, shape = held_dof_stiffness(stiffness, mesh.boundary_vertices)  # a removed vertex is no boundary
        out = response.fg_state.sim_stiffness_mat
        out.header = header
        out.rows, out.cols = shape
        out.row_indices = RCLPY_FACTORY.sequence(rows, np.int32)
        out.col_indices = RCLPY_FACTORY.sequence(cols, np.int32)
        out.values = RCLPY_FACTORY.sequence(values, np.float32)
    response.updated_last_mesh = state
    return response


class SimBridgeService:
    """The service on `node`, answering each request with `answer(request)` (a Response)."""

    def __init__(self, node: Node, answer: Callable[[FactorGraphState.Request], FactorGraphState.Response],
                 name: str = SERVICE) -> None:
        self._answer = answer
        self.calls = 0
        node.create_service(FactorGraphState, name, self._serve)

    def _serve(self, request, response):
        self.calls += 1
        return self._answer(request)


class ServerReports:
    """sim_bridge_server's counters and health (nodes/diagnostics.py) on /diagnostics every second,
    with its wiring first: input publishers whose QoS cannot match (`unmatched_publishers`) and
    what run_nodes found wrong in the set-up (`setup_warnings`)."""

    def __init__(self, node: Node, waiting_for_mesh: Callable[[], bool],
                 unmatched_publishers: Callable[[], list[str]]) -> None:
        self._node, self._waiting_for_mesh, self._unmatched_publishers = node, waiting_for_mesh, unmatched_publishers
        self.counters = BridgeServerCounters()
        self.health = BridgeServerHealth()
        self.setup_warnings: list[str] = []
        self._diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        node.create_timer(_REPORT_PERIOD_S, self.report, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def count(self, counter: str, reason: str) -> None:
        """One more of `counter`; `reason` is the newest problem. The caller logs it: rclpy throttles
        a warning per call site, so each cause's warnings are throttled apart."""
        self.counters.count(counter)
        self.health.last_problem = reason

    def report(self) -> None:
        """Publish the counters with the level and reason."""
        health = self.health.assess(self.counters, self._waiting_for_mesh())
        level, message = with_setup_problems(*health, self._unmatched_publishers(), self.setup_warnings)
        self._diagnostics.publish(diagnostic_array(f"{self._node.get_fully_qualified_name()}: sim_bridge", level,
                                                   message, self.counters, self._node.get_clock().now().nanoseconds))


class SimBridgeServer(Node):
    """The project's simulator behind the sim_bridge service (module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("sim_bridge_server", **kwargs)
        self.params = declare_parameters(self, "sim_bridge_server")
        self._frame = self.params["world_frame"]
        self._config = config_from_parameters(OpenLoopSimulatorConfig, self.params)
        self._grasped_vertices = self.params["grasped_vertices"] or None
        self._simulator: ElasticSimulator | None = None
        self._model: ElasticModel | None = None
        self._mesh: TetMesh | None = None
        self._state: np.ndarray | None = None
        self._last_stamp_ns: int | None = None
        self._mesh_source = InitialMeshSource(self, self._frame, self._set_mesh, on_rejected=self._mesh_rejected)
        tool_pose = tool_pose_qos(self.params)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, tool_pose)
        self.create_subscription(UInt32MultiArray, "remove_elements", self._on_remove_elements, REQUEST_QOS)
        input_qos = IncompatiblePublishers(self)
        input_qos.watch("tool_pose", tool_pose, TOOL_POSE_QOS_FIX)
        for topic, qos in (("remove_elements", REQUEST_QOS), ("initial_mesh", LATCHED_QOS)):
            input_qos.watch(topic, qos, TOPIC_TABLE_FIX)
        self.reports = ServerReports(self, lambda: self._simulator is None, input_qos.find)
        self.setup_warnings = self.reports.setup_warnings  # what run_nodes found wrong in the set-up
        self.service = SimBridgeService(self, self._respond)
        self._mesh_source.load_file(self.params)

    def _mesh_rejected(self, reason: str) -> None:
        self.reports.counters.count("initial_meshes_rejected")
        self.reports.health.last_mesh_rejection = reason

    def _set_mesh(self, mesh: TetMesh, state) -> None:
        self._simulator = ElasticSimulator(mesh, self._config, self._grasped_vertices)
        self._model = self._elastic_model(mesh)
        self._mesh, self._state, self._last_stamp_ns = mesh, mesh.vertices.copy(), None

    def _elastic_model(self, mesh: TetMesh) -> ElasticModel:
        return ElasticModel(mesh.vertices, mesh.tetrahedra, self._config.youngs_modulus, self._config.poisson_ratio)

    def _on_remove_elements(self, msg: UInt32MultiArray) -> None:
        if self._simulator is None:
            reason = "remove_elements before the mesh: ignored"
            self.get_logger().warning(reason)
            return self.reports.count("cuts_rejected", reason)
        try:
            changed = self._simulator.remove_elements(np.asarray(msg.data, dtype=np.int64))
        except (InvalidMeshError, NotPositiveDefiniteError, SimulatorInputError) as error:  # a cut it cannot make
            # (one that removes every grasped vertex, say) leaves it as it was
            reason = f"cut refused: {error}"
            self.get_logger().warning(reason)
            return self.reports.count("cuts_rejected", reason)
        if changed:
            self._mesh = self._simulator.rest_mesh
            self._model = self._elastic_model(self._mesh)
            self.get_logger().info(f"cut: {self._mesh.removed_elements.size} elements removed, "
                                   f"{self._mesh.invalid_vertices.size} vertices invalid")

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        """One simulation step to the pose, over the time since the previous pose's stamp (at most
        _MAX_STEP_S). The first pose after a mesh sets the tool (and a grasp's reference) there
        without a step; one stamped at or before the previous puts the tool there without a step
        and keeps the grasp's reference (one that goes back, as a restarted recording's, is
        counted and warned of). Each cause of a pose the server cannot take has its own counter
        and warning (each throttled on its own)."""
        self.reports.counters.tool_poses_received += 1
        try:
            record = pose_from_msg(msg)
            pose = as_pose(record.pose)  # a quaternion too short to normalise is malformed too
        except (MessageValidationError, InvalidPoseError) as error:
            reason = f"tool_pose rejected: {error}"
            self.get_logger().warning(reason, throttle_duration_sec=1.0)
            return self.reports.count("tool_poses_rejected_malformed", reason)
        if record.frame_id.strip("/") != self._frame.strip("/"):
            reason = (f"tool_pose in frame {record.frame_id!r} rejected: this server takes tool poses in its "
                      f"world_frame {self._frame!r} only; publish them there, or set world_frame")
            self.get_logger().warning(reason, throttle_duration_sec=1.0)
            return self.reports.count("tool_poses_rejected_frame", reason)
        if self._simulator is None:
            reason = "tool_pose before the mesh ignored: set mesh_file or publish initial_mesh"
            self.get_logger().warning(reason, throttle_duration_sec=1.0)
            return self.reports.count("tool_poses_rejected_before_mesh", reason)
        previous_ns, self._last_stamp_ns = self._last_stamp_ns, record.stamp_ns
        if previous_ns is None:
            return self._simulator.reset(pose)
        if record.stamp_ns < previous_ns:
            reason = (f"tool_pose stamped {(previous_ns - record.stamp_ns) / 1e9:.3f} s before the previous one: "
                      "the tool is put there without a simulation step")
            self.get_logger().warning(reason, throttle_duration_sec=1.0)
            self.reports.count("tool_poses_stamped_back", reason)
        if record.stamp_ns <= previous_ns:
            return self._simulator.place_tool(pose)
        dt = min((record.stamp_ns - previous_ns) * 1e-9, _MAX_STEP_S)
        try:
            self._state = self._simulator.predict(self._state, pose, dt)
        except Exception as error:  # noqa: BLE001 - a failed step keeps the last state, as a simulator would
            reason = f"simulation step failed, state kept: {error}"
            self.get_logger().warning(reason, throttle_duration_sec=1.0)
            self.reports.count("steps_failed", reason)

    def _respond(self, request) -> FactorGraphState.Response:
        if self._mesh is None:
            return FactorGraphState.Response()  # no mesh yet: an empty answer, which a client refuses
        stiffness = (self._model.stiffness(self._state, kind="corotational") if request.compute_stiffness_matrix
                     else None)
        return factor_graph_state_response(self._state, self._mesh, self._frame, self.get_clock().now().nanoseconds,
                                           stiffness)


def main(args=None) -> int:
    """Console script `sim_bridge_server` (accepts --ros-args)."""
    return run_nodes("sim_bridge_server", [SimBridgeServer], args=args)


if __name__ == "__main__":
    sys.exit(main())
