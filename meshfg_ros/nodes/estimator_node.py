"""estimator_node: the sliding-window factor-graph estimator, as a ROS 2 node (a shell over
core.scheduler.EstimationScheduler).

Subscribes `points` (sensor_msgs/PointCloud2, any frame placed through /tf, sensor-data QoS
unless points_reliable), `tool_pose` (geometry_msgs/PoseStamped, any frame and rate: points on
the tool are segmentation leaks), `predicted_mesh` and `prediction_failed` (the simulation node's
answers), `initial_mesh` (or parameter mesh_file), /tf and /tf_static. Each accepted cloud is
announced on `prediction_request` (std_msgs/Header). Publishes `estimated_mesh` (TetraMesh with
position_std; latched for late-joining planners), `status` (meshfg_msgs/EstimatorStatus),
`markers` (only while someone subscribes) and `/diagnostics` (counters, stage times and health:
nodes/diagnostics.py). Nothing non-finite is published. Updates run in their own thread, so a
long solve does not make DDS drop input.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from meshfg_msgs.msg import EstimatorStatus, PredictionFailure, TetraMesh
from meshfg_ros import blas
from meshfg_ros.core.scheduler import EstimationScheduler, Prediction, Rejection, SchedulingTimeouts, StepOutcome
from meshfg_ros.core.world_frame import CLOUD, POSE, FramedInput, Unplaceable
from meshfg_ros.io.messages import MessageValidationError, header_msg, pose_from_msg, stamp_ns_from_msg, status_record
from meshfg_ros.io.messages import status_to_msg
from meshfg_ros.io.pointcloud import PointCloudError, cloud_record_from_msg
from meshfg_ros.markers import mesh_markers, surface_edges
from meshfg_ros.nodes.diagnostics import EstimatorCounters, EstimatorHealth, diagnostic_array
from meshfg_ros.nodes.frame_inputs import FrameInputs
from meshfg_ros.nodes.ros_conversions import LATCHED_QOS, PREDICTION_QOS, RCLPY_FACTORY, REQUEST_QOS, STREAM_QOS
from meshfg_ros.nodes.ros_conversions import InitialMeshSource, MeshMessages, positions_from_msg
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import SolverThread, run_nodes
from meshfg_ros.parameters import estimator_changes, estimator_config, world_frame_inputs

RELIABLE_POINTS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
_LATENCY_HISTORY = 100
_STALL_MARGIN_S = 1.0  # beyond the prediction wait and two time budgets: no estimate means stuck


class EstimatorNode(Node):
    """Estimated mesh per point cloud (see the module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("estimator_node", **kwargs)
        self.params = declare_parameters(self, "estimator_node", on_change=self._reconfigure)
        self._frame = self.params["world_frame"]
        self.counters = EstimatorCounters()
        budget = estimator_config(self.params).update_time_budget or 0.0
        self.health = EstimatorHealth(self.params["prediction_timeout"] + 2.0 * budget + _STALL_MARGIN_S)
        self._lock = threading.Lock()  # guards the scheduler's queues and the counters
        self._scheduler: EstimationScheduler | None = None
        self._latencies: deque[float] = deque(maxlen=_LATENCY_HISTORY)
        self._unanswered_since_s: float | None = None
        self._last_rejection, self._markers_job = "", None
        self._estimates = self.create_publisher(TetraMesh, "estimated_mesh", LATCHED_QOS)
        self._statuses = self.create_publisher(EstimatorStatus, "status", STREAM_QOS)
        self._markers = self.create_publisher(MarkerArray, "markers", STREAM_QOS)
        self._requests = self.create_publisher(Header, "prediction_request", REQUEST_QOS)
        self._diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self._mesh = InitialMeshSource(self, self._frame, self._set_mesh)
        self._inputs = FrameInputs(self, world_frame_inputs(self.params), self._on_placed, self._on_unplaceable)
        self.create_subscription(TetraMesh, "predicted_mesh", self._on_prediction, PREDICTION_QOS)
        self.create_subscription(PredictionFailure, "prediction_failed", self._on_failure, PREDICTION_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, STREAM_QOS)
        points_qos = RELIABLE_POINTS_QOS if self.params["points_reliable"] else qos_profile_sensor_data
        self.create_subscription(PointCloud2, "points", self._on_cloud, points_qos)
        self._wake_reports = self.create_guard_condition(self._publish_reports)
        self.create_timer(1.0, self._publish_reports, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._mesh.load_file(self.params)
        self._solver = SolverThread(self._next_step, self._run, self.get_logger())

    def destroy_node(self) -> None:
        self._solver.stop()
        super().destroy_node()

    def _reconfigure(self, changes: dict) -> None:
        """Dynamic parameters set while running: the estimator uses them from its next update on."""
        with self._lock:
            if self._scheduler is not None:
                self._scheduler.reconfigure(estimator_config(self.params), estimator_changes(changes))

    # ------------------------------------------------------------------ input (executor thread)
    def _set_mesh(self, mesh, state) -> None:
        scheduler = EstimationScheduler(
            mesh, estimator_config(self.params), clock_jump_threshold=self.params["clock_jump_threshold"],
            tool_pose_extrapolation=self.params["tool_pose_horizon"],
            timeouts=SchedulingTimeouts(prediction_timeout=self.params["prediction_timeout"]))
        with self._lock:
            self._scheduler, self._messages, self._edges = scheduler, MeshMessages(state), surface_edges(
                state.surface_triangles)
        self.get_logger().info(f"sparse Cholesky BLAS: {blas.backend().name}, {blas.backend().threads} thread(s)")

    def _on_cloud(self, msg: PointCloud2) -> None:
        arrival_s = time.monotonic()
        with self._lock:
            self.counters.clouds_received += 1
            self._unanswered_since_s = self._unanswered_since_s or arrival_s
        try:
            record = cloud_record_from_msg(msg)
        except (PointCloudError, MessageValidationError) as error:
            return self._note([Rejection("clouds_rejected_malformed", f"malformed cloud rejected: {error}")])
        except Exception as error:  # noqa: BLE001 - no cloud, however odd, may stop the node
            return self._note([Rejection("clouds_rejected_malformed", f"undecodable cloud rejected: {error!r}")])
        with self._lock:
            self.counters.nan_points_dropped += record.dropped_nonfinite
        if len(record.points) == 0:
            return self._note([Rejection("clouds_rejected_empty", f"cloud at {record.stamp_ns} ns has no finite "
                                         "points: rejected")])
        self._inputs.add(FramedInput(CLOUD, record.stamp_ns, record.frame_id, record.points, arrival_s))

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        try:
            record = pose_from_msg(msg)
        except (MessageValidationError, ValueError):
            return  # the simulation node counts tool poses it cannot use
        self._inputs.add(FramedInput(POSE, record.stamp_ns, record.frame_id, record.pose, time.monotonic()))

    def _on_placed(self, item: FramedInput) -> None:
        """A cloud or tool pose in world_frame: to the scheduler (a cloud also to the simulator)."""
        with self._lock:
            if self._scheduler is None:
                return
            if item.kind == POSE:
                return self._scheduler.add_tool_pose(item.stamp_ns, item.data)
            notes = self._scheduler.add_cloud(item.stamp_ns, item.data, item.arrival_s)
        if not any(note.counter in ("clouds_rejected_stamp", "clouds_rejected_registration") for note in notes):
            self._requests.publish(header_msg(item.stamp_ns, self._frame, RCLPY_FACTORY))
        self._note(notes)
        self._solver.wake()

    def _on_unplaceable(self, unplaceable: Unplaceable) -> None:
        if unplaceable.item.kind == CLOUD:
            self._note([Rejection("clouds_rejected_frame", f"cloud rejected: {unplaceable.reason}")])

    def _on_prediction(self, msg: TetraMesh) -> None:
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = positions_from_msg(msg, len(msg.positions) // 3)
        if positions is None:
            self._note([Rejection("predictions_rejected", f"predicted_mesh at {stamp_ns} ns is malformed or not "
                                  "finite: the step runs without it")])
        self._take_answer(Prediction(stamp_ns, positions, "" if positions is not None else "malformed or not finite"))

    def _on_failure(self, msg: PredictionFailure) -> None:
        self._take_answer(Prediction(stamp_ns_from_msg(msg.header.stamp), None, msg.reason), "predictions_failed")

    def _take_answer(self, answer: Prediction, counter: str = "predictions_received") -> None:
        with self._lock:
            self.counters.count(counter)
            rejection = None if self._scheduler is None else self._scheduler.add_prediction(answer)
        self._note([rejection] if rejection else [])
        self._solver.wake()

    def _note(self, rejections: list[Rejection]) -> None:
        """Count and log what was set aside."""
        for rejection in rejections:
            with self._lock:
                self.counters.count(rejection.counter)
                self._last_rejection = rejection.reason
            self.get_logger().warning(rejection.reason, throttle_duration_sec=1.0)
        if rejections:
            self._wake_reports.trigger()

    # ------------------------------------------------------------------ solver thread
    def _next_step(self) -> tuple | None:
        """(scheduler, the step it has ready) or None."""
        with self._lock:
            step = None if self._scheduler is None else self._scheduler.next_step(time.monotonic())
            return None if step is None else (self._scheduler, step)

    def _run(self, scheduler: EstimationScheduler, step) -> None:
        start_s = time.monotonic()
        try:
            outcome = scheduler.run(step, time.monotonic)
        except Exception as error:  # noqa: BLE001 - the solver thread must outlive any one failure
            outcome = StepOutcome(step, None, repr(error), "failed_steps")
        if self._solver.stopping:
            return  # shut down while it ran: the node may be gone already
        result = outcome.result
        if result is None:
            self.get_logger().error(f"update at {step.stamp_ns} ns: {outcome.error}")
            with self._lock:
                self.counters.count(outcome.counter)
            return self._wake_reports.trigger()
        publish_start = time.monotonic()
        self._estimates.publish(self._messages.message(step.stamp_ns, self._frame, result.step, result.positions,
                                                       result.position_std))
        self._statuses.publish(status_to_msg(status_record(result, self._frame), RCLPY_FACTORY))
        done = time.monotonic()
        with self._lock:
            self._latencies.append(1e3 * (done - step.arrival_s))
            self.counters.record_step(result, 1e3 * (start_s - step.arrival_s), 1e3 * (done - publish_start),
                                      list(self._latencies))
            self.health.record(result.degraded, result.converged, result.num_points, result.num_points_rejected)
            self._unanswered_since_s = None
            self._markers_job = (result.positions, result.position_std, step.points, step.stamp_ns)
        self._wake_reports.trigger()

    # ------------------------------------------------------------------ reports (executor thread)
    def _publish_reports(self) -> None:
        """Diagnostics (after each step and periodically) and markers of the newest estimate."""
        with self._lock:
            self.counters.queued_clouds = 0 if self._scheduler is None else self._scheduler.queued
            counters, job, self._markers_job = replace(self.counters), self._markers_job, None
            waiting, since, last_rejection = self._scheduler is None, self._unanswered_since_s, self._last_rejection
        unanswered_s = 0.0 if since is None else time.monotonic() - since
        level, message = self.health.assess(counters, waiting, unanswered_s, last_rejection)
        self._diagnostics.publish(diagnostic_array(f"{self.get_fully_qualified_name()}: estimation", level, message,
                                                   counters, self.get_clock().now().nanoseconds))
        if job is not None and self._markers.get_subscription_count() > 0:
            positions, position_std, points, stamp_ns = job
            self._markers.publish(mesh_markers(positions, self._mesh.state.surface_triangles, position_std, points,
                                               self._frame, stamp_ns, self.params["marker_std_max"], self._edges,
                                               RCLPY_FACTORY))


def main(args=None) -> int:
    """Console script `estimator_node` (accepts --ros-args)."""
    return run_nodes("estimator_node", [EstimatorNode], args=args)  # + its solver thread


if __name__ == "__main__":
    sys.exit(main())
