"""simulation_node: the physics prior, as a ROS 2 node (a shell over core.scheduler.PredictionScheduler).

Subscribes `tool_pose` (geometry_msgs/PoseStamped, any rate, any frame placed through /tf and
/tf_static), `prediction_request`
(std_msgs/Header: the stamp of each cloud the estimator accepted), `estimated_mesh` and
`initial_mesh` (meshfg_msgs/TetraMesh; or parameter mesh_file) and `remove_elements`
(std_msgs/UInt32MultiArray: element slots to cut away, core/geometry/topology.py; the tool's blade, when
blade_half_extents is set, cuts too, at each tool pose). For each request it publishes
`predicted_mesh` (TetraMesh at the cloud's stamp: the simulator moved from the estimate of the
previous request to the tool pose interpolated at the cloud's stamp), or `prediction_failed`
(meshfg_msgs/PredictionFailure, same stamp, with the reason) so that the estimator runs that step
at once without one. A predicted_mesh is on the simulator's topology: after a cut its tetrahedra
and surface are the remaining ones and it lists removed_elements and invalid_vertices, which the
estimator follows. After each estimate it takes it publishes `body_acceleration`
(geometry_msgs/Vector3Stamped at the estimate's stamp, m/s^2): the unmodelled body load learnt so
far (core/physics/body_load.py; not published with estimate_body_load off). The Poisson ratio the
predictions use (core/physics/poisson_ratio.py) is in the diagnostics. The waits and the stamp rule
are the scheduler's; counters go to /diagnostics.
Tool poses, requests and estimates that arrive before the mesh are held until it comes
(nodes/held_inputs.py).
"""

from __future__ import annotations

import sys
import time
from collections import Counter

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header, UInt32MultiArray

from meshfg_msgs.msg import PredictionFailure, TetraMesh
from meshfg_ros.core.scheduler import MAX_QUEUED_CLOUDS, PredictionScheduler, SchedulingTimeouts
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError
from meshfg_ros.core.geometry.mesh import InvalidMeshError
from meshfg_ros.core.inputs.tool_poses import DEFAULT_MAX_SAMPLES
from meshfg_ros.core.geometry.topology import cut_elements
from meshfg_ros.core.inputs.world_frame import POSE, FramedInput, Unplaceable
from meshfg_ros.io.messages import (MeshState, MessageValidationError, header_msg, pose_from_msg, stamp_ns_from_msg,
                                    vector_msg)
from meshfg_ros.nodes.diagnostics import (SimulatorCounters, diagnostic_array, waiting_for_mesh_message,
                                          with_setup_problems)
from meshfg_ros.nodes.frame_inputs import TF_QOS, TF_STATIC_QOS, FrameInputs
from meshfg_ros.nodes.held_inputs import HeldUntilMesh
from meshfg_ros.nodes.ros_conversions import (
    LATCHED_QOS,
    PREDICTION_QOS,
    RCLPY_FACTORY,
    REQUEST_QOS,
    STREAM_QOS,
    TOOL_POSE_QOS_FIX,
    InitialMeshSource,
    MeshMessages,
    position_std_from_msg,
    positions_from_msg,
    tool_pose_qos,
)
from meshfg_ros.nodes.publisher_qos import TOPIC_TABLE_FIX, IncompatiblePublishers
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.parameters import simulator_config, world_frame_inputs

_POLL_PERIOD_S = 0.02
_DIAGNOSTICS_PERIOD_S = 1.0


class SimulationNode(Node):
    """Simulator predictions at the stamps the estimator asks for (see the module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("simulation_node", **kwargs)
        self.params = declare_parameters(self, "simulation_node")
        self._frame = self.params["world_frame"]
        self.counters = SimulatorCounters()
        self._scheduler: PredictionScheduler | None = None
        self._messages: MeshMessages | None = None
        self._last_failure: str | None = None
        self._rejected_at_last_report = 0
        self._ignored_at_last_report = 0
        self._std_ignored_at_last_report = 0
        self._unavailable_earlier: Counter[str] = Counter()  # of the schedulers of earlier meshes
        self._held = HeldUntilMesh({"tool pose": DEFAULT_MAX_SAMPLES, "estimated_mesh": MAX_QUEUED_CLOUDS,
                                    "prediction request": MAX_QUEUED_CLOUDS, "remove_elements": MAX_QUEUED_CLOUDS})
        self._publisher = self.create_publisher(TetraMesh, "predicted_mesh", PREDICTION_QOS)
        self._failure_publisher = self.create_publisher(PredictionFailure, "prediction_failed", PREDICTION_QOS)
        self._load_publisher = self.create_publisher(Vector3Stamped, "body_acceleration", PREDICTION_QOS)
        self._diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self._mesh = InitialMeshSource(self, self._frame, self._set_mesh, self._held.release)
        self._inputs = FrameInputs(self, world_frame_inputs(self.params), self._on_placed, self._on_unplaceable)
        self.create_subscription(TetraMesh, "estimated_mesh", self._on_estimate, LATCHED_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, tool_pose_qos(self.params))
        self.create_subscription(Header, "prediction_request", self._on_request, REQUEST_QOS)
        self.create_subscription(UInt32MultiArray, "remove_elements", self._on_remove_elements, REQUEST_QOS)
        self.setup_warnings: list[str] = []  # what run_nodes found wrong in the set-up (a parameters file)
        self._input_qos = IncompatiblePublishers(self)
        self._input_qos.watch("tool_pose", tool_pose_qos(self.params), TOOL_POSE_QOS_FIX)
        for topic, qos in (("estimated_mesh", LATCHED_QOS), ("prediction_request", REQUEST_QOS),
                           ("initial_mesh", LATCHED_QOS), ("/tf", TF_QOS), ("/tf_static", TF_STATIC_QOS)):
            self._input_qos.watch(topic, qos, TOPIC_TABLE_FIX)
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # waits on wall time, also with use_sim_time
        self.create_timer(_POLL_PERIOD_S, self._answer, clock=steady)
        self.create_timer(_DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=steady)
        self._mesh.load_file(self.params)

    def _set_mesh(self, mesh, state) -> None:
        timeouts = SchedulingTimeouts(estimate_timeout=self.params["estimate_timeout"],
                                      tool_pose_timeout=self.params["tool_pose_timeout"])
        if self._scheduler is not None:  # a new mesh: the counters are since the node started
            self._unavailable_earlier.update(self._scheduler.tool_pose_unavailable)
        self._scheduler = PredictionScheduler(
            mesh, simulator_config(self.params), self.params["grasped_vertices"] or None, timeouts=timeouts,
            clock_jump_threshold=self.params["clock_jump_threshold"],
            tool_pose_extrapolation=self.params["tool_pose_horizon"], newest_first=self.params["newest_first"])
        self._messages = MeshMessages(state)

    def _hold(self, kind: str, handler, item) -> None:
        """Keep an input that came before the mesh for `handler` (counted; an overflow drops the
        oldest of its kind)."""
        self.counters.count("inputs_held_before_mesh")
        dropped = self._held.hold(kind, handler, item)
        if dropped is not None:
            self._count("inputs_dropped_before_mesh", dropped)

    def _on_estimate(self, msg: TetraMesh) -> None:
        if self._scheduler is None:
            return self._hold("estimated_mesh", self._on_estimate, msg)
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = positions_from_msg(msg, self._scheduler.mesh.vertex_count)
        # A malformed estimate is no estimate: the next request does not wait for it.
        position_std = position_std_from_msg(msg, self._scheduler.mesh.vertex_count)
        if positions is not None and position_std is None and len(msg.position_std):
            self._count("estimate_std_ignored", f"estimated_mesh at {stamp_ns} ns: position_std has a wrong count "
                        "or entries NaN or negative; the body load and the Poisson ratio learn nothing from it")
        rejection = self._scheduler.add_estimate(stamp_ns, positions, degraded=bool(msg.degraded),
                                                 position_std=position_std)
        if positions is None:
            self._count("estimates_ignored", f"estimated_mesh at {stamp_ns} ns ignored: wrong vertex count or "
                        "non-finite positions")
        elif rejection is not None:
            self._count(rejection.counter, rejection.reason)
        elif self._scheduler.body_load is not None and self._scheduler.state_stamp_ns == stamp_ns:
            self._load_publisher.publish(vector_msg(stamp_ns, self._frame, self._scheduler.body_load.acceleration,
                                                    RCLPY_FACTORY))
        self._answer()

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        self.counters.tool_poses_received += 1
        try:
            record = pose_from_msg(msg)
        except MessageValidationError as error:
            return self._count("tool_poses_rejected_malformed", f"tool_pose rejected: {error}")
        self._inputs.add(FramedInput(POSE, record.stamp_ns, record.frame_id, record.pose, time.monotonic()))

    def _on_placed(self, item: FramedInput) -> None:
        """A tool pose in world_frame."""
        if self._scheduler is None:
            return self._hold("tool pose", self._on_placed, item)
        rejection = self._scheduler.add_tool_pose(item.stamp_ns, item.data)
        if rejection is not None:
            return self._count(rejection.counter, rejection.reason)
        self._cut_with_blade(item.data)
        if self._scheduler.restarted:
            self.counters.clock_jumps_back += 1
            self.get_logger().warning("tool_pose stamp jumped back: restarting from the initial mesh")
        self._answer()

    def _cut_with_blade(self, pose) -> None:
        """Cut away what the blade box (blade_half_extents about blade_offset, in the tool frame at
        `pose`) reaches at the state the next prediction starts from."""
        half_extents = np.asarray(self.params["blade_half_extents"], dtype=np.float64)
        if not half_extents.any():
            return
        rotation = Rotation.from_quat(pose[3:]).as_matrix()
        centre = pose[:3] + rotation @ np.asarray(self.params["blade_offset"], dtype=np.float64)
        mesh = self._scheduler.mesh.with_vertices(self._scheduler.state)
        self._remove_elements(cut_elements(mesh, centre, half_extents, rotation), "the blade")

    def _on_remove_elements(self, msg: UInt32MultiArray) -> None:
        if self._scheduler is None:
            return self._hold("remove_elements", self._on_remove_elements, msg)
        self._remove_elements(np.asarray(msg.data, dtype=np.int64), "remove_elements")

    def _remove_elements(self, slots: np.ndarray, source: str) -> None:
        """Cut the element slots away from the next prediction on; the predictions carry the cut
        mesh's topology. A cut the simulator cannot take (a slot out of range, every element, a
        piece left with rigid modes) is counted and changes nothing."""
        removed_before = self._scheduler.mesh.removed_elements.size
        try:
            changed = self._scheduler.remove_elements(slots)
        except (InvalidMeshError, NotPositiveDefiniteError) as error:
            return self._count("cuts_rejected", f"cut from {source} rejected: {error}")
        if changed:
            mesh = self._scheduler.mesh
            self.counters.elements_removed = int(mesh.removed_elements.size)
            self._messages = MeshMessages(MeshState.of_mesh(mesh, 0, self._frame, 0))
            self.get_logger().info(f"cut ({source}): {mesh.removed_elements.size - removed_before} elements removed, "
                                   f"{mesh.tetrahedron_count} left, {mesh.invalid_vertices.size} vertices invalid")

    def _on_unplaceable(self, unplaceable: Unplaceable) -> None:
        self._count("tool_poses_rejected_frame", f"tool_pose rejected: {unplaceable.reason}")

    def _on_request(self, msg: Header) -> None:
        """A cloud's stamp to predict; a held one waits for its estimate and pose from the mesh's
        arrival on (the estimate_timeout counts from then)."""
        if self._scheduler is None:
            return self._hold("prediction request", self._on_request, msg)
        self.counters.requests += 1
        self._scheduler.request(stamp_ns_from_msg(msg.stamp), time.monotonic())
        self._answer()

    def _answer(self) -> None:
        if self._scheduler is None:
            return
        start = time.perf_counter()
        answers = self._scheduler.poll(time.monotonic())
        predicted = sum(answer.positions is not None for answer in answers)
        if predicted:
            self.counters.last_prediction_ms = 1e3 * (time.perf_counter() - start) / predicted
        for answer in answers:
            if answer.superseded:
                self.counters.predictions_superseded += 1
                self._failure_publisher.publish(PredictionFailure(
                    header=header_msg(answer.stamp_ns, self._frame, RCLPY_FACTORY), reason=answer.failure,
                    superseded=True))
                continue
            if answer.positions is None:
                self.counters.predictions_failed += 1
                self._last_failure = answer.failure
                self.get_logger().warning(f"no prediction for {answer.stamp_ns} ns: {answer.failure}",
                                          throttle_duration_sec=1.0)
                self._failure_publisher.publish(PredictionFailure(
                    header=header_msg(answer.stamp_ns, self._frame, RCLPY_FACTORY), reason=answer.failure))
                continue
            self.counters.predictions += 1
            self._last_failure = None
            self._publisher.publish(self._messages.message(answer.stamp_ns, self._frame, self.counters.predictions,
                                                           answer.positions))

    def _count(self, counter: str, reason: str) -> None:
        self.counters.count(counter)
        self.get_logger().warning(reason, throttle_duration_sec=1.0)

    def _publish_diagnostics(self) -> None:
        """The counters, with OK / WARN: waiting for the mesh, rejected tool poses, ignored estimates,
        estimates with a malformed std, a failed prediction."""
        counters = self.counters
        if self._scheduler is not None:
            totals = self._unavailable_earlier + Counter(self._scheduler.tool_pose_unavailable)
            for reason, count in totals.items():
                setattr(counters, f"tool_pose_unavailable_{reason}", count)
            if self._scheduler.body_load is not None:
                (counters.body_acceleration_x, counters.body_acceleration_y,
                 counters.body_acceleration_z) = self._scheduler.body_load.acceleration.tolist()
            counters.poisson_ratio = self._scheduler.simulator.poisson_ratio
        new_rejections = counters.tool_poses_rejected - self._rejected_at_last_report
        new_ignored = counters.estimates_ignored - self._ignored_at_last_report
        new_std_ignored = counters.estimate_std_ignored - self._std_ignored_at_last_report
        self._rejected_at_last_report = counters.tool_poses_rejected
        self._ignored_at_last_report = counters.estimates_ignored
        self._std_ignored_at_last_report = counters.estimate_std_ignored
        level, message = DiagnosticStatus.OK, "predicting"
        if self._scheduler is None:
            level, message = DiagnosticStatus.WARN, waiting_for_mesh_message(counters)
        elif counters.requests and not counters.tool_poses_received:
            level, message = DiagnosticStatus.WARN, (
                f"{counters.requests} prediction requests but no tool pose received: every step runs without a "
                "prediction; publish tool_pose (geometry_msgs/PoseStamped) in this node's namespace, with a QoS "
                "it matches")
        elif new_rejections:
            level, message = DiagnosticStatus.WARN, f"{new_rejections} tool poses rejected since the last report"
        elif new_ignored:
            level, message = DiagnosticStatus.WARN, (f"{new_ignored} estimates ignored since the last report: "
                                                     "predicting from the newest usable state")
        elif new_std_ignored:
            level, message = DiagnosticStatus.WARN, (f"{new_std_ignored} estimates' position_std malformed since the "
                                                     "last report: the model is not learnt from them")
        elif self._last_failure is not None:
            level, message = DiagnosticStatus.WARN, f"the last prediction failed: {self._last_failure}"
        level, message = with_setup_problems(level, message, self._input_qos.find(), self.setup_warnings)
        self._diagnostics_publisher.publish(diagnostic_array(
            f"{self.get_fully_qualified_name()}: simulation", level, message, counters,
            self.get_clock().now().nanoseconds))


def main(args=None) -> int:
    """Console script `simulation_node` (accepts --ros-args)."""
    return run_nodes("simulation_node", [SimulationNode], args=args)


if __name__ == "__main__":
    sys.exit(main())
