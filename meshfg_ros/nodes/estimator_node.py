"""estimator_node: the sliding-window factor-graph estimator, as a ROS 2 node.

Subscribes `points` (sensor_msgs/PointCloud2, sensor-data QoS), `predicted_mesh` and
`initial_mesh` (meshfg_msgs/TetraMesh; or parameter mesh_file), `prediction_failed`
(meshfg_msgs/PredictionFailure) and `tool_pose` (geometry_msgs/PoseStamped: points on the tool
sphere are segmentation leaks). Each cloud at stamp t is paired with the prediction and the tool
pose stamped t;
without one after prediction_timeout seconds of wall time (counted from when the solver is
free for that cloud), once a prediction for a later cloud has arrived, or at once when the
simulator reports that it failed for t, the step runs degraded without it. Publishes
`estimated_mesh` (TetraMesh with position_std; reliable, transient-local, depth 1: a
late-joining planner gets the latest state), `status` (meshfg_msgs/EstimatorStatus), `markers` (visualization_msgs/MarkerArray,
built only while someone subscribes) and `/diagnostics` (counters, see diagnostics.py).

Robustness: malformed, empty and wrong-frame clouds are rejected and counted, NaN points are
dropped and counted, repeated, out-of-order and negative stamps are dropped and counted, a stamp
that jumps back by more than clock_jump_threshold (a looped recording) restarts the estimator
from the initial mesh (the stamp rule of core/input_checks.py, which the offline replay follows
too), and nothing non-finite is ever published. Points, predictions and tool poses far outside
the scene, and predictions the cloud contradicts, are set aside by the estimator and counted
from its status message. Clouds and predictions are taken in by one thread and solved in
another, so a long solve does not make DDS drop input; an update stops after
update_time_budget, and on shutdown the node waits at most _STOP_WAIT_S for a running one.
Diagnostics are an ERROR when clouds keep arriving and none has been answered with an estimate
for _stalled_after_s (the prediction timeout and two time budgets, plus a margin).
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from meshfg_msgs.msg import EstimatorStatus, PredictionFailure, TetraMesh
from meshfg_ros import blas
from meshfg_ros.core.estimator import SlidingWindowEstimator, StepResult
from meshfg_ros.core.input_checks import INVALID, JUMP_BACK, STALE, check_initial_mesh, rejections_in, stamp_order
from meshfg_ros.core.mesh import TetMesh
from meshfg_ros.parameters import FrameError, cloud_to_world, estimator_changes, estimator_config, load_mesh_file
from meshfg_ros.io.messages import (
    MeshState,
    MessageValidationError,
    mesh_state_from_msg,
    pose_from_msg,
    stamp_ns_from_msg,
    status_to_msg,
)
from meshfg_ros.io.pointcloud import PointCloudError, cloud_record_from_msg
from meshfg_ros.markers import mesh_markers, surface_edges
from meshfg_ros.nodes.diagnostics import EstimatorCounters, diagnostic_array
from meshfg_ros.nodes.ros_conversions import (
    RCLPY_FACTORY,
    MeshMessages,
    same_mesh,
    tet_mesh_from_state,
)
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.replay import status_record

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
STREAM_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# Predictions and failure reports keep their last ten for a reader that matches late (DDS
# discovery can finish after the first tool pose is predicted): that step would otherwise wait
# out prediction_timeout and run degraded.
PREDICTION_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
RELIABLE_POINTS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
MAX_QUEUED_CLOUDS = 100
MAX_STORED_PREDICTIONS = 100
_TIMEOUT_CHECK_PERIOD_S = 0.02
_DIAGNOSTICS_PERIOD_S = 1.0
_LATENCY_HISTORY = 100
_WARN_THROTTLE_S = 1.0
_NS_PER_S = 1e9
# Shutdown waits this long for a running update, then leaves the (daemon) solver thread behind.
_STOP_WAIT_S = 2.0
# Beyond a cloud's wait for its prediction and two time budgets (an update, and the iteration and
# covariance it may be in when the budget runs out): no estimate by then means a stuck solver.
_STALL_MARGIN_S = 1.0


@dataclass(frozen=True, eq=False)
class _Cloud:
    stamp_ns: int
    points: np.ndarray  # (K, 3) world frame
    arrival_s: float  # time.monotonic() at reception


_RESTART = "restart"  # queue entry: a stamp jumped back, restart from the initial mesh


class EstimatorNode(Node):
    """Estimated mesh per point cloud (see the module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("estimator_node", **kwargs)
        self.params = declare_parameters(self, "estimator_node", on_change=self._reconfigure)
        self._config = estimator_config(self.params)
        self._frame = self.params["world_frame"]
        self._jump_ns = int(self.params["clock_jump_threshold"] * _NS_PER_S)
        self.counters = EstimatorCounters()
        # Shared by the input thread and the solver thread (guarded by _lock).
        self._lock = threading.Lock()
        self._queue: deque[_Cloud | str] = deque()
        self._predictions: dict[int, np.ndarray] = {}
        self._tool_poses: dict[int, np.ndarray] = {}
        self._failed_predictions: set[int] = set()  # stamps the simulator reported it cannot predict
        self._newest_cloud_ns: int | None = None
        self._newest_prediction_ns: int | None = None
        self._last_step_ns: int | None = None
        self._received_initial: MeshState | None = None
        self._solver_free_s = time.monotonic()
        self._latencies: deque[float] = deque(maxlen=_LATENCY_HISTORY)
        self._markers_job: tuple | None = None
        self._last_result: StepResult | None = None
        self._rejected_at_last_report = 0
        self._failed_at_last_report = 0
        self._unanswered_since_s: float | None = None  # arrival of the first cloud after the last estimate
        budget = self._config.update_time_budget
        self._stalled_after_s = (self.params["prediction_timeout"] + 2.0 * (budget if budget is not None else 0.0)
                                 + _STALL_MARGIN_S)
        # Solver thread only.
        self._initial: MeshState | None = None
        self._initial_mesh: TetMesh | None = None
        self._estimator: SlidingWindowEstimator | None = None
        self._messages: MeshMessages | None = None
        self._edges: np.ndarray | None = None

        steady = Clock(clock_type=ClockType.STEADY_TIME)  # diagnostics on wall time, also with use_sim_time
        self._estimate_publisher = self.create_publisher(TetraMesh, "estimated_mesh", LATCHED_QOS)
        self._status_publisher = self.create_publisher(EstimatorStatus, "status", STREAM_QOS)
        self._markers_publisher = self.create_publisher(MarkerArray, "markers", STREAM_QOS)
        self._diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self.create_subscription(TetraMesh, "initial_mesh", self._on_initial_mesh, LATCHED_QOS)
        self.create_subscription(TetraMesh, "predicted_mesh", self._on_prediction, PREDICTION_QOS)
        self.create_subscription(PredictionFailure, "prediction_failed", self._on_prediction_failure,
                                 PREDICTION_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, STREAM_QOS)
        points_qos = RELIABLE_POINTS_QOS if self.params["points_reliable"] else qos_profile_sensor_data
        self.create_subscription(PointCloud2, "points", self._on_cloud, points_qos)
        # The solver runs in its own thread and the executor is single-threaded (main below):
        # under rclpy's MultiThreadedExecutor each message (/clock at 100 Hz with use_sim_time)
        # cost 3x the CPU, and its executor thread, contending for the GIL, made solves in the
        # live pipeline take 2-15x their offline time (cloud-to-estimate median 1.2-2.6 s on
        # the bundled airway recording, against 0.2 s with this design).
        self._solver_wakeup = threading.Event()
        self._stopping = False
        self._solver_thread = threading.Thread(target=self._solver_loop, name="meshfg-solver", daemon=True)
        self._wake_outputs = self.create_guard_condition(self._publish_reports)
        self.create_timer(_DIAGNOSTICS_PERIOD_S, self._publish_reports, clock=steady)
        if self.params["mesh_file"]:
            self._load_mesh_file(self.params["mesh_file"])
        self._solver_thread.start()

    def destroy_node(self) -> None:
        """Stop the solver thread (a running update has _STOP_WAIT_S to finish; it is left behind,
        and publishes nothing, if it takes longer), then destroy the node."""
        self._stopping = True
        self._solver_wakeup.set()
        self._solver_thread.join(_STOP_WAIT_S)
        if self._solver_thread.is_alive():
            self.get_logger().warning(f"an update still runs after {_STOP_WAIT_S:g} s: left behind at shutdown")
        super().destroy_node()

    def _reconfigure(self, changes: dict) -> None:
        """Dynamic parameters set while running: the estimator uses them from its next update on."""
        self._config = estimator_config(self.params)
        if self._estimator is not None:
            self._estimator.reconfigure(**estimator_changes(changes))

    # ------------------------------------------------------------------ input thread
    def _load_mesh_file(self, path: str) -> None:
        mesh = load_mesh_file(path)  # ParameterError: the node stops at start-up
        self._received_initial = MeshState(0, self._frame, 0, mesh.vertices, mesh.tetrahedra,
                                           mesh.surface_triangles, mesh.fixed_vertices)

    def _on_initial_mesh(self, msg: TetraMesh) -> None:
        try:
            state = mesh_state_from_msg(msg)
        except MessageValidationError as error:
            self.get_logger().error(f"initial_mesh rejected: {error}")
            return
        if state.frame_id != self._frame:
            self.get_logger().error(f"initial_mesh in frame {state.frame_id!r}, expected {self._frame!r}: rejected")
            return
        with self._lock:
            self._received_initial = state
        self._solver_wakeup.set()

    def _on_prediction(self, msg: TetraMesh) -> None:
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = np.asarray(msg.positions, dtype=np.float64)
        with self._lock:
            self.counters.predictions_received += 1
            if positions.size % 3 or not np.isfinite(positions).all():
                self.counters.predictions_rejected += 1
                self.get_logger().warning(f"predicted_mesh at {stamp_ns} ns is malformed or not finite: ignored")
                return
            if not self._wanted_simulator_stamp(stamp_ns):
                self.counters.predictions_rejected += 1  # its cloud has been processed already
                return
            self._predictions[stamp_ns] = positions.reshape(-1, 3)
            while len(self._predictions) > MAX_STORED_PREDICTIONS:
                del self._predictions[min(self._predictions)]
        self._solver_wakeup.set()

    def _on_prediction_failure(self, msg: PredictionFailure) -> None:
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        with self._lock:
            self.counters.predictions_failed += 1
            if not self._wanted_simulator_stamp(stamp_ns):
                return  # its cloud has been processed already
            self._failed_predictions.add(stamp_ns)
            while len(self._failed_predictions) > MAX_STORED_PREDICTIONS:
                self._failed_predictions.remove(min(self._failed_predictions))
        self.get_logger().warning(f"simulator failed for {stamp_ns} ns ({msg.reason}): that step runs without "
                                  "a prediction", throttle_duration_sec=_WARN_THROTTLE_S)
        self._solver_wakeup.set()

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        try:
            record = pose_from_msg(msg)
        except (MessageValidationError, ValueError) as error:
            self.get_logger().warning(f"tool_pose rejected: {error}", throttle_duration_sec=_WARN_THROTTLE_S)
            return
        if record.frame_id != self._frame or not np.isfinite(record.pose).all():
            return  # the simulation node reports tool poses it cannot use
        with self._lock:
            self._tool_poses[record.stamp_ns] = record.pose
            while len(self._tool_poses) > MAX_STORED_PREDICTIONS:
                del self._tool_poses[min(self._tool_poses)]
        self._solver_wakeup.set()

    def _wanted_simulator_stamp(self, stamp_ns: int) -> bool:
        """Under the lock: whether the simulator's outcome (a prediction or a failure) for stamp_ns
        can still serve a cloud. A stamp far older than the newest one means the simulator
        restarted (a looped recording): the outcomes kept for the old timeline are dropped."""
        newest = self._newest_prediction_ns
        if newest is not None and newest - stamp_ns > self._jump_ns:
            self._predictions.clear()
            self._failed_predictions.clear()
        elif self._last_step_ns is not None and 0 <= self._last_step_ns - stamp_ns <= self._jump_ns:
            return False
        self._newest_prediction_ns = stamp_ns
        return True

    def _on_cloud(self, msg: PointCloud2) -> None:
        arrival_s = time.monotonic()
        with self._lock:
            self.counters.clouds_received += 1
        try:
            record = cloud_record_from_msg(msg)
        except (PointCloudError, MessageValidationError) as error:
            self._count_rejection("clouds_rejected_malformed")
            self.get_logger().warning(f"malformed cloud rejected: {error}", throttle_duration_sec=_WARN_THROTTLE_S)
            return
        except Exception as error:  # noqa: BLE001 - no cloud, however odd, may stop the node
            self._count_rejection("clouds_rejected_malformed")
            self.get_logger().warning(f"undecodable cloud rejected: {error!r}", throttle_duration_sec=_WARN_THROTTLE_S)
            return
        with self._lock:
            self.counters.nan_points_dropped += record.dropped_nonfinite
        if record.points.shape[0] == 0:
            self._count_rejection("clouds_rejected_empty")
            self.get_logger().warning(f"cloud at {record.stamp_ns} ns has no finite points: rejected",
                                      throttle_duration_sec=_WARN_THROTTLE_S)
            return
        try:
            points = cloud_to_world(record.points, record.frame_id, self.params)
        except FrameError as error:
            self._count_rejection("clouds_rejected_frame")
            self.get_logger().warning(f"cloud rejected: {error}", throttle_duration_sec=_WARN_THROTTLE_S)
            return
        self._enqueue(record.stamp_ns, points, arrival_s)

    def _enqueue(self, stamp_ns: int, points: np.ndarray, arrival_s: float) -> None:
        """Queue a valid cloud for the solver. A repeated or slightly older stamp is dropped; one older
        by more than clock_jump_threshold first queues a restart from the initial mesh."""
        with self._lock:
            newest = self._newest_cloud_ns
        order = stamp_order(newest, stamp_ns, self._jump_ns)
        if order in (STALE, INVALID):
            self._count_rejection("clouds_rejected_stamp")
            reason = "is negative" if order == INVALID else f"is not newer than {newest} ns"
            self.get_logger().warning(f"cloud stamp {stamp_ns} ns {reason}: dropped",
                                      throttle_duration_sec=_WARN_THROTTLE_S)
            return
        with self._lock:
            if self._unanswered_since_s is None:
                self._unanswered_since_s = arrival_s
            if order == JUMP_BACK:
                self.counters.clock_jumps_back += 1
                self.get_logger().warning(f"cloud stamp jumped back by {(newest - stamp_ns) / _NS_PER_S:.3f} s: "
                                          "restarting from the initial mesh")
                self._queue.append(_RESTART)
            self._newest_cloud_ns = stamp_ns
            self._queue.append(_Cloud(stamp_ns, points, arrival_s))
            if sum(isinstance(entry, _Cloud) for entry in self._queue) > MAX_QUEUED_CLOUDS:
                oldest = next(i for i, entry in enumerate(self._queue) if isinstance(entry, _Cloud))
                del self._queue[oldest]
                self.counters.clouds_dropped_backlog += 1
        self._solver_wakeup.set()

    def _count_rejection(self, counter: str) -> None:
        """Count a rejected cloud and report it in the diagnostics (the caller logs why)."""
        with self._lock:
            setattr(self.counters, counter, getattr(self.counters, counter) + 1)
        self._wake_outputs.trigger()

    # ------------------------------------------------------------------ solver thread
    def _solver_loop(self) -> None:
        """Solve when woken by new input, and every _TIMEOUT_CHECK_PERIOD_S for the prediction timeout."""
        while not self._stopping:
            self._solver_wakeup.wait(_TIMEOUT_CHECK_PERIOD_S)
            self._solver_wakeup.clear()
            if self._stopping:
                return
            try:
                self._solve()
            except Exception as error:  # noqa: BLE001 - the solver thread must outlive any one failure
                self.get_logger().error(f"solver thread: {error!r}")

    def _solve(self) -> None:
        """Run every step that is ready, in stamp order."""
        self._install_initial_mesh()
        while True:
            job = self._next_job()
            if job is None:
                return
            if job is _RESTART:
                self._restart()
            else:
                self._step(*job)

    def _install_initial_mesh(self) -> None:
        with self._lock:
            state, self._received_initial = self._received_initial, None
        if state is None or (self._initial is not None and same_mesh(self._initial, state)):
            return
        try:
            check_initial_mesh(state.positions)
            mesh = tet_mesh_from_state(state)
            estimator = SlidingWindowEstimator(mesh, self._config)
        except (ValueError, RuntimeError) as error:
            self.get_logger().error(f"cannot estimate on the initial mesh: {error}")
            return
        if self._initial is not None:
            self.get_logger().warning("new initial mesh: the estimator restarts from it")
        self._initial, self._initial_mesh, self._estimator = state, mesh, estimator
        self._messages = MeshMessages(state)
        self._edges = surface_edges(state.surface_triangles)
        with self._lock:
            self._solver_free_s = time.monotonic()
        self.get_logger().info(f"initial mesh: {mesh.vertex_count} vertices, {mesh.tetrahedron_count} tetrahedra; "
                               f"sparse Cholesky BLAS: {blas.backend().name}, {blas.backend().threads} thread(s)")

    def _next_job(self):
        """The next ready queue entry: _RESTART, or (cloud, its prediction or None, its tool pose
        or None); None to wait."""
        with self._lock:
            if self._estimator is None or not self._queue:
                return None
            head = self._queue[0]
            if head is _RESTART:
                return self._queue.popleft()
            predicted = self._predictions.get(head.stamp_ns)
            tool_pose = self._tool_poses.get(head.stamp_ns)
            waited = time.monotonic() - max(head.arrival_s, self._solver_free_s)
            if predicted is None and head.stamp_ns not in self._failed_predictions:
                newer = any(head.stamp_ns < stamp <= self._newest_cloud_ns for stamp in self._predictions)
                if not newer and waited < self.params["prediction_timeout"]:
                    return None
            released = predicted is not None or head.stamp_ns in self._failed_predictions
            if tool_pose is None and not released and waited < self.params["prediction_timeout"]:
                return None
            self._queue.popleft()
            for stamp in [stamp for stamp in self._predictions if stamp <= head.stamp_ns]:
                del self._predictions[stamp]
            for stamp in [stamp for stamp in self._tool_poses if stamp <= head.stamp_ns]:
                del self._tool_poses[stamp]
            self._failed_predictions = {stamp for stamp in self._failed_predictions if stamp > head.stamp_ns}
            self._last_step_ns = head.stamp_ns
        if predicted is not None and predicted.shape != self._initial.positions.shape:
            self.get_logger().warning(f"prediction at {head.stamp_ns} ns has {predicted.shape[0]} vertices, "
                                      f"the mesh {self._initial.positions.shape[0]}: ignored")
            with self._lock:
                self.counters.predictions_rejected += 1
            predicted = None
        return head, predicted, tool_pose

    def _restart(self) -> None:
        self._estimator = SlidingWindowEstimator(self._initial_mesh, self._config)

    def _step(self, cloud: _Cloud, predicted: np.ndarray | None, tool_pose: np.ndarray | None) -> None:
        try:
            result = self._estimator.update(cloud.stamp_ns, cloud.points, predicted, tool_pose)
        except Exception as error:  # noqa: BLE001 - one failed step must not stop the node
            if self._stopping:
                return  # shut down while it ran: the node may be gone already
            self.get_logger().error(f"estimator update at {cloud.stamp_ns} ns failed: {error!r}")
            with self._lock:
                self.counters.failed_steps += 1
                self._solver_free_s = time.monotonic()
            self._wake_outputs.trigger()
            return
        if self._stopping:
            return
        if not _finite(result):
            self.get_logger().error(f"estimate at {cloud.stamp_ns} ns is not finite: not published; "
                                    "the estimator restarts from the initial mesh")
            self._restart()
            with self._lock:
                self.counters.nonfinite_estimates += 1
                self._solver_free_s = time.monotonic()
            self._wake_outputs.trigger()
            return
        self._estimate_publisher.publish(self._messages.message(
            cloud.stamp_ns, self._frame, result.step, result.positions, result.position_std))
        latency_ms = (time.monotonic() - cloud.arrival_s) * 1e3
        self._status_publisher.publish(status_to_msg(status_record(result, self._frame), RCLPY_FACTORY))
        with self._lock:
            self.counters.steps += 1
            self.counters.degraded_steps += int(result.degraded)
            for counter in rejections_in(result.message):
                setattr(self.counters, counter, getattr(self.counters, counter) + 1)
            self._unanswered_since_s = None
            self.counters.last_solve_time_ms = float(result.solve_time_ms)
            self.counters.last_latency_ms = latency_ms
            self._latencies.append(latency_ms)
            self.counters.median_latency_ms = float(np.median(self._latencies))
            self._last_result = result
            self._markers_job = (result.positions, result.position_std, cloud.points, cloud.stamp_ns)
            self._solver_free_s = time.monotonic()
        self._wake_outputs.trigger()

    # ------------------------------------------------------------------ output thread
    def _publish_reports(self) -> None:
        """Diagnostics (after each step and periodically) and markers of the newest estimate."""
        with self._lock:
            counters = replace(self.counters)
            job, self._markers_job = self._markers_job, None
            last = self._last_result
            waiting = self._estimator is None
            unanswered_since_s = self._unanswered_since_s
        level, message = DiagnosticStatus.OK, "estimating"
        new_rejections = counters.clouds_rejected - self._rejected_at_last_report
        self._rejected_at_last_report = counters.clouds_rejected
        new_failures = counters.failed_steps - self._failed_at_last_report
        self._failed_at_last_report = counters.failed_steps
        unanswered_s = 0.0 if unanswered_since_s is None else time.monotonic() - unanswered_since_s
        if waiting:
            level, message = DiagnosticStatus.WARN, "waiting for initial_mesh"
        elif unanswered_s > self._stalled_after_s:
            level, message = DiagnosticStatus.ERROR, (f"no estimate for the clouds of the last {unanswered_s:.0f} s: "
                                                      "the solver is stuck or every update fails")
        elif new_failures:
            level, message = DiagnosticStatus.WARN, f"{new_failures} updates failed since the last report"
        elif last is not None and last.degraded:
            level, message = DiagnosticStatus.WARN, "degraded: the last step had no simulator prediction"
        elif new_rejections:
            level, message = DiagnosticStatus.WARN, f"{new_rejections} clouds rejected since the last report"
        name = f"{self.get_fully_qualified_name()}: estimation"
        self._diagnostics_publisher.publish(
            diagnostic_array(name, level, message, counters, self.get_clock().now().nanoseconds))
        if job is not None and self._markers_publisher.get_subscription_count() > 0:
            positions, position_std, points, stamp_ns = job
            self._markers_publisher.publish(mesh_markers(
                positions, self._initial.surface_triangles, position_std, points, self._frame, stamp_ns,
                self.params["marker_std_max"], self._edges, RCLPY_FACTORY))


def _finite(result: StepResult) -> bool:
    values = [result.positions, result.position_std, result.initial_cost, result.final_cost, result.solve_time_ms]
    return all(np.isfinite(np.asarray(value, dtype=np.float64)).all() for value in values)




def main(args=None) -> int:
    """Console script `estimator_node` (accepts --ros-args)."""
    return run_nodes("estimator_node", [EstimatorNode], args=args)  # + its solver thread


if __name__ == "__main__":
    sys.exit(main())
