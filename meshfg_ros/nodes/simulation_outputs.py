"""What the simulation node publishes, and the bookkeeping behind its diagnostics.

`SimulationOutputs` owns the node's publishers (`predicted_mesh` and `prediction_failed` for each
answer, `body_acceleration` after each estimate the simulator learns from, `/diagnostics` every
second), its counters and health (nodes/diagnostics.py). The node's callbacks report to it, all
on the executor's thread.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from meshfg_msgs.msg import PredictionFailure, TetraMesh
from meshfg_ros.core.scheduler import Prediction, PredictionScheduler, Rejection
from meshfg_ros.io.messages import MeshState, header_msg, vector_msg
from meshfg_ros.nodes.diagnostics import SimulatorCounters, SimulatorHealth, diagnostic_array, with_setup_problems
from meshfg_ros.nodes.ros_conversions import PREDICTION_QOS, RCLPY_FACTORY, STREAM_QOS, MeshMessages

_REPORT_PERIOD_S = 1.0


class SimulationOutputs:
    """The simulation node's publications (module docstring)."""

    def __init__(self, node: Node, frame: str) -> None:
        self._node, self._frame = node, frame
        self.counters = SimulatorCounters()
        self.health = SimulatorHealth()
        # The node's wiring, which the diagnostics put first: input publishers whose QoS cannot
        # match (nodes/publisher_qos.py) and what run_nodes found wrong in the set-up.
        self.unmatched_publishers: Callable[[], list[str]] = list
        self.setup_warnings: list[str] = []
        self._scheduler: PredictionScheduler | None = None
        self._messages: MeshMessages | None = None
        self._unavailable_earlier: Counter[str] = Counter()  # of the schedulers of earlier meshes
        self._predictions = node.create_publisher(TetraMesh, "predicted_mesh", PREDICTION_QOS)
        self._failures = node.create_publisher(PredictionFailure, "prediction_failed", PREDICTION_QOS)
        self._body_acceleration = node.create_publisher(Vector3Stamped, "body_acceleration", PREDICTION_QOS)
        self._diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        node.create_timer(_REPORT_PERIOD_S, self.report, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def set_scheduler(self, scheduler: PredictionScheduler, state: MeshState) -> None:
        """A new mesh's scheduler and the topology of its predictions; the tool pose counters stay
        those since the node started."""
        if self._scheduler is not None:
            self._unavailable_earlier.update(self._scheduler.tool_pose_unavailable)
        self._scheduler = scheduler
        self._messages = MeshMessages(state)

    def set_topology(self, state: MeshState) -> None:
        """The topology of the predictions to come (after a cut)."""
        self._messages = MeshMessages(state)

    def mesh_rejected(self, reason: str) -> None:
        """An initial_mesh message refused (InitialMeshSource logged it): counted, and named while
        the node waits for a mesh."""
        self.counters.count("initial_meshes_rejected")
        self.health.last_mesh_rejection = reason

    def count(self, counter: str, reason: str) -> None:
        """One more of `counter`, with its reason logged."""
        self.counters.count(counter)
        self._node.get_logger().warning(reason, throttle_duration_sec=1.0)

    def note(self, rejection: Rejection) -> None:
        """Count and log an input the scheduler set aside."""
        self.count(rejection.counter, rejection.reason)

    def estimate_taken(self, stamp_ns: int) -> None:
        """After the scheduler took the estimate at `stamp_ns`: publish the body load learnt so far,
        when it is learnt and that estimate is the next prediction's start."""
        acceleration = self._scheduler.simulator.body_acceleration
        if acceleration is not None and self._scheduler.state_stamp_ns == stamp_ns:
            self._body_acceleration.publish(vector_msg(stamp_ns, self._frame, acceleration, RCLPY_FACTORY))

    def answers(self, answers: list[Prediction], elapsed_s: float) -> None:
        """Publish the scheduler's answers, given in `elapsed_s` of simulator time: a prediction, or
        a failure with its reason (superseded ones flagged)."""
        predicted = sum(answer.positions is not None for answer in answers)
        if predicted:
            self.counters.last_prediction_ms = 1e3 * elapsed_s / predicted
        for answer in answers:
            if answer.positions is None:
                if answer.superseded:
                    self.counters.predictions_superseded += 1
                else:
                    self.counters.predictions_failed += 1
                    self.health.record(answer.failure)
                    self._node.get_logger().warning(f"no prediction for {answer.stamp_ns} ns: {answer.failure}",
                                                    throttle_duration_sec=1.0)
                self._failures.publish(PredictionFailure(header=header_msg(answer.stamp_ns, self._frame, RCLPY_FACTORY),
                                                         reason=answer.failure, superseded=answer.superseded))
                continue
            self.counters.predictions += 1
            self.counters.catch_up_predictions += int(answer.catch_up)
            self.health.record(None)
            self._predictions.publish(self._messages.message(answer.stamp_ns, self._frame, self.counters.predictions,
                                                             answer.positions))

    def report(self) -> None:
        """Diagnostics: the counters, with what the simulator has learnt, and the health's level and reason."""
        counters = self.counters
        if self._scheduler is not None:
            totals = self._unavailable_earlier + Counter(self._scheduler.tool_pose_unavailable)
            for reason, count in totals.items():
                setattr(counters, f"tool_pose_unavailable_{reason}", count)
            simulator = self._scheduler.simulator
            acceleration = simulator.body_acceleration
            if acceleration is not None:
                counters.body_acceleration_x, counters.body_acceleration_y, counters.body_acceleration_z = (
                    acceleration.tolist())
            counters.poisson_ratio = simulator.poisson_ratio
        health = self.health.assess(counters, self._scheduler is None)
        level, message = with_setup_problems(*health, self.unmatched_publishers(), self.setup_warnings)
        self._diagnostics.publish(diagnostic_array(f"{self._node.get_fully_qualified_name()}: simulation", level,
                                                   message, counters, self._node.get_clock().now().nanoseconds))
