"""simulation_node: the physics prior, as a ROS 2 node.

Subscribes `tool_pose` (geometry_msgs/PoseStamped), `estimated_mesh` and `initial_mesh`
(meshfg_msgs/TetraMesh; or parameter mesh_file) and publishes `predicted_mesh` (TetraMesh
stamped with the tool pose's stamp), or `prediction_failed` (meshfg_msgs/PredictionFailure,
same stamp, with the reason) when the simulator cannot predict that pose, so that the estimator
runs that step without a prediction at once instead of waiting for one. The first tool pose only resets the simulator; each later
pose is predicted from the latest estimate (the initial mesh until one arrives) with
dt = the time between the two poses' stamps, as the offline replay does.

To reproduce the replay exactly, a pose waits for the estimate of the previous pose (at most
estimate_timeout seconds of wall time, then it predicts from the newest state it has). This
suits tool poses stamped like the clouds (the recordings); with tool poses faster than the
camera, set estimate_timeout to 0: each pose is then predicted from the newest estimate.
A tool-pose stamp that jumps back by more than clock_jump_threshold (a looped recording)
restarts from the initial mesh; smaller steps back, repeated and negative stamps are dropped, and
so are tool poses far outside the scene and estimates far outside it (the rules of
core/input_checks.py, which the offline replay follows too). Counters of all of it go to
/diagnostics every second (nodes/diagnostics.py). Predictions run in the executor's callbacks,
so Ctrl-C / SIGINT stops the node between two Python steps of a prediction.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from meshfg_msgs.msg import PredictionFailure, TetraMesh
from meshfg_ros.core.input_checks import INVALID, JUMP_BACK, STALE, Scene, check_initial_mesh, stamp_order
from meshfg_ros.parameters import load_mesh_file, simulator_config
from meshfg_ros.core.simulator import XpbdSimulator
from meshfg_ros.io.messages import (
    MeshState,
    MessageValidationError,
    mesh_state_from_msg,
    header_msg,
    pose_from_msg,
    stamp_ns_from_msg,
)
from meshfg_ros.nodes.diagnostics import SimulatorCounters, diagnostic_array
from meshfg_ros.nodes.ros_conversions import (
    RCLPY_FACTORY,
    MeshMessages,
    positions_from_msg,
    same_mesh,
    tet_mesh_from_state,
)
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
STREAM_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# Predictions and failure reports keep their last ten for a reader that matches late (DDS
# discovery can finish after the first tool pose is predicted): that step would otherwise wait
# out prediction_timeout and run degraded.
PREDICTION_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
_TIMEOUT_CHECK_PERIOD_S = 0.02
_DIAGNOSTICS_PERIOD_S = 1.0
_NS_PER_S = 1e9


@dataclass(frozen=True, eq=False)
class _PendingPose:
    stamp_ns: int
    pose: np.ndarray
    arrival_s: float  # time.monotonic() at reception


class SimulationNode(Node):
    """Simulator predictions of the mesh for each tool pose (see the module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("simulation_node", **kwargs)
        self.params = declare_parameters(self, "simulation_node")
        self._config = simulator_config(self.params)
        self._frame = self.params["world_frame"]
        self._jump_ns = int(self.params["clock_jump_threshold"] * _NS_PER_S)
        self._simulator: XpbdSimulator | None = None
        self._messages: MeshMessages | None = None
        self._initial: MeshState | None = None
        self._scene: Scene | None = None
        self.counters = SimulatorCounters()
        self._rejected_at_last_report = 0
        self._last_failure: str | None = None  # reason of the last prediction, if it failed
        self._pending: deque[_PendingPose] = deque()
        self._reset_timeline()

        self._publisher = self.create_publisher(TetraMesh, "predicted_mesh", PREDICTION_QOS)
        self._failure_publisher = self.create_publisher(PredictionFailure, "prediction_failed", PREDICTION_QOS)
        self._diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self.create_subscription(TetraMesh, "initial_mesh", self._on_initial_mesh, LATCHED_QOS)
        self.create_subscription(TetraMesh, "estimated_mesh", self._on_estimate, LATCHED_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, STREAM_QOS)
        # Wall-clock timer: the estimate timeout must not depend on /clock (use_sim_time).
        self.create_timer(_TIMEOUT_CHECK_PERIOD_S, self._process_poses, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.create_timer(_DIAGNOSTICS_PERIOD_S, self._publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        if self.params["mesh_file"]:
            self._load_mesh_file(self.params["mesh_file"])

    def _reset_timeline(self) -> None:
        """Forget tool poses and estimates: the next pose is a first pose again."""
        self._previous: _PendingPose | None = None
        self._previous_done_s = 0.0
        self._state: np.ndarray | None = None if self._initial is None else self._initial.positions.copy()
        self._state_stamp_ns: int | None = None
        self._timeline_start_ns: int | None = None
        self._newest_pose_ns: int | None = None
        self._pending.clear()
        self._step = 0

    def _load_mesh_file(self, path: str) -> None:
        mesh = load_mesh_file(path)  # ParameterError: the node stops at start-up
        self._set_initial(MeshState(0, self._frame, 0, mesh.vertices, mesh.tetrahedra,
                                    mesh.surface_triangles, mesh.fixed_vertices))

    def _on_initial_mesh(self, msg: TetraMesh) -> None:
        try:
            state = mesh_state_from_msg(msg)
        except MessageValidationError as error:
            self.get_logger().error(f"initial_mesh rejected: {error}")
            return
        if state.frame_id != self._frame:
            self.get_logger().error(f"initial_mesh in frame {state.frame_id!r}, expected {self._frame!r}: rejected")
            return
        if self._initial is not None and same_mesh(self._initial, state):
            return  # the latched message again (e.g. a reconnection)
        self._set_initial(state)

    def _set_initial(self, state: MeshState) -> None:
        grasped = np.asarray(self.params["grasped_vertices"], dtype=np.int64)
        try:
            scene = check_initial_mesh(state.positions)
            simulator = XpbdSimulator(tet_mesh_from_state(state), self._config, grasped if grasped.size else None)
        except ValueError as error:
            self.get_logger().error(f"cannot simulate the initial mesh: {error}")
            return
        restart = self._initial is not None
        self._initial, self._simulator, self._scene = state, simulator, scene
        self._messages = MeshMessages(state)
        if restart:
            self.get_logger().warning("new initial mesh: the simulation restarts from it")
            self._reset_timeline()
        self.get_logger().info(f"initial mesh: {state.positions.shape[0]} vertices, {len(state.tetrahedra)} tetrahedra")

    def _on_estimate(self, msg: TetraMesh) -> None:
        """Keep an estimate of this timeline's poses that is newer than the current state.

        Stamps outside [first pose, newest pose] belong to another timeline (an estimator that
        still works through a recording that has looped) and are ignored.
        """
        if self._state_stamp_ns is None:
            return  # no pose handled yet: the first prediction starts from the initial mesh
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        if not max(self._timeline_start_ns, self._state_stamp_ns) <= stamp_ns <= self._newest_pose_ns:
            return
        positions = positions_from_msg(msg, self._initial.positions.shape[0])
        if positions is None or self._scene.far(positions).any():
            self.counters.estimates_ignored += 1
            self.get_logger().warning("estimated_mesh ignored: wrong vertex count, non-finite positions or positions "
                                      "far outside the scene", throttle_duration_sec=1.0)
            return
        self._state, self._state_stamp_ns = positions, stamp_ns
        self._process_poses()

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        self.counters.tool_poses_received += 1
        try:
            record = pose_from_msg(msg)
        except MessageValidationError as error:
            self.counters.tool_poses_rejected_malformed += 1
            self.get_logger().warning(f"tool_pose rejected: {error}")
            return
        if record.frame_id != self._frame:
            self.counters.tool_poses_rejected_frame += 1
            self.get_logger().warning(f"tool_pose in frame {record.frame_id!r}, expected {self._frame!r}: rejected")
            return
        order = stamp_order(self._newest_pose_ns, record.stamp_ns, self._jump_ns)
        if order in (STALE, INVALID):
            self.counters.tool_poses_rejected_stamp += 1
            reason = "is negative" if order == INVALID else f"is not newer than {self._newest_pose_ns} ns"
            self.get_logger().warning(f"tool_pose stamp {record.stamp_ns} ns {reason}: dropped")
            return
        if self._scene is not None and self._scene.far(record.pose[None, :3])[0]:
            self.counters.tool_poses_rejected_far += 1
            where = self._scene.describe(record.pose[None, :3])
            self.get_logger().warning(f"tool_pose at {record.stamp_ns} ns is {where}: dropped")
            return
        if order == JUMP_BACK:
            self.counters.clock_jumps_back += 1
            self.get_logger().warning("tool_pose stamp jumped back: restarting from the initial mesh")
            self._reset_timeline()
        if self._timeline_start_ns is None:
            self._timeline_start_ns = record.stamp_ns
        self._newest_pose_ns = record.stamp_ns
        self._pending.append(_PendingPose(record.stamp_ns, record.pose, time.monotonic()))
        self._process_poses()

    def _process_poses(self) -> None:
        """Handle queued poses in order, each once its previous estimate is in (or timed out)."""
        if self._simulator is None:
            return
        while self._pending:
            pose = self._pending[0]
            if self._previous is None:
                self._simulator.reset(pose.pose)
                self._state, self._state_stamp_ns = self._initial.positions.copy(), pose.stamp_ns
                self._finish(pose)
                continue
            missing = self._state_stamp_ns < self._previous.stamp_ns
            timeout_s = self.params["estimate_timeout"]
            if missing and time.monotonic() - max(pose.arrival_s, self._previous_done_s) < timeout_s:
                return
            if missing and timeout_s > 0.0:
                self.get_logger().warning(f"no estimate for {self._previous.stamp_ns} ns: predicting from the state "
                                          f"of {self._state_stamp_ns} ns", throttle_duration_sec=1.0)
            self._predict(pose)
            self._finish(pose)

    def _predict(self, pose: _PendingPose) -> None:
        dt = (pose.stamp_ns - self._previous.stamp_ns) / _NS_PER_S
        try:
            predicted = self._simulator.predict(self._state, pose.pose, dt)
        except (ValueError, RuntimeError) as error:
            self._fail(pose, str(error))
            return
        if not np.isfinite(predicted).all():
            self._fail(pose, "the predicted positions are not finite")
            return
        self.counters.predictions += 1
        self._last_failure = None
        self._publisher.publish(self._messages.message(pose.stamp_ns, self._frame, self._step, predicted))

    def _fail(self, pose: _PendingPose, reason: str) -> None:
        """Restart the simulator at this pose and say so on prediction_failed."""
        self._simulator.reset(pose.pose)
        self.counters.predictions_failed += 1
        self._last_failure = reason
        self.get_logger().error(f"prediction for {pose.stamp_ns} ns failed: {reason}")
        self._failure_publisher.publish(
            PredictionFailure(header=header_msg(pose.stamp_ns, self._frame, RCLPY_FACTORY), reason=reason))

    def _publish_diagnostics(self) -> None:
        """The counters, with OK / WARN: waiting for the mesh, rejected tool poses, a failed prediction."""
        counters = self.counters
        new_rejections = counters.tool_poses_rejected - self._rejected_at_last_report
        self._rejected_at_last_report = counters.tool_poses_rejected
        level, message = DiagnosticStatus.OK, "predicting"
        if self._simulator is None:
            level, message = DiagnosticStatus.WARN, "waiting for initial_mesh"
        elif new_rejections:
            level, message = DiagnosticStatus.WARN, f"{new_rejections} tool poses rejected since the last report"
        elif self._last_failure is not None:
            level, message = DiagnosticStatus.WARN, f"the last prediction failed: {self._last_failure}"
        self._diagnostics_publisher.publish(diagnostic_array(
            f"{self.get_fully_qualified_name()}: simulation", level, message, counters,
            self.get_clock().now().nanoseconds))

    def _finish(self, pose: _PendingPose) -> None:
        self._pending.popleft()
        self._previous = pose
        self._previous_done_s = time.monotonic()
        self._step += 1


def main(args=None) -> int:
    """Console script `simulation_node` (accepts --ros-args)."""
    return run_nodes("simulation_node", [SimulationNode], args=args)


if __name__ == "__main__":
    sys.exit(main())
