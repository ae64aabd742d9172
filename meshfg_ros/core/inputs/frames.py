"""Transform buffer for the robot's frame tree (/tf and /tf_static), without ROS.

The nodes feed it every transform they receive (`set_transform`, static or not) and ask it
where a frame is at a stamp: `lookup(target_frame, source_frame, stamp_ns)` returns the 4x4
float64 matrix that maps points given in `source_frame` into `target_frame` (tf2's
lookupTransform), chaining through the tree (world -> ecm -> endoscope_optical_frame, world ->
psm1_base -> psm1_tool, ...). Each frame has one parent; a transform (parent, child) gives the
child's pose in the parent. Between two stamps of an edge the translation is interpolated
linearly and the rotation by slerp, as tf2 does; static edges hold at every stamp.

History is bounded: each edge keeps the last `buffer_duration_s` seconds (tf2's cache time) and
at most `max_samples_per_edge` samples. A sample older than its edge's newest by more than
`jump_back_s` is a jump back in time (a looped recording, a reset clock): the edge's history
restarts from it, as tf2_ros clears its buffer when the clock jumps back, instead of mixing two
timelines or refusing the new one until its stamps catch up; later samples that are less late
are inserted in stamp order. A lookup that cannot be answered raises
FrameLookupError with a one-line message and a `reason`: an unknown frame, frames in two
separate trees, a stamp older than an edge's history, or a stamp beyond its newest transform by
more than `extrapolation_horizon_s` (0 by default, as tf2: never guess ahead).

Why not pytransform3d's TemporalTransformManager (evaluated, 3.17.0): its
NumpyTimeseriesTransform interpolates by screw motion (ScLERP), whose translation is not the
linear one tf2 and every other ROS consumer of /tf compute; it holds immutable arrays, so a
rolling history re-adds the edge per message, and each add recomputes the graph's all-pairs
shortest paths; and out of range it either raises a generic ValueError or clamps without
bound. The tree walk below (tf2's own algorithm) and scipy's rotations cover what is needed.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from meshfg_ros.core.inputs.input_checks import DEFAULT_CLOCK_JUMP_THRESHOLD_S, JUMP_BACK, NS_PER_S, stamp_order
from meshfg_ros.core.inputs.pose_history import (
    InvalidPoseError,
    OutsideHistory,
    PoseHistory,
    ReasonedLookupError,
    as_pose,
    as_stamp,
    pose_matrix,
    seconds,
)

__all__ = [
    "DEFAULT_BUFFER_DURATION_S",
    "FrameLookupError",
    "InvalidTransformError",
    "StampedTransform",
    "TransformBuffer",
    "transform_points",
]

DEFAULT_BUFFER_DURATION_S = 10.0  # tf2's default cache time
# Per edge: 10 s of a 1 kHz /tf stream (a robot arm's joint states), 0.6 MB.
DEFAULT_MAX_SAMPLES_PER_EDGE = 10_000


class InvalidTransformError(InvalidPoseError):
    """A transform that cannot enter the tree: bad values, an empty or self-referencing frame
    name, or a parent that would close a loop."""


class FrameLookupError(ReasonedLookupError):
    """A lookup the buffer cannot answer; `reason` says which case, the message why."""

    UNKNOWN_FRAME = "unknown_frame"
    NO_PATH = "no_path"
    TOO_OLD = "too_old"
    BEYOND_HORIZON = "beyond_horizon"


@dataclass(frozen=True, eq=False)
class StampedTransform:
    """The pose of `child` in `parent` at `stamp_ns`: translation (3,) and quaternion xyzw (4,)."""

    parent: str
    child: str
    stamp_ns: int
    translation: np.ndarray
    rotation: np.ndarray

    @property
    def pose(self) -> np.ndarray:
        """(7,) [x, y, z, qx, qy, qz, qw]."""
        return np.concatenate([np.asarray(self.translation, dtype=np.float64).reshape(3),
                               np.asarray(self.rotation, dtype=np.float64).reshape(4)])


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (K, 3) mapped by a 4x4 rigid transform: one matrix product for the whole cloud."""
    points = np.asarray(points, dtype=np.float64)
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _milliseconds(duration_ns: int) -> str:
    return f"{duration_ns / 1e6:.3g} ms"


class _Edge:
    """A child's link to its parent: one static pose, or a history of stamped poses."""

    def __init__(self, parent: str, static_pose: np.ndarray | None, history: PoseHistory | None):
        self.parent = parent
        self.static_matrix = None if static_pose is None else pose_matrix(static_pose)
        self.history = history


class TransformBuffer:
    """Static and time-stamped transforms of a frame tree; lookups at a stamp (module doc)."""

    def __init__(self, buffer_duration_s: float = DEFAULT_BUFFER_DURATION_S,
                 extrapolation_horizon_s: float = 0.0,
                 max_samples_per_edge: int = DEFAULT_MAX_SAMPLES_PER_EDGE,
                 jump_back_s: float = DEFAULT_CLOCK_JUMP_THRESHOLD_S):
        if not buffer_duration_s > 0.0:
            raise ValueError(f"buffer_duration_s must be > 0, got {buffer_duration_s}")
        if not extrapolation_horizon_s >= 0.0:
            raise ValueError(f"extrapolation_horizon_s must be >= 0, got {extrapolation_horizon_s}")
        if not jump_back_s >= 0.0:
            raise ValueError(f"jump_back_s must be >= 0, got {jump_back_s}")
        self.buffer_duration_ns = round(buffer_duration_s * NS_PER_S)
        self.jump_back_ns = round(jump_back_s * NS_PER_S)
        self.extrapolation_horizon_ns = round(extrapolation_horizon_s * NS_PER_S)
        self.max_samples_per_edge = int(max_samples_per_edge)
        self._edges: dict[str, _Edge] = {}  # by child frame

    @property
    def frames(self) -> frozenset[str]:
        """Every frame named by a transform so far (children and parents)."""
        return frozenset(self._edges) | {edge.parent for edge in self._edges.values()}

    def set_transforms(self, transforms: Iterable[StampedTransform], static: bool = False) -> list[str]:
        """set_transform for each of a /tf (or /tf_static, static=True) message's transforms; a
        transform that cannot enter the tree is skipped, the others kept. Returns why each skipped
        one was (one line each)."""
        refused = []
        for transform in transforms:
            try:
                self.set_transform(transform, static)
            except InvalidTransformError as error:
                refused.append(str(error))
        return refused

    def set_transform(self, transform: StampedTransform, static: bool = False) -> bool:
        """Add `transform` to the tree. Static: replaces the edge, valid at every stamp. Dynamic:
        one more sample of the edge's history (which restarts from it after a jump back in time,
        module doc); False when it is older than the kept window.

        A child that gets a different parent (or changes between static and dynamic) starts a new
        edge: its earlier samples are dropped. Raises InvalidTransformError for bad values and
        for loops.
        """
        parent, child = str(transform.parent).strip("/"), str(transform.child).strip("/")
        if not parent or not child or parent == child:
            raise InvalidTransformError(f"transform needs two different, non-empty frame names, "
                                        f"got parent {transform.parent!r} child {transform.child!r}")
        try:
            pose = as_pose(transform.pose)
            stamp = None if static else as_stamp(transform.stamp_ns)
        except InvalidPoseError as error:
            raise InvalidTransformError(f"transform {parent!r} -> {child!r}: {error}") from None
        ancestor = parent
        while ancestor in self._edges:
            ancestor = self._edges[ancestor].parent
            if ancestor == child:
                raise InvalidTransformError(f"transform {parent!r} -> {child!r} would close a loop: "
                                            f"{parent!r} descends from {child!r}")
        edge = self._edges.get(child)
        if static:
            self._edges[child] = _Edge(parent, pose, None)
            return True
        jumped_back = (edge is not None and edge.history is not None
                       and stamp_order(edge.history.newest_ns, stamp, self.jump_back_ns) == JUMP_BACK)
        if edge is None or edge.parent != parent or edge.history is None or jumped_back:
            edge = _Edge(parent, None, PoseHistory(self.buffer_duration_ns, self.max_samples_per_edge))
            self._edges[child] = edge
        return edge.history.insert(stamp, pose)

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int) -> np.ndarray:
        """4x4 float64 matrix mapping points in `source_frame` to `target_frame` at `stamp_ns`."""
        target_chain, source_chain, common = self._paths(target_frame, source_frame)
        root_from_source = self._pose_in_ancestor(source_chain, common, int(stamp_ns))
        root_from_target = self._pose_in_ancestor(target_chain, common, int(stamp_ns))
        return _rigid_inverse(root_from_target) @ root_from_source

    def newest_stamp(self, target_frame: str, source_frame: str) -> int | None:
        """The newest stamp `lookup(target_frame, source_frame, stamp)` answers without
        extrapolating: the oldest of the newest samples of the time-stamped transforms between
        the two frames (tf2's latest common time, what its lookups at time zero use); None when
        only static transforms join them (any stamp). FrameLookupError as `lookup`."""
        target_chain, source_chain, common = self._paths(target_frame, source_frame)
        path = target_chain[:target_chain.index(common)] + source_chain[:source_chain.index(common)]
        newest = [self._edges[child].history.newest_ns for child in path if self._edges[child].history is not None]
        return min(newest) if newest else None

    def _paths(self, target_frame: str, source_frame: str) -> tuple[list[str], list[str], str]:
        """The chains of the two frames to their root, and their nearest common frame, or
        FrameLookupError (an unknown frame, separate trees)."""
        target, source = target_frame.strip("/"), source_frame.strip("/")
        known = self.frames
        for frame in (target, source):
            if frame not in known:
                listed = ", ".join(sorted(known)) or "none yet"
                raise FrameLookupError(FrameLookupError.UNKNOWN_FRAME,
                                       f"unknown frame {frame!r} (known frames: {listed})")
        target_chain, source_chain = self._chain_to_root(target), self._chain_to_root(source)
        if target_chain[-1] != source_chain[-1]:
            raise FrameLookupError(
                FrameLookupError.NO_PATH,
                f"no path between {target!r} and {source!r}: they are in separate trees, rooted at "
                f"{target_chain[-1]!r} and {source_chain[-1]!r}")
        target_ancestors = set(target_chain)
        return target_chain, source_chain, next(frame for frame in source_chain if frame in target_ancestors)

    def transform_points(self, points: np.ndarray, target_frame: str, source_frame: str,
                         stamp_ns: int) -> np.ndarray:
        """Points (K, 3) given in `source_frame` at `stamp_ns`, expressed in `target_frame`."""
        return transform_points(self.lookup(target_frame, source_frame, stamp_ns), points)

    def _chain_to_root(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self._edges:
            chain.append(self._edges[chain[-1]].parent)
        return chain

    def _pose_in_ancestor(self, chain: list[str], ancestor: str, stamp_ns: int) -> np.ndarray:
        """Pose (4x4) of chain[0] in `ancestor`, a frame of its chain to the root."""
        matrix = np.eye(4)
        for child in chain[:chain.index(ancestor)]:
            matrix = self._edge_matrix(child, stamp_ns) @ matrix
        return matrix

    def _edge_matrix(self, child: str, stamp_ns: int) -> np.ndarray:
        edge = self._edges[child]
        if edge.static_matrix is not None:
            return edge.static_matrix
        history, name = edge.history, f"{edge.parent!r} -> {child!r}"
        try:
            return pose_matrix(history.pose_at(stamp_ns, self.extrapolation_horizon_ns))
        except OutsideHistory as outside:
            if outside.reason == OutsideHistory.TOO_OLD:
                raise FrameLookupError(
                    FrameLookupError.TOO_OLD,
                    f"stamp {seconds(stamp_ns)} is older than the buffered transforms {name} "
                    f"({seconds(history.oldest_ns)} to {seconds(history.newest_ns)}; "
                    f"buffer {self.buffer_duration_ns / NS_PER_S:g} s)") from None
            raise FrameLookupError(
                FrameLookupError.BEYOND_HORIZON,
                f"stamp {seconds(stamp_ns)} is {_milliseconds(outside.ahead_ns)} beyond the newest transform {name} "
                f"({seconds(history.newest_ns)}), more than the extrapolation horizon "
                f"{_milliseconds(self.extrapolation_horizon_ns)}") from None


def _rigid_inverse(matrix: np.ndarray) -> np.ndarray:
    inverse = np.eye(4)
    inverse[:3, :3] = matrix[:3, :3].T
    inverse[:3, 3] = -matrix[:3, :3].T @ matrix[:3, 3]
    return inverse
