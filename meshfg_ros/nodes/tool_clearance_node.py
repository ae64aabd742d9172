"""tool_clearance_node: an example planner that keeps a tool tip away from the uncertain tissue.

Subscribes `desired_tip_pose` (geometry_msgs/PoseStamped, any frame /tf knows), asks the
estimator node's `surface_query` service (meshfg_msgs/SurfaceQuery) where the tip is with
respect to the newest estimated surface, and publishes `safe_tip_pose` (PoseStamped, the desired
pose's frame, stamp and orientation): the desired position where it keeps at least
max(min_clearance, clearance_sigmas x the distance's std) from the surface, else the position
moved out along the surface normal to that distance (meshfg_ros.planner_client.clearance_positions).

A desired pose that cannot be checked (no estimate yet, the service down, a frame /tf cannot
place) is held back, not passed on unchecked: nothing is published for it, the reason is logged,
counted and shown on /diagnostics. A desired pose that comes while the previous one's query is
still out replaces it (the older answer would be stale). As the pipeline's nodes do, its
diagnostics put its wiring first: a desired_tip_pose publisher whose QoS cannot match (ERROR,
with the fix), then a parameters file that sets nothing (WARN).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point, Pose, PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from meshfg_ros.io.messages import stamp_ns_from_msg
from meshfg_ros.nodes.diagnostics import Counters, diagnostic_array, with_setup_problems
from meshfg_ros.nodes.planner_service import SURFACE_QUERY_SERVICE
from meshfg_ros.nodes.publisher_qos import TOPIC_TABLE_FIX, IncompatiblePublishers
from meshfg_ros.nodes.ros_conversions import STREAM_QOS
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.planner_client import SurfaceQueryClient, SurfaceQueryError, clearance_positions

_REPORT_PERIOD_S = 1.0


@dataclass
class ClearanceCounters(Counters):
    """What the node has done since it started (the values of its diagnostics)."""

    desired_poses_received: int = 0
    safe_poses_published: int = 0
    poses_moved_out: int = 0        # published at the clearance instead of where desired
    poses_held_back: int = 0        # not checked (refused query, service down): nothing published
    poses_superseded: int = 0       # a newer desired pose came before the answer


class ToolClearanceNode(Node):
    """Desired tool tip in, safe tool tip out (module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("tool_clearance_node", **kwargs)
        # Both parameters are dynamic: a set updates self.params, read at each answer; nothing else to redo.
        self.params = declare_parameters(self, "tool_clearance_node", on_change=lambda changes: None)
        self.counters = ClearanceCounters()
        self.setup_warnings: list[str] = []  # what run_nodes found wrong in the set-up (a parameters file)
        self._held_back_since_report = 0
        self._last_hold_back = ""
        self._pending = None  # (future, desired pose) of the query out
        self._surface = SurfaceQueryClient(self, SURFACE_QUERY_SERVICE)
        self._safe = self.create_publisher(PoseStamped, "safe_tip_pose", STREAM_QOS)
        self._diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self.create_subscription(PoseStamped, "desired_tip_pose", self._on_desired, STREAM_QOS)
        self._input_qos = IncompatiblePublishers(self)
        self._input_qos.watch("desired_tip_pose", STREAM_QOS, TOPIC_TABLE_FIX)
        self.create_timer(_REPORT_PERIOD_S, self._report, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _on_desired(self, msg: PoseStamped) -> None:
        self.counters.desired_poses_received += 1
        if self._pending is not None:
            self._surface.client.remove_pending_request(self._pending[0])
            self.counters.poses_superseded += 1
            self._pending = None
        if not self._surface.client.service_is_ready():
            return self._hold_back(f"service {self._surface.client.srv_name} is not available: is the estimator "
                                   "node running in this namespace?")
        position = msg.pose.position
        future = self._surface.query_async([[position.x, position.y, position.z]], msg.header.frame_id,
                                           stamp_ns_from_msg(msg.header.stamp))
        self._pending = (future, msg)
        future.add_done_callback(self._on_answer)

    def _on_answer(self, future) -> None:
        if self._pending is None or self._pending[0] is not future:
            return  # superseded
        _, desired = self._pending
        self._pending = None
        try:
            answer = self._surface.answer_from_response(future.result())
        except SurfaceQueryError as error:
            return self._hold_back(str(error))
        position = desired.pose.position
        wanted = np.array([[position.x, position.y, position.z]])
        safe = clearance_positions(wanted, answer, self.params["clearance_sigmas"], self.params["min_clearance"])[0]
        if not np.array_equal(safe, wanted[0]):
            self.counters.poses_moved_out += 1
        x, y, z = safe.tolist()
        self._safe.publish(PoseStamped(header=desired.header, pose=Pose(
            position=Point(x=x, y=y, z=z), orientation=desired.pose.orientation)))
        self.counters.safe_poses_published += 1

    def _hold_back(self, reason: str) -> None:
        self.counters.poses_held_back += 1
        self._held_back_since_report += 1
        self._last_hold_back = reason
        self.get_logger().warning(f"desired tip pose held back: {reason}", throttle_duration_sec=1.0)

    def _report(self) -> None:
        held_back, self._held_back_since_report = self._held_back_since_report, 0
        if held_back:
            level, message = DiagnosticStatus.WARN, (f"{held_back} desired tip poses held back since the last report "
                                                     f"(not checked, not published); the last: {self._last_hold_back}")
        elif not self.counters.desired_poses_received:
            level, message = DiagnosticStatus.OK, "waiting for desired_tip_pose"
        else:
            level, message = DiagnosticStatus.OK, "keeping the tool tip clear of the tissue"
        level, message = with_setup_problems(level, message, self._input_qos.find(), self.setup_warnings)
        self._diagnostics.publish(diagnostic_array(f"{self.get_fully_qualified_name()}: tool clearance", level,
                                                   message, self.counters, self.get_clock().now().nanoseconds))


def main(args=None) -> int:
    """Console script `tool_clearance_node` (accepts --ros-args)."""
    return run_nodes("tool_clearance_node", [ToolClearanceNode], args=args)


if __name__ == "__main__":
    sys.exit(main())
