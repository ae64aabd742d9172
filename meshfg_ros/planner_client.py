"""For planners: where points are with respect to the estimated tissue surface, live or on a recording.

Both classes answer `query(points, ...)` with a `SurfaceAnswer`: per point the closest surface
point, the signed distance (negative inside the tissue), the outward unit normal and the
distance's standard deviation, with the stamp and step of the estimate they were computed on
(core/geometry/surface_query.py says how).

- `SurfaceQueryClient(node)` calls the estimator node's `surface_query` service
  (meshfg_msgs/SurfaceQuery): points in any frame /tf knows, on the newest estimate.
- `RecordedSurface(path)` answers the same queries on the estimates of a recording (the
  `estimated_mesh` of `meshfg replay`'s output, or of a recorded live run) without ROS: points in
  the estimates' frame, on the newest estimate at or before a stamp.

`clearance_positions(points, answer, clearance_sigmas, min_clearance)` moves points out of the
uncertain surface's reach: what the example planner node (nodes/tool_clearance_node.py) does to
a tool tip.

This module imports no ROS package until a `SurfaceQueryClient` is made, so `RecordedSurface`
works where ROS is not installed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshfg_ros.core.geometry.surface_query import SurfaceQuery
from meshfg_ros.io.messages import MeshState, RclpyMessageFactory, header_msg, stamp_ns_from_msg
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.topics import ESTIMATED_MESH_TOPIC

__all__ = ["RecordedSurface", "SurfaceAnswer", "SurfaceQueryClient", "SurfaceQueryError", "clearance_positions"]


class SurfaceQueryError(RuntimeError):
    """A query that got no answer: refused by the service (the message says why), timed out, or
    asked of a recording at a stamp before its first estimate."""


@dataclass(frozen=True)
class SurfaceAnswer:
    """Answers for K points. stamp_ns, step, degraded: the estimate's; frame_id: the frame of
    closest and normal (the points'); closest (K, 3) m; signed_distance (K,) m, negative inside;
    normal (K, 3) outward unit; distance_std (K,) m, or None where the estimate has no covariance."""

    stamp_ns: int
    step: int
    degraded: bool
    frame_id: str
    closest: np.ndarray
    signed_distance: np.ndarray
    normal: np.ndarray
    distance_std: np.ndarray | None


def clearance_positions(points, answer: SurfaceAnswer, clearance_sigmas: float, min_clearance: float = 0.0) -> np.ndarray:
    """`points` (K, 3) moved out along their normals to a signed distance of at least
    max(min_clearance, clearance_sigmas x distance_std) from the surface; points already that far
    are kept. Without a covariance only min_clearance counts.

    Moving a point along the signed distance's gradient by (required - d) puts it at the required
    distance from its closest point; where the surface curves back towards it (a fold), another
    part may be nearer: query the result again to check.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    required = np.full(len(points), float(min_clearance))
    if answer.distance_std is not None:
        required = np.maximum(required, clearance_sigmas * answer.distance_std)
    shortfall = np.maximum(required - answer.signed_distance, 0.0)
    return points + shortfall[:, None] * answer.normal


def _xyz(values) -> np.ndarray:
    return np.asarray(values, dtype=np.float64).reshape(-1, 3)


class RecordedSurface:
    """Surface queries on the estimates of a recording, without ROS (module docstring).

    `estimates`: MeshState estimates in stamp order (as `RecordingReader.records` gives them), or
    use `from_recording(path)`. Each estimate's search structures are built at its first query.
    """

    def __init__(self, estimates) -> None:
        self.estimates: list[MeshState] = sorted(estimates, key=lambda state: state.stamp_ns)
        if not self.estimates:
            raise SurfaceQueryError("no estimates to query")
        self.stamps_ns = np.array([state.stamp_ns for state in self.estimates], dtype=np.int64)
        self._surfaces: dict[int, SurfaceQuery] = {}

    @classmethod
    def from_recording(cls, path: str | Path, topic: str = ESTIMATED_MESH_TOPIC) -> RecordedSurface:
        """The estimates on `topic` of the recording at `path` (RecordingError when it has none)."""
        with RecordingReader(path) as reader:
            return cls(list(reader.records(topic, MeshState)))

    def query(self, points, stamp_ns: int | None = None) -> SurfaceAnswer:
        """Answers for `points` (K, 3, in the estimates' frame) on the newest estimate at or
        before `stamp_ns` (None: the last one)."""
        position = len(self.estimates) - 1 if stamp_ns is None else int(np.searchsorted(self.stamps_ns, stamp_ns,
                                                                                          side="right")) - 1
        if position < 0:
            raise SurfaceQueryError(f"no estimate at or before {stamp_ns} ns: the first is at {self.stamps_ns[0]} ns")
        estimate = self.estimates[position]
        if position not in self._surfaces:
            self._surfaces[position] = SurfaceQuery(estimate.positions, estimate.surface_triangles,
                                                    estimate.position_covariance)
        answer = self._surfaces[position].query(points)
        return SurfaceAnswer(estimate.stamp_ns, estimate.step, estimate.degraded, estimate.frame_id, answer.closest,
                             answer.signed_distance, answer.normal, answer.distance_std)


class SurfaceQueryClient:
    """Calls the estimator node's `surface_query` service from `node` (module docstring).

    `service`: its name, resolved in the node's namespace (e.g. /meshfg/surface_query).
    `query` waits for the answer by spinning `node`: call it from a script or a thread that does
    not spin the node already; in a callback use `query_async` and `answer_from_response`.
    """

    def __init__(self, node, service: str = "surface_query") -> None:
        # ROS is imported here, not with the module: RecordedSurface needs none.
        from meshfg_msgs.srv import SurfaceQuery as SurfaceQueryService

        self._node, self._service_type = node, SurfaceQueryService
        self._factory = RclpyMessageFactory()
        self.client = node.create_client(SurfaceQueryService, service)

    def query_async(self, points, frame_id: str = "", stamp_ns: int = 0):
        """Send the request; the rclpy Future of its response. points (K, 3) metres in `frame_id`
        (empty: the estimate's frame), placed through /tf at stamp_ns (0: the newest transforms)."""
        request = self._service_type.Request()
        request.header = header_msg(int(stamp_ns), frame_id, self._factory)
        request.points = self._factory.sequence(np.asarray(points, dtype=np.float64).reshape(-1, 3), np.float64)
        return self.client.call_async(request)

    def query(self, points, frame_id: str = "", stamp_ns: int = 0, timeout_s: float = 1.0) -> SurfaceAnswer:
        """query_async, waited for up to timeout_s (also for the service to appear); SurfaceQueryError
        when it is refused or does not come."""
        import rclpy

        if not self.client.wait_for_service(timeout_sec=timeout_s):
            raise SurfaceQueryError(f"service {self.client.srv_name} is not available")
        future = self.query_async(points, frame_id, stamp_ns)
        rclpy.spin_until_future_complete(self._node, future, timeout_sec=timeout_s)
        if not future.done():
            self.client.remove_pending_request(future)
            raise SurfaceQueryError(f"no answer from {self.client.srv_name} within {timeout_s:g} s")
        return self.answer_from_response(future.result())

    @staticmethod
    def answer_from_response(response) -> SurfaceAnswer:
        """The SurfaceAnswer of a SurfaceQuery response, or SurfaceQueryError with its reason."""
        if not response.success:
            raise SurfaceQueryError(f"surface query refused: {response.message}")
        signed_distance = np.asarray(response.signed_distances, dtype=np.float64)
        distance_std = np.asarray(response.distance_std, dtype=np.float64)
        return SurfaceAnswer(stamp_ns_from_msg(response.header.stamp), response.estimate_step, response.degraded,
                             response.header.frame_id, _xyz(response.closest_points), signed_distance,
                             _xyz(response.normals),
                             None if distance_std.size < signed_distance.size else distance_std)
