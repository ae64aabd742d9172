"""The estimator node's service for planners: `surface_query` (meshfg_msgs/SurfaceQuery).

For points in any frame (placed in world_frame through /tf at the request's stamp, or at the
newest transforms for a zero stamp, as tf2's time zero) it answers, on the newest estimate
published on `estimated_mesh`, each point's closest surface point, signed distance (negative
inside the tissue), outward normal and the distance's standard deviation from the estimate's
per-vertex covariance (core/geometry/surface_query.py), with the estimate's stamp and step. Points and
normals come back in the request's frame.

The service reads the estimates from the node's own latched `estimated_mesh`, so it answers on
exactly what subscribers see; the surface's search structures are built at the first query of
each estimate, so a node without planners spends nothing on them. A refused query (no estimate
yet, a frame /tf cannot place, non-finite points) is answered with success false and the reason,
logged, and counted in its own status on /diagnostics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from meshfg_msgs.msg import TetraMesh
from meshfg_msgs.srv import SurfaceQuery as SurfaceQueryService
from meshfg_ros.core.geometry.closest_point import InvalidGeometryError
from meshfg_ros.core.inputs.frames import FrameLookupError, transform_points
from meshfg_ros.core.geometry.surface_query import SurfaceQuery
from meshfg_ros.core.inputs.world_frame import WorldFrameInputs
from meshfg_ros.io.messages import MeshState, MessageValidationError, header_msg, mesh_state_from_msg, stamp_ns_from_msg
from meshfg_ros.nodes.diagnostics import Counters, diagnostic_array
from meshfg_ros.nodes.ros_conversions import LATCHED_QOS, RCLPY_FACTORY, STREAM_QOS

__all__ = ["SURFACE_QUERY_SERVICE", "PlannerService", "points_from_flat"]

SURFACE_QUERY_SERVICE = "surface_query"
_REPORT_PERIOD_S = 1.0


def points_from_flat(values) -> np.ndarray:
    """(K, 3) float64 of a flat x0 y0 z0 x1 ... array; MessageValidationError for a length that
    is not a multiple of 3."""
    flat = np.asarray(values, dtype=np.float64)
    if flat.size % 3:
        raise MessageValidationError(f"points has {flat.size} values, not a multiple of 3 (x y z per point)")
    return flat.reshape(-1, 3)


class QueryRefused(Exception):
    """A query the service cannot answer: `counter` names why (a field of SurfaceQueryCounters)."""

    def __init__(self, counter: str, message: str) -> None:
        self.counter = counter
        super().__init__(message)


@dataclass
class SurfaceQueryCounters(Counters):
    """What the service has done since it started (the values of its diagnostics)."""

    queries_answered: int = 0
    queries_refused_no_estimate: int = 0
    queries_refused_frame: int = 0
    queries_refused_points: int = 0
    estimates_unreadable: int = 0  # estimated_mesh messages that are malformed: the previous one is kept


class PlannerService:
    """`surface_query` on `node` (module docstring); `placer`: the node's placement of inputs
    into world_frame (its /tf buffer and static fallbacks)."""

    def __init__(self, node: Node, placer: WorldFrameInputs) -> None:
        self._node, self._placer = node, placer
        self.counters = SurfaceQueryCounters()
        self._refused_since_report = 0
        self._last_refusal = ""
        self._estimate: MeshState | None = None
        self._surface: SurfaceQuery | None = None  # of self._estimate, made at its first query
        node.create_subscription(TetraMesh, "estimated_mesh", self._on_estimate, LATCHED_QOS)
        node.create_service(SurfaceQueryService, SURFACE_QUERY_SERVICE, self._on_request)
        self._diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        node.create_timer(_REPORT_PERIOD_S, self.report, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _on_estimate(self, msg: TetraMesh) -> None:
        try:
            estimate = mesh_state_from_msg(msg)
            if not len(estimate.surface_triangles):
                raise MessageValidationError("it has no surface triangles")
            self._estimate, self._surface = estimate, None
        except MessageValidationError as error:
            self.counters.estimates_unreadable += 1
            self._node.get_logger().warning(f"surface_query: estimated_mesh at {stamp_ns_from_msg(msg.header.stamp)} "
                                            f"ns is malformed ({error}): queries use the previous one",
                                            throttle_duration_sec=1.0)

    def _on_request(self, request, response):
        try:
            self._answer(request, response)
            self.counters.queries_answered += 1
        except QueryRefused as refusal:
            self.counters.count(refusal.counter)
            self._refused_since_report += 1
            self._last_refusal = str(refusal)
            self._node.get_logger().warning(f"surface_query refused: {refusal}", throttle_duration_sec=1.0)
            response.success, response.message = False, str(refusal)
        return response

    def _answer(self, request, response) -> None:
        """Fill `response` for `request`, or QueryRefused."""
        estimate = self._estimate
        if estimate is None:
            raise QueryRefused("queries_refused_no_estimate", "no estimate yet: the estimator has published none")
        frame_id = request.header.frame_id or estimate.frame_id
        stamp_ns = stamp_ns_from_msg(request.header.stamp)
        try:
            matrix = self._placer.matrix_to_world(frame_id, stamp_ns or None)
        except FrameLookupError as error:
            raise QueryRefused("queries_refused_frame", f"points in {frame_id!r} cannot be placed in "
                               f"{estimate.frame_id!r}: {error}") from None
        if self._surface is None:
            self._surface = SurfaceQuery(estimate.positions, estimate.surface_triangles, estimate.position_covariance)
        try:
            answer = self._surface.query(transform_points(matrix, points_from_flat(request.points)))
        except (InvalidGeometryError, MessageValidationError) as error:
            raise QueryRefused("queries_refused_points", f"points rejected: {error}") from None
        rotation = matrix[:3, :3]
        response.success = True
        response.message = "" if answer.distance_std is not None else (
            "the estimate has no covariance: distance_std is empty")
        response.header = header_msg(estimate.stamp_ns, frame_id, RCLPY_FACTORY)
        response.estimate_step, response.degraded = estimate.step, estimate.degraded
        # The answer back in the request's frame: the inverse rigid transform (rows: p' = R^T (p - t)).
        response.closest_points = RCLPY_FACTORY.sequence((answer.closest - matrix[:3, 3]) @ rotation, np.float64)
        response.normals = RCLPY_FACTORY.sequence(answer.normal @ rotation, np.float64)
        response.signed_distances = RCLPY_FACTORY.sequence(answer.signed_distance, np.float64)
        if answer.distance_std is not None:
            response.distance_std = RCLPY_FACTORY.sequence(answer.distance_std, np.float64)

    def report(self) -> None:
        """The service's status on /diagnostics: WARN while queries were refused since the last report."""
        refused, self._refused_since_report = self._refused_since_report, 0
        if refused:
            level, message = DiagnosticStatus.WARN, f"{refused} surface queries refused since the last report; " \
                                                    f"the last: {self._last_refusal}"
        elif self._estimate is None:
            level, message = DiagnosticStatus.OK, "no estimate to answer surface queries on yet"
        else:
            level, message = DiagnosticStatus.OK, f"answering surface queries on the estimate of step {self._estimate.step}"
        self._diagnostics.publish(diagnostic_array(f"{self._node.get_fully_qualified_name()}: surface queries", level,
                                                   message, self.counters, self._node.get_clock().now().nanoseconds))
