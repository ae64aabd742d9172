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
at once without one. After a stalled tool stream it also publishes, before the next prediction,
the catch-up predictions of the stamps it answered without a tool pose; the estimator runs those
clouds again with them and sends the estimates on `catch_up_estimate` (TetraMesh), which this
node learns from (core/scheduler.py). A predicted_mesh is on the simulator's topology: after a cut its tetrahedra
and surface are the remaining ones and it lists removed_elements and invalid_vertices, which the
estimator follows. After each estimate it takes it publishes `body_acceleration`
(geometry_msgs/Vector3Stamped at the estimate's stamp, m/s^2): the unmodelled body load learnt so
far (core/physics/body_load.py; not published with estimate_body_load off). The Poisson ratio the
predictions use (core/physics/poisson_ratio.py) is in the diagnostics. The waits and the stamp rule
are the scheduler's; what the node publishes, its counters and its health are
nodes/simulation_outputs.py's.
Tool poses, requests and estimates that arrive before the mesh are held until it comes
(nodes/held_inputs.py).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header, UInt32MultiArray

from meshfg_msgs.msg import TetraMesh
from meshfg_ros.core.scheduler import MAX_QUEUED_CLOUDS, PredictionScheduler, Rejection, SchedulingTimeouts
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError
from meshfg_ros.core.geometry.mesh import InvalidMeshError
from meshfg_ros.core.physics.simulator import SimulatorInputError
from meshfg_ros.core.inputs.tool_poses import DEFAULT_MAX_SAMPLES
from meshfg_ros.core.geometry.topology import cut_elements
from meshfg_ros.core.inputs.world_frame import POSE, FramedInput, Unplaceable
from meshfg_ros.io.messages import MeshState, MessageValidationError, pose_from_msg, stamp_ns_from_msg
from meshfg_ros.nodes.frame_inputs import TF_QOS, TF_STATIC_QOS, FrameInputs
from meshfg_ros.nodes.held_inputs import HeldUntilMesh
from meshfg_ros.nodes.ros_conversions import (
    LATCHED_QOS,
    REQUEST_QOS,
    TOOL_POSE_QOS_FIX,
    InitialMeshSource,
    position_std_from_msg,
    positions_from_msg,
    tool_pose_qos,
)
from meshfg_ros.nodes.publisher_qos import TOPIC_TABLE_FIX, IncompatiblePublishers
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import run_nodes
from meshfg_ros.nodes.simulation_outputs import SimulationOutputs
from meshfg_ros.parameters import simulator_config, world_frame_inputs

_POLL_PERIOD_S = 0.02


class SimulationNode(Node):
    """Simulator predictions at the stamps the estimator asks for (see the module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("simulation_node", **kwargs)
        self.params = declare_parameters(self, "simulation_node")
        self._frame = self.params["world_frame"]
        self._scheduler: PredictionScheduler | None = None
        self.outputs = SimulationOutputs(self, self._frame)
        self._held = HeldUntilMesh({"tool pose": DEFAULT_MAX_SAMPLES, "estimated_mesh": MAX_QUEUED_CLOUDS,
                                    "prediction request": MAX_QUEUED_CLOUDS, "remove_elements": MAX_QUEUED_CLOUDS})
        self._mesh = InitialMeshSource(self, self._frame, self._set_mesh, self._held.release, self.outputs.mesh_rejected)
        self._inputs = FrameInputs(self, world_frame_inputs(self.params), self._on_placed, self._on_unplaceable)
        self.create_subscription(TetraMesh, "estimated_mesh", self._on_estimate, LATCHED_QOS)
        self.create_subscription(TetraMesh, "catch_up_estimate", self._on_catch_up_estimate, REQUEST_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, tool_pose_qos(self.params))
        self.create_subscription(Header, "prediction_request", self._on_request, REQUEST_QOS)
        self.create_subscription(UInt32MultiArray, "remove_elements", self._on_remove_elements, REQUEST_QOS)
        self.setup_warnings = self.outputs.setup_warnings  # what run_nodes found wrong in the set-up
        self._input_qos = IncompatiblePublishers(self)
        self._input_qos.watch("tool_pose", tool_pose_qos(self.params), TOOL_POSE_QOS_FIX)
        for topic, qos in (("estimated_mesh", LATCHED_QOS), ("catch_up_estimate", REQUEST_QOS),
                           ("prediction_request", REQUEST_QOS),
                           ("initial_mesh", LATCHED_QOS), ("/tf", TF_QOS), ("/tf_static", TF_STATIC_QOS)):
            self._input_qos.watch(topic, qos, TOPIC_TABLE_FIX)
        self.outputs.unmatched_publishers = self._input_qos.find
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # waits on wall time, also with use_sim_time
        self.create_timer(_POLL_PERIOD_S, self._answer, clock=steady)
        self._mesh.load_file(self.params)

    def _set_mesh(self, mesh, state) -> None:
        timeouts = SchedulingTimeouts(estimate_timeout=self.params["estimate_timeout"],
                                      tool_pose_timeout=self.params["tool_pose_timeout"])
        self._scheduler = PredictionScheduler(
            mesh, simulator_config(self.params), self.params["grasped_vertices"] or None, timeouts=timeouts,
            clock_jump_threshold=self.params["clock_jump_threshold"],
            tool_pose_extrapolation=self.params["tool_pose_horizon"], newest_first=self.params["newest_first"])
        self.outputs.set_scheduler(self._scheduler, state)

    def _hold(self, kind: str, handler, item) -> None:
        """Keep an input that came before the mesh for `handler` (counted; an overflow drops the
        oldest of its kind)."""
        self.outputs.counters.count("inputs_held_before_mesh")
        dropped = self._held.hold(kind, handler, item)
        if dropped is not None:
            self.outputs.count("inputs_dropped_before_mesh", dropped)

    def _on_estimate(self, msg: TetraMesh) -> None:
        if self._scheduler is None:
            return self._hold("estimated_mesh", self._on_estimate, msg)
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = positions_from_msg(msg, self._scheduler.mesh.vertex_count)
        # A malformed estimate is no estimate: the next request does not wait for it.
        position_std = position_std_from_msg(msg, self._scheduler.mesh.vertex_count)
        if positions is not None and position_std is None and len(msg.position_std):
            self.outputs.count("estimate_std_ignored", f"estimated_mesh at {stamp_ns} ns: position_std has a wrong "
                               "count or entries NaN or negative; the body load and the Poisson ratio learn nothing "
                               "from it")
        rejection = self._scheduler.add_estimate(stamp_ns, positions, degraded=bool(msg.degraded),
                                                 position_std=position_std)
        if positions is None:
            self.outputs.count("estimates_ignored", f"estimated_mesh at {stamp_ns} ns ignored: wrong vertex count or "
                               "non-finite positions")
        elif rejection is not None:
            self.outputs.note(rejection)
        else:
            self.outputs.estimate_taken(stamp_ns)
        self._answer()

    def _on_catch_up_estimate(self, msg: TetraMesh) -> None:
        """The estimate of a stalled stream's cloud run again with this node's catch-up prediction
        (core/scheduler.py): learnt from, the state left at the newest estimate."""
        if self._scheduler is None:
            return
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = positions_from_msg(msg, self._scheduler.mesh.vertex_count)
        position_std = position_std_from_msg(msg, self._scheduler.mesh.vertex_count)
        if positions is None:
            return self.outputs.count("estimates_ignored", f"catch_up_estimate at {stamp_ns} ns ignored: wrong vertex "
                                      "count or non-finite positions")
        learnt = self._scheduler.learn_from_catch_up(stamp_ns, positions, position_std, degraded=bool(msg.degraded))
        if isinstance(learnt, Rejection):
            return self.outputs.note(learnt)
        self.outputs.counters.catch_up_estimates_learnt += int(learnt)

    def _on_tool_pose(self, msg: PoseStamped) -> None:
        self.outputs.counters.tool_poses_received += 1
        try:
            record = pose_from_msg(msg)
        except MessageValidationError as error:
            return self.outputs.count("tool_poses_rejected_malformed", f"tool_pose rejected: {error}")
        self._inputs.add(FramedInput(POSE, record.stamp_ns, record.frame_id, record.pose, time.monotonic()))

    def _on_placed(self, item: FramedInput) -> None:
        """A tool pose in world_frame."""
        if self._scheduler is None:
            return self._hold("tool pose", self._on_placed, item)
        rejection = self._scheduler.add_tool_pose(item.stamp_ns, item.data)
        if rejection is not None:
            return self.outputs.note(rejection)
        self._cut_with_blade(item.data)
        if self._scheduler.restarted:
            self.outputs.counters.clock_jumps_back += 1
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
        mesh's topology. A cut the simulator cannot take (a slot out of range, every element,
        every grasped vertex, a piece left with rigid modes) is counted and changes nothing."""
        removed_before = self._scheduler.mesh.removed_elements.size
        try:
            changed = self._scheduler.remove_elements(slots)
        except (InvalidMeshError, NotPositiveDefiniteError, SimulatorInputError) as error:
            return self.outputs.count("cuts_rejected", f"cut from {source} rejected: {error}")
        if changed:
            mesh = self._scheduler.mesh
            self.outputs.counters.elements_removed = int(mesh.removed_elements.size)
            self.outputs.set_topology(MeshState.of_mesh(mesh, 0, self._frame, 0))
            self.get_logger().info(f"cut ({source}): {mesh.removed_elements.size - removed_before} elements removed, "
                                   f"{mesh.tetrahedron_count} left, {mesh.invalid_vertices.size} vertices invalid")

    def _on_unplaceable(self, unplaceable: Unplaceable) -> None:
        self.outputs.count("tool_poses_rejected_frame", f"tool_pose rejected: {unplaceable.reason}")

    def _on_request(self, msg: Header) -> None:
        """A cloud's stamp to predict; a held one waits for its estimate and pose from the mesh's
        arrival on (the estimate_timeout counts from then)."""
        if self._scheduler is None:
            return self._hold("prediction request", self._on_request, msg)
        self.outputs.counters.requests += 1
        self._scheduler.request(stamp_ns_from_msg(msg.stamp), time.monotonic())
        self._answer()

    def _answer(self) -> None:
        if self._scheduler is None:
            return
        start = time.perf_counter()
        answers = self._scheduler.poll(time.monotonic())
        self.outputs.answers(answers, time.perf_counter() - start)


def main(args=None) -> int:
    """Console script `simulation_node` (accepts --ros-args)."""
    return run_nodes("simulation_node", [SimulationNode], args=args)


if __name__ == "__main__":
    sys.exit(main())
