"""What the estimator node publishes, and the bookkeeping behind its diagnostics.

`EstimatorOutputs` owns the node's publishers (`estimated_mesh` latched, with its std and
covariance, `status`, `markers` built only while someone subscribes, `/diagnostics` after each
step and every second, `catch_up_estimate` for the simulation node after a stalled tool stream),
its counters and health (nodes/diagnostics.py), and the latency history.
Input callbacks and the solver thread both report to it; a lock of its own guards the counters.
"""

from __future__ import annotations

import re
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from visualization_msgs.msg import MarkerArray

from meshfg_msgs.msg import EstimatorStatus, TetraMesh
from meshfg_ros.core.inputs.camera_check import IMPLAUSIBLE_SHARE, implausible_view
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.scheduler import CloudStep, Rejection, StepOutcome
from meshfg_ros.io.messages import MeshState, status_record, status_to_msg
from meshfg_ros.markers import mesh_markers, spread_surface_sample, surface_edges
from meshfg_ros.nodes.diagnostics import (ERROR, OK, EstimatorCounters, EstimatorHealth, diagnostic_array,
                                          with_setup_problems)
from meshfg_ros.nodes.ros_conversions import LATCHED_QOS, RCLPY_FACTORY, REQUEST_QOS, STREAM_QOS, MeshMessages

_LATENCY_HISTORY = 100
MIN_VIEW_POINTS = 30  # a cloud with fewer points near the surface says nothing of the camera
_REPORT_PERIOD_S = 1.0


class EstimatorOutputs:
    """The estimator node's publications (module docstring)."""

    def __init__(self, node: Node, frame: str, stalled_after_s: float, marker_std_max: Callable[[], float],
                 queued: Callable[[], int | None]) -> None:
        """marker_std_max: the current parameter; queued: clouds waiting in the scheduler (None: no mesh yet)."""
        self._node, self._frame, self._marker_std_max, self._queued = node, frame, marker_std_max, queued
        self.counters = EstimatorCounters()
        self.health = EstimatorHealth(stalled_after_s)
        self._lock = threading.Lock()
        self._latencies: deque[float] = deque(maxlen=_LATENCY_HISTORY)
        self._unanswered_since_s: float | None = None
        self._last_rejection = ""
        self._last_prediction_problem = ""  # the newest sim_bridge answer refused, and why
        # The node's wiring, which the diagnostics put first: input publishers whose QoS cannot
        # match (nodes/publisher_qos.py) and what run_nodes found wrong in the set-up.
        self.unmatched_publishers: Callable[[], list[str]] = list
        self.setup_warnings: list[str] = []
        self._logged_health = ""  # the last WARN / ERROR logged, numbers aside (_log_new_health)
        self._markers_job: tuple | None = None
        # The mesh's state, its TetraMesh builder, surface edges and vertices given ellipsoids (markers).
        self._mesh: tuple[MeshState, MeshMessages, np.ndarray, np.ndarray] | None = None
        self._estimates = node.create_publisher(TetraMesh, "estimated_mesh", LATCHED_QOS)
        self._catch_up_estimates = node.create_publisher(TetraMesh, "catch_up_estimate", REQUEST_QOS)
        self._statuses = node.create_publisher(EstimatorStatus, "status", STREAM_QOS)
        self._markers = node.create_publisher(MarkerArray, "markers", STREAM_QOS)
        self._diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self._wake = node.create_guard_condition(self.report)
        node.create_timer(_REPORT_PERIOD_S, self.report, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def set_mesh(self, state: MeshState) -> None:
        """The topology of the estimates to come. Clouds that came before it (held until now)
        are awaited from now on: the stall test does not count the wait for the mesh."""
        self._set_topology(state)
        with self._lock:
            if self._unanswered_since_s is not None:
                self._unanswered_since_s = time.monotonic()

    def _set_topology(self, state: MeshState) -> None:
        self._mesh = (state, MeshMessages(state), surface_edges(state.surface_triangles),
                      spread_surface_sample(state.positions, state.surface_triangles, state.fixed_vertices))

    def cloud_received(self, arrival_s: float, dropped_nonfinite: int = 0) -> None:
        with self._lock:
            self.counters.clouds_received += 1
            self.counters.nan_points_dropped += dropped_nonfinite
            self._unanswered_since_s = self._unanswered_since_s or arrival_s

    def count(self, counter: str) -> None:
        with self._lock:
            self.counters.count(counter)

    def mesh_rejected(self, reason: str) -> None:
        """An initial_mesh message refused (InitialMeshSource logged it): counted, and named while
        the node waits for a mesh."""
        with self._lock:
            self.counters.count("initial_meshes_rejected")
            self.health.last_mesh_rejection = reason

    def note(self, rejections: list[Rejection]) -> None:
        """Count and log what was set aside, and report it."""
        for rejection in rejections:
            with self._lock:
                self.counters.count(rejection.counter)
                if rejection.counter in EstimatorCounters.CLOUD_REJECTIONS:  # what "every cloud is rejected" names
                    self._last_rejection = rejection.reason
                if rejection.counter.startswith("sim_bridge_") and rejection.counter != "sim_bridge_stiffness_repaired":
                    self._last_prediction_problem = rejection.reason
            self._node.get_logger().warning(rejection.reason, throttle_duration_sec=1.0)
        if rejections:
            self._wake.trigger()

    def step(self, step: CloudStep, outcome: StepOutcome, start_s: float, mesh: TetMesh | None = None) -> None:
        """Publish a step's estimate and status (solver thread), or log and count its failure.
        `mesh`: the estimator's after the step; after a cut the estimate is published (and drawn)
        on its topology: the remaining elements and surface, the removed elements and invalid
        vertices listed."""
        self._send_reruns(outcome.reruns)
        result = outcome.result
        if result is None:
            self._failed(outcome, "")
            return self._wake.trigger()
        if mesh is not None and not np.array_equal(mesh.removed_elements, self._mesh[0].removed_elements):
            self._set_topology(MeshState.of_mesh(mesh, step.stamp_ns, self._frame, 0))
            self._node.get_logger().info(f"following a cut: {mesh.removed_elements.size} elements removed, "
                                         f"{mesh.invalid_vertices.size} vertices invalid")
        _, messages, _, _ = self._mesh
        publish_start = time.monotonic()
        self._estimates.publish(messages.message(step.stamp_ns, self._frame, result.step, result.positions,
                                                 result.position_std, result.degraded, result.position_covariance))
        self._statuses.publish(status_to_msg(status_record(result, self._frame), RCLPY_FACTORY))
        done = time.monotonic()
        view_implausible = self._view_implausible(step, result)
        with self._lock:
            self._latencies.append(1e3 * (done - step.arrival_s))
            self.counters.record_step(result, 1e3 * (start_s - step.arrival_s), 1e3 * (done - publish_start),
                                      list(self._latencies))
            self.health.record(result.degraded, result.converged, result.num_points, result.num_points_rejected,
                               result.noise_off_nominal, view_implausible)
            self.counters.steps_view_implausible += int(view_implausible)
            self._unanswered_since_s = None
            self._markers_job = (result.positions, result.position_std, result.position_covariance, step.points,
                                 step.stamp_ns)
        self._wake.trigger()

    def _failed(self, outcome: StepOutcome, what: str) -> None:
        """Log and count a step that gave no estimate (`what` qualifies the update in the log)."""
        self._node.get_logger().error(f"update at {outcome.step.stamp_ns} ns{what}: {outcome.error}")
        self.count(outcome.counter)

    def _send_reruns(self, reruns: tuple[StepOutcome, ...]) -> None:
        """The estimates of a stalled stream's clouds run again (StepOutcome.reruns), to the
        simulation node on catch_up_estimate: older than the estimates published, not published
        as estimates. A re-run that failed is logged and counted as any step's failure."""
        messages = self._mesh[1]
        for outcome in reruns:
            self.note(list(outcome.notes))
            result = outcome.result
            if result is None:
                self._failed(outcome, ", run again")
                continue
            self._catch_up_estimates.publish(messages.message(result.stamp_ns, self._frame, result.step,
                                                              result.positions, result.position_std, result.degraded,
                                                              result.position_covariance))
            self.count("clouds_run_again")
        if reruns:
            estimated = sum(outcome.result is not None for outcome in reruns)
            self._node.get_logger().info(f"tool poses came again: {len(reruns)} clouds of the stall run again with "
                                         f"the simulator's late predictions, {estimated} estimated")

    def _view_implausible(self, step: CloudStep, result) -> bool:
        """Whether more than IMPLAUSIBLE_SHARE of the step's cloud lies at angles no camera at its
        viewpoint sees (core/inputs/camera_check.py); after the estimate is out, so it adds no latency."""
        if step.viewpoint is None or step.points is None:
            return False
        state = self._mesh[0]
        implausible, considered = implausible_view(result.positions, state.surface_triangles, step.points,
                                                   step.viewpoint, result.measurement_sigma)
        return considered >= MIN_VIEW_POINTS and implausible > IMPLAUSIBLE_SHARE * considered

    def _log_new_health(self, level: bytes, message: str) -> None:
        """Log a WARN or ERROR the first time it says something new, its numbers aside: the
        diagnostics repeat it every second, the log says it once (a camera or a measurement_sigma
        that the clouds contradict is otherwise only in /diagnostics)."""
        kind = re.sub(r"\d+(\.\d+)?", "N", message) if level != OK else ""
        if kind and kind != self._logged_health:
            if level == ERROR:  # rclpy: one severity per call site
                self._node.get_logger().error(f"diagnostics: {message}")
            else:
                self._node.get_logger().warning(f"diagnostics: {message}")
        self._logged_health = kind

    def report(self) -> None:
        """Diagnostics (after each step and periodically) and markers of the newest estimate."""
        queued = self._queued()
        with self._lock:
            self.counters.queued_clouds = queued or 0
            counters, job, self._markers_job = replace(self.counters), self._markers_job, None
            since, last_rejection = self._unanswered_since_s, self._last_rejection
            self.health.prediction_problem = self._last_prediction_problem
        unanswered_s = 0.0 if since is None else time.monotonic() - since
        health = self.health.assess(counters, queued is None, unanswered_s, last_rejection)
        self._log_new_health(*health)  # the wiring's problems are logged where they are found
        level, message = with_setup_problems(*health, self.unmatched_publishers(), self.setup_warnings)
        self._diagnostics.publish(diagnostic_array(f"{self._node.get_fully_qualified_name()}: estimation", level,
                                                   message, counters, self._node.get_clock().now().nanoseconds))
        if job is not None and self._markers.get_subscription_count() > 0:
            state, _, edges, ellipsoid_vertices = self._mesh
            positions, position_std, position_covariance, points, stamp_ns = job
            self._markers.publish(mesh_markers(positions, state.surface_triangles, position_std, points, self._frame,
                                               stamp_ns, self._marker_std_max(), edges, RCLPY_FACTORY,
                                               position_covariance, ellipsoid_vertices))
