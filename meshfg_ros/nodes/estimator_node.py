"""estimator_node: the sliding-window factor-graph estimator, as a ROS 2 node (a shell over
core.scheduler.EstimationScheduler).

Subscribes `points` (sensor_msgs/PointCloud2, any frame placed through /tf, sensor-data QoS
unless points_reliable), `tool_pose` (geometry_msgs/PoseStamped, any frame and rate: points on
the tool are segmentation leaks), `predicted_mesh` and `prediction_failed` (the simulation node's
answers), `initial_mesh` (or parameter mesh_file), /tf and /tf_static. Each accepted cloud is
announced on `prediction_request` (std_msgs/Header); with prediction_source sim_bridge it is
asked of the XPBD simulator's sim_bridge service instead (nodes/sim_bridge_client.py), whose
answer takes the same path to the estimator. Publishes the estimate, its status, markers
and diagnostics (nodes/estimator_outputs.py), and answers planners' `surface_query`
(nodes/planner_service.py). Updates run in their own thread, so a long solve
does not make DDS drop input. Clouds and tool poses that arrive before the mesh are held until
it comes (nodes/held_inputs.py).
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import replace

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from meshfg_msgs.msg import PredictionFailure, TetraMesh
from meshfg_ros import blas
import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.scheduler import (
    MAX_QUEUED_CLOUDS,
    EstimationScheduler,
    Prediction,
    Rejection,
    SchedulingTimeouts,
    StepOutcome,
    cloud_queued,
)
from meshfg_ros.core.inputs.tool_poses import DEFAULT_MAX_SAMPLES
from meshfg_ros.core.inputs.world_frame import CLOUD, POSE, FramedInput, Unplaceable
from meshfg_ros.io.messages import MessageValidationError, header_msg, pose_from_msg, stamp_ns_from_msg
from meshfg_ros.io.pointcloud import PointCloudError, cloud_record_from_msg
from meshfg_ros.nodes.estimator_outputs import EstimatorOutputs
from meshfg_ros.nodes.frame_inputs import TF_QOS, TF_STATIC_QOS, FrameInputs
from meshfg_ros.nodes.held_inputs import HeldUntilMesh
from meshfg_ros.nodes.planner_service import PlannerService
from meshfg_ros.nodes.publisher_qos import TOPIC_TABLE_FIX, IncompatiblePublishers
from meshfg_ros.nodes.ros_conversions import LATCHED_QOS, PREDICTION_QOS, RCLPY_FACTORY, REQUEST_QOS, TOOL_POSE_QOS_FIX
from meshfg_ros.nodes.ros_conversions import InitialMeshSource, positions_from_msg, tool_pose_qos
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import SolverThread, run_nodes
from meshfg_ros.nodes.sim_bridge_client import SimBridgeClient
from meshfg_ros.parameters import estimator_changes, estimator_config, world_frame_inputs

RELIABLE_POINTS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
_STALL_MARGIN_S = 1.0  # beyond the transform and prediction waits and two time budgets: no estimate means stuck


class EstimatorNode(Node):
    """Estimated mesh per point cloud (see the module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("estimator_node", **kwargs)
        self.params = declare_parameters(self, "estimator_node", on_change=self._reconfigure)
        self._frame = self.params["world_frame"]
        self._lock = threading.Lock()  # guards the scheduler
        self._scheduler: EstimationScheduler | None = None
        stalled_after_s = (self.params["transform_timeout"] + self.params["prediction_timeout"] + _STALL_MARGIN_S
                           + 2.0 * (estimator_config(self.params).update_time_budget or 0.0))
        self.outputs = EstimatorOutputs(self, self._frame, stalled_after_s, lambda: self.params["marker_std_max"],
                                        self._queued)
        self._requests = self.create_publisher(Header, "prediction_request", REQUEST_QOS)
        self._held = HeldUntilMesh({POSE: DEFAULT_MAX_SAMPLES, CLOUD: MAX_QUEUED_CLOUDS})
        self._mesh = InitialMeshSource(self, self._frame, self._set_mesh, self._held.release, self.outputs.mesh_rejected)
        self._inputs = FrameInputs(self, world_frame_inputs(self.params), self._on_placed, self._on_unplaceable)
        self._bridge = None if self.params["prediction_source"] != "sim_bridge" else SimBridgeClient(
            self, self.params["sim_bridge_service"], self.params["sim_bridge_stiffness"], self._frame,
            self._inputs.placer.transforms, self.params["prediction_timeout"], self._on_bridge_answer)
        self._planner_service = PlannerService(self, self._inputs.placer)
        self._predictions = None  # the simulation node's predictions; none with sim_bridge
        if self._bridge is None:  # else nothing but the service predicts
            self._predictions = self.create_subscription(TetraMesh, "predicted_mesh", self._on_prediction,
                                                         PREDICTION_QOS)
            self.create_subscription(PredictionFailure, "prediction_failed", self._on_failure, PREDICTION_QOS)
        self.create_subscription(PoseStamped, "tool_pose", self._on_tool_pose, tool_pose_qos(self.params))
        points_qos = RELIABLE_POINTS_QOS if self.params["points_reliable"] else qos_profile_sensor_data
        self.create_subscription(PointCloud2, "points", self._on_cloud, points_qos)
        self.setup_warnings = self.outputs.setup_warnings  # what run_nodes found wrong in the set-up
        self._input_qos = IncompatiblePublishers(self)
        self._input_qos.watch("points", points_qos, "publish it reliable, or set points_reliable:=false")
        self._input_qos.watch("tool_pose", tool_pose_qos(self.params), TOOL_POSE_QOS_FIX)
        for topic, qos in (("predicted_mesh", PREDICTION_QOS), ("prediction_failed", PREDICTION_QOS),
                           ("initial_mesh", LATCHED_QOS), ("/tf", TF_QOS), ("/tf_static", TF_STATIC_QOS)):
            self._input_qos.watch(topic, qos, TOPIC_TABLE_FIX)
        self.outputs.unmatched_publishers = self._input_qos.find
        self._mesh.load_file(self.params)
        self._solver = SolverThread(self._next_step, self._run, self.get_logger())

    def destroy_node(self) -> None:
        self._solver.stop()
        super().destroy_node()

    def _reconfigure(self, changes: dict) -> None:
        """Dynamic parameters set while running: the estimator uses them from its next update on."""
        with self._lock:
            if self._scheduler is not None:
                self._scheduler.reconfigure(estimator_changes(changes))

    def _queued(self) -> int | None:
        with self._lock:
            return None if self._scheduler is None else self._scheduler.queued

    # ------------------------------------------------------------------ input (executor thread)
    def _set_mesh(self, mesh, state) -> None:
        scheduler = EstimationScheduler(
            mesh, estimator_config(self.params), clock_jump_threshold=self.params["clock_jump_threshold"],
            tool_pose_extrapolation=self.params["tool_pose_horizon"],
            timeouts=SchedulingTimeouts(prediction_timeout=self.params["prediction_timeout"]),
            scale_origin=np.asarray(self.params["mesh_pose"][:3]) if self._mesh.from_file else None,
            simulator_present=None if self._predictions is None else self._simulation_node_present)
        self.outputs.set_mesh(state)
        if self._bridge is not None:
            self._bridge.set_mesh(mesh)
        with self._lock:
            self._scheduler = scheduler
        self.get_logger().info(f"sparse Cholesky BLAS: {blas.backend().name}, {blas.backend().threads} thread(s); "
                               f"worker threads: {worker_threads.count()}")

    def _simulation_node_present(self) -> bool:
        """Whether a simulation node publishes predicted_mesh (the first clouds' wait, core/scheduler.py)."""
        return self._predictions.get_publisher_count() > 0

    def _on_cloud(self, msg: PointCloud2) -> None:
        arrival_s = time.monotonic()
        try:
            record = cloud_record_from_msg(msg)
        except Exception as error:  # noqa: BLE001 - no cloud, however odd, may stop the node
            self.outputs.cloud_received(arrival_s)
            known = isinstance(error, (PointCloudError, MessageValidationError))
            why = f"malformed cloud rejected: {error}" if known else f"undecodable cloud rejected: {error!r}"
            return self.outputs.note([Rejection("clouds_rejected_malformed", why)])
        self.outputs.cloud_received(arrival_s, record.dropped_nonfinite)
        if len(record.points) == 0:
            return self.outputs.note([Rejection("clouds_rejected_empty", f"cloud at {record.stamp_ns} ns has no "
                                                "finite points: rejected")])
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
            scheduler = self._scheduler
            if scheduler is not None and item.kind == POSE:
                scheduler.add_tool_pose(item.stamp_ns, item.data)
                notes = []
            elif scheduler is not None:
                notes = scheduler.add_cloud(item.stamp_ns, item.data, item.arrival_s, item.viewpoint)
        if scheduler is None:
            return self._hold(item)
        if item.kind == CLOUD and cloud_queued(notes):
            self._request_prediction(item.stamp_ns)
        self.outputs.note(notes)
        self._solver.wake()

    def _hold(self, item: FramedInput) -> None:
        """Keep an input that came before the mesh (counted; an overflow drops the oldest of its
        kind). A held cloud's wait for its prediction counts from its release, when it can first
        be requested (its latency too)."""
        self.outputs.count("inputs_held_before_mesh")
        handler = self._on_placed if item.kind == POSE else (
            lambda cloud: self._on_placed(replace(cloud, arrival_s=time.monotonic())))
        dropped = self._held.hold(item.kind, handler, item)
        if dropped is not None:
            self.outputs.note([Rejection("inputs_dropped_before_mesh", dropped)])

    def _on_unplaceable(self, unplaceable: Unplaceable) -> None:
        if unplaceable.item.kind == CLOUD:
            self.outputs.note([Rejection("clouds_rejected_frame", f"cloud rejected: {unplaceable.reason}")])

    def _on_prediction(self, msg: TetraMesh) -> None:
        stamp_ns = stamp_ns_from_msg(msg.header.stamp)
        positions = positions_from_msg(msg, len(msg.positions) // 3)
        if positions is None:
            self.outputs.note([Rejection("predictions_rejected", f"predicted_mesh at {stamp_ns} ns is malformed or "
                                         "not finite: the step runs without it")])
        # The simulator's topology: after a cut, the element slots it removed (the estimator follows them).
        removed = np.asarray(msg.removed_elements, dtype=np.int64)
        self._take_answer(Prediction(stamp_ns, positions, "" if positions is not None else "malformed or not finite",
                                     removed_elements=removed if removed.size else None))

    def _on_failure(self, msg: PredictionFailure) -> None:
        answer = Prediction(stamp_ns_from_msg(msg.header.stamp), None, msg.reason, superseded=msg.superseded)
        self._take_answer(answer, None if msg.superseded else "predictions_failed")  # superseded: the skip counts

    def _take_answer(self, answer: Prediction, counter: str | None = "predictions_received") -> None:
        if counter is not None:
            self.outputs.count(counter)
        with self._lock:
            rejection = None if self._scheduler is None else self._scheduler.add_prediction(answer, time.monotonic())
        self.outputs.note([rejection] if rejection else [])
        self._solver.wake()

    def _request_prediction(self, stamp_ns: int) -> None:
        """Ask the prediction source for the prediction of the cloud at `stamp_ns`."""
        if self._bridge is None:
            return self._requests.publish(header_msg(stamp_ns, self._frame, RCLPY_FACTORY))
        self.outputs.count("sim_bridge_calls")
        self._bridge.request(stamp_ns)

    def _on_bridge_answer(self, answer: Prediction | None, notes: list[Rejection]) -> None:
        self.outputs.note(notes)
        if answer is not None:
            self._take_answer(answer, "predictions_received" if answer.positions is not None else "predictions_failed")

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
        if not self._solver.stopping:  # after shutdown the node may be gone already
            self.outputs.note(list(outcome.notes))
            self.outputs.step(step, outcome, start_s, scheduler.estimator.mesh)


def main(args=None) -> int:
    """Console script `estimator_node` (accepts --ros-args)."""
    return run_nodes("estimator_node", [EstimatorNode], args=args)  # + its solver thread


if __name__ == "__main__":
    sys.exit(main())
