"""estimator_node: the sliding-window factor-graph estimator, as a ROS 2 node (a shell over
core.scheduler.EstimationScheduler).

Subscribes `points` (sensor_msgs/PointCloud2, sensor-data QoS unless points_reliable),
`predicted_mesh` and `initial_mesh` (meshfg_msgs/TetraMesh; or parameter mesh_file),
`prediction_failed` (meshfg_msgs/PredictionFailure) and `tool_pose` (geometry_msgs/PoseStamped,
any rate: points on the tool sphere are segmentation leaks). Each accepted cloud is announced on
`prediction_request` (std_msgs/Header) for the simulation node and waits for its answer as the
scheduler says. Publishes `estimated_mesh` (TetraMesh with position_std; latched: a late-joining
planner gets the newest state), `status` (meshfg_msgs/EstimatorStatus), `markers`
(visualization_msgs/MarkerArray, built only while someone subscribes) and `/diagnostics`
(counters, stage times and health, nodes/diagnostics.py). Nothing non-finite is ever published.

Clouds are taken in by the executor thread and solved in a thread of their own, so a long solve
does not make DDS drop input; an update stops after update_time_budget, and on shutdown the node
waits at most _STOP_WAIT_S for a running one.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import replace

import numpy as np
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
from meshfg_ros.core.input_checks import rejections_in
from meshfg_ros.core.scheduler import EstimationScheduler, Prediction, Rejection, SchedulingTimeouts, StepOutcome
from meshfg_ros.io.messages import (
    MessageValidationError, header_msg, pose_from_msg, stamp_ns_from_msg, status_record, status_to_msg,
)
from meshfg_ros.io.pointcloud import PointCloudError, cloud_record_from_msg
from meshfg_ros.markers import mesh_markers, surface_edges
from meshfg_ros.nodes.diagnostics import EstimatorCounters, EstimatorHealth, diagnostic_array
from meshfg_ros.nodes.ros_conversions import (
    LATCHED_QOS, PREDICTION_QOS, RCLPY_FACTORY, REQUEST_QOS, STREAM_QOS, InitialMeshSource, MeshMessages,
    positions_from_msg,
)
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.parameters import FrameError, cloud_to_world, estimator_changes, estimator_config

RELIABLE_POINTS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
_POLL_PERIOD_S = 0.02
_DIAGNOSTICS_PERIOD_S = 1.0
_LATENCY_HISTORY = 100
_STOP_WAIT_S = 2.0  # shutdown waits this long for a running update, then leaves the daemon thread behind
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
        self._messages: MeshMessages | None = None
        self._latencies: deque[float] = deque(maxlen=_LATENCY_HISTORY)
        self._unanswered_since_s: float | None = None
        self._last_rejection = ""
        self._markers_job = None
        self._estimate_publisher = self.create_publisher(TetraMesh, "estimated_mesh", LATCHED_QOS)
        self._status_publisher = self.create_publisher(EstimatorStatus, "status", STREAM_QOS)
        self._markers_publisher = self.create_publisher(MarkerArray, "markers", STREAM_QOS)
        self._request_publisher = self.create_publisher(Header, "prediction_request", REQUEST_QOS)
        self._diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self._mesh = InitialMeshSource(self, self._frame, self._set_mesh)
        self.create_subscription(TetraMesh, "predicted_mesh", self._on_prediction, PREDICTION_QOS)
        self.create_subscription(PredictionFailure, "prediction_failed", self._on_failure, PREDICTION_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, STREAM_QOS)
        points_qos = RELIABLE_POINTS_QOS if self.params["points_reliable"] else qos_profile_sensor_data
        self.create_subscription(PointCloud2, "points", self._on_cloud, points_qos)
        self._wake_reports = self.create_guard_condition(self._publish_reports)
        self.create_timer(_DIAGNOSTICS_PERIOD_S, self._publish_reports, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._mesh.load_file(self.params["mesh_file"])
        self._wakeup, self._stopping = threading.Event(), False
        self._solver = threading.Thread(target=self._solver_loop, name="meshfg-solver", daemon=True)
        self._solver.start()

    def destroy_node(self) -> None:
        """Stop the solver thread (a running update has _STOP_WAIT_S to finish), then the node."""
        self._stopping = True
        self._wakeup.set()
        self._solver.join(_STOP_WAIT_S)
        if self._solver.is_alive():
            self.get_logger().warning(f"an update still runs after {_STOP_WAIT_S:g} s: left behind at shutdown")
        super().destroy_node()

    def _reconfigure(self, changes: dict) -> None:
        """Dynamic parameters set while running: the estimator uses them from its next update on."""
        with self._lock:
            if self._scheduler is not None:
                self._scheduler.reconfigure(estimator_config(self.params), estimator_changes(changes))

    # ------------------------------------------------------------------ input (executor thread)
    def _set_mesh(self, mesh, state) -> None:
        timeouts = SchedulingTimeouts(prediction_timeout=self.params["prediction_timeout"])
        scheduler = EstimationScheduler(mesh, estimator_config(self.params), timeouts=timeouts,
                                        clock_jump_threshold=self.params["clock_jump_threshold"])
        with self._lock:
            self._scheduler, self._messages, self._edges = scheduler, MeshMessages(state), surface_edges(
                state.surface_triangles)
        self.get_logger().info(f"sparse Cholesky BLAS: {blas.backend().name}, {blas.backend().threads} thread(s)")

    def _on_cloud(self, msg: PointCloud2) -> None:
        arrival_s = time.monotonic()
        with self._lock:
            self.counters.clouds_received += 1
            if self._unanswered_since_s is None:
                self._unanswered_since_s = arrival_s
        try:
            record = cloud_record_from_msg(msg)
            points = cloud_to_world(record.points, record.frame_id, self.params)
        except (PointCloudError, MessageValidationError) as error:
            return self._note([Rejection("clouds_rejected_malformed", f"malformed cloud rejected: {error}")])
        except FrameError as error:
            return self._note([Rejection("clouds_rejected_frame", f"cloud rejected: {error}")])
        except Exception as error:  # noqa: BLE001 - no cloud, however odd, may stop the node
            return self._note([Rejection("clouds_rejected_malformed", f"undecodable cloud rejected: {error!r}")])
        with self._lock:
            self.counters.nan_points_dropped += record.dropped_nonfinite
        if len(points) == 0:
            return self._note([Rejection("clouds_rejected_empty", f"cloud at {record.stamp_ns} ns has no finite "
                                         "points: rejected")])
        with self._lock:
            if self._scheduler is None:
                return
            notes = self._scheduler.add_cloud(record.stamp_ns, points, arrival_s)
        if not any(note.counter == "clouds_rejected_stamp" for note in notes):
            self._request_publisher.publish(header_msg(record.stamp_ns, self._frame, RCLPY_FACTORY))
        self._note(notes)
        self._wakeup.set()

    def _on_prediction(self, msg: TetraMesh) -> None:
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = positions_from_msg(msg, len(msg.positions) // 3)
        if positions is None:
            self._note([Rejection("predictions_rejected", f"predicted_mesh at {stamp_ns} ns is malformed or not "
                                  "finite: the step runs without it")])
        self._take_answer(Prediction(stamp_ns, positions, "" if positions is not None else "malformed or not finite"))

    def _on_failure(self, msg: PredictionFailure) -> None:
        with self._lock:
            self.counters.predictions_failed += 1
        self._take_answer(Prediction(stamp_ns_from_msg(msg.header.stamp), None, msg.reason))

    def _take_answer(self, answer: Prediction) -> None:
        with self._lock:
            self.counters.predictions_received += answer.positions is not None
            if self._scheduler is None:
                return
            rejection = self._scheduler.add_prediction(answer)
        self._note([rejection] if rejection else [])
        self._wakeup.set()

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        try:
            record = pose_from_msg(msg)
        except (MessageValidationError, ValueError):
            return  # the simulation node counts tool poses it cannot use
        with self._lock:
            if self._scheduler is not None and record.frame_id == self._frame:
                self._scheduler.add_tool_pose(record.stamp_ns, record.pose)
        self._wakeup.set()

    def _note(self, rejections: list[Rejection]) -> None:
        """Count and log what was set aside."""
        for rejection in rejections:
            with self._lock:
                setattr(self.counters, rejection.counter, getattr(self.counters, rejection.counter) + 1)
                self._last_rejection = rejection.reason
            self.get_logger().warning(rejection.reason, throttle_duration_sec=1.0)
        if rejections:
            self._wake_reports.trigger()

    # ------------------------------------------------------------------ solver thread
    def _solver_loop(self) -> None:
        while not self._stopping:
            self._wakeup.wait(_POLL_PERIOD_S)
            self._wakeup.clear()
            while not self._stopping:
                with self._lock:
                    step = None if self._scheduler is None else self._scheduler.next_step(time.monotonic())
                    scheduler = self._scheduler
                if step is None:
                    break
                start_s = time.monotonic()
                try:
                    outcome = scheduler.run(step, time.monotonic)
                except Exception as error:  # noqa: BLE001 - the solver thread must outlive any one failure
                    outcome = StepOutcome(step, None, repr(error), "failed_steps")
                if not self._stopping:
                    self._publish(outcome, start_s)

    def _publish(self, outcome: StepOutcome, start_s: float) -> None:
        step, result = outcome.step, outcome.result
        if result is None:
            self.get_logger().error(f"update at {step.stamp_ns} ns: {outcome.error}")
            with self._lock:
                setattr(self.counters, outcome.counter, getattr(self.counters, outcome.counter) + 1)
            self._wake_reports.trigger()
            return
        publish_start = time.monotonic()
        self._estimate_publisher.publish(self._messages.message(
            step.stamp_ns, self._frame, result.step, result.positions, result.position_std))
        self._status_publisher.publish(status_to_msg(status_record(result, self._frame), RCLPY_FACTORY))
        done = time.monotonic()
        with self._lock:
            counters = self.counters
            counters.steps += 1
            counters.degraded_steps += int(result.degraded)
            counters.unconverged_steps += int(not result.converged)
            counters.points_used += result.num_points
            counters.points_set_aside += result.num_points_rejected
            for counter in rejections_in(result.message):
                setattr(counters, counter, getattr(counters, counter) + 1)
            self._latencies.append(1e3 * (done - step.arrival_s))
            counters.last_wait_ms = 1e3 * (start_s - step.arrival_s)
            counters.last_solve_time_ms = float(result.solve_time_ms)
            counters.last_publish_ms = 1e3 * (done - publish_start)
            counters.last_latency_ms = self._latencies[-1]
            counters.median_latency_ms = float(np.median(self._latencies))
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
            waiting = self._scheduler is None
            since, last_rejection = self._unanswered_since_s, self._last_rejection
        unanswered_s = 0.0 if since is None else time.monotonic() - since
        level, message = self.health.assess(counters, waiting, unanswered_s, last_rejection)
        self._diagnostics_publisher.publish(diagnostic_array(f"{self.get_fully_qualified_name()}: estimation", level,
                                                             message, counters, self.get_clock().now().nanoseconds))
        if job is not None and self._markers_publisher.get_subscription_count() > 0:
            positions, position_std, points, stamp_ns = job
            self._markers_publisher.publish(mesh_markers(
                positions, self._mesh.state.surface_triangles, position_std, points, self._frame, stamp_ns,
                self.params["marker_std_max"], self._edges, RCLPY_FACTORY))


def main(args=None) -> int:
    """Console script `estimator_node` (accepts --ros-args)."""
    return run_nodes("estimator_node", [EstimatorNode], args=args)  # + its solver thread


if __name__ == "__main__":
    sys.exit(main())
