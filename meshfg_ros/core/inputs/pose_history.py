"""Bounded, time-sorted history of one rigid pose, interpolated the way tf2 does. ROS-free.

A pose is 7 float64 in the project's (and ROS') order: translation x, y, z, then the unit
quaternion qx, qy, qz, qw. `PoseHistory` keeps the samples of one moving thing (a tool, the
child frame of one /tf edge) sorted by their integer-nanosecond stamps, whatever order they
arrive in, and answers the pose at any stamp between its oldest and newest sample:
translation linear, rotation spherical-linear (slerp), between the two neighbours, as tf2's
buffer does. Past the newest sample it continues the last two samples' motion (constant linear
and angular velocity); how far a caller lets it do so is the caller's extrapolation horizon
(`core.inputs.frames`, `core.inputs.tool_poses`). Memory is bounded twice: samples older than the newest by
more than `duration_ns` are dropped, and so are the oldest beyond `max_samples`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from meshfg_ros.core.inputs.input_checks import NS_PER_S, StampError, check_stamp

__all__ = ["InvalidPoseError", "OutsideHistory", "PoseHistory", "ReasonedLookupError", "as_pose", "as_stamp", "pose_matrix", "seconds"]

_INITIAL_CAPACITY = 64


class InvalidPoseError(ValueError):
    """A pose that is not 7 finite values with a non-zero quaternion, or a stamp that is not an
    integer number of nanoseconds in [0, 2**63)."""


class OutsideHistory(LookupError):
    """A stamp `PoseHistory.pose_at` cannot answer: `reason` EMPTY, TOO_OLD (before the oldest
    sample) or BEYOND_HORIZON (`ahead_ns` past the newest, more than the caller's horizon)."""

    EMPTY = "empty"
    TOO_OLD = "too_old"
    BEYOND_HORIZON = "beyond_horizon"

    def __init__(self, reason: str, ahead_ns: int = 0):
        self.reason, self.ahead_ns = reason, ahead_ns
        super().__init__(reason)


class ReasonedLookupError(LookupError):
    """A lookup of the pose buffers that fails for one of its class's named reasons: `reason`
    says which (for counters and diagnostics), the message why."""

    def __init__(self, reason: str, message: str):
        self.reason = reason
        super().__init__(message)


def seconds(stamp_ns: int) -> str:
    """A stamp for messages: '12.345678 s'."""
    return f"{stamp_ns / NS_PER_S:.6f} s"


def as_pose(pose) -> np.ndarray:
    """`pose` as (7,) float64 [x, y, z, qx, qy, qz, qw] with a unit quaternion, or InvalidPoseError."""
    values = np.array(pose, dtype=np.float64).reshape(-1)
    if values.shape != (7,):
        raise InvalidPoseError(f"a pose is 7 values [x, y, z, qx, qy, qz, qw], got {values.size}")
    if not np.isfinite(values).all():
        raise InvalidPoseError("pose has non-finite values")
    norm = np.linalg.norm(values[3:])
    if norm < 1e-9:
        raise InvalidPoseError("pose quaternion has zero norm")
    values[3:] /= norm
    return values


def pose_matrix(poses: np.ndarray) -> np.ndarray:
    """Homogeneous matrices (..., 4, 4) float64 of poses (..., 7): x' = R x + t."""
    poses = np.asarray(poses, dtype=np.float64)
    flat = poses.reshape(-1, 7)
    matrices = np.zeros((flat.shape[0], 4, 4))
    matrices[:, :3, :3] = Rotation.from_quat(flat[:, 3:]).as_matrix()
    matrices[:, :3, 3] = flat[:, :3]
    matrices[:, 3, 3] = 1.0
    return matrices.reshape(*poses.shape[:-1], 4, 4)


def as_stamp(stamp_ns) -> int:
    """`stamp_ns` as an int in [0, 2**63) (the project's stamp rule, core.inputs.input_checks), or InvalidPoseError."""
    try:
        return check_stamp(stamp_ns)
    except StampError as error:
        raise InvalidPoseError(str(error)) from None


class PoseHistory:
    """Samples (stamp_ns, pose) of one rigid pose, sorted by stamp, bounded in time and count.

    Storage is a pair of arrays with room to grow; samples live in [start, end). Appending in
    stamp order (the usual case) is amortised O(1); an out-of-order sample is inserted in place.
    """

    def __init__(self, duration_ns: int, max_samples: int):
        if duration_ns < 0:
            raise ValueError(f"duration_ns must be >= 0, got {duration_ns}")
        if max_samples < 2:
            raise ValueError(f"max_samples must be >= 2 (interpolation needs two), got {max_samples}")
        self.duration_ns = int(duration_ns)
        self.max_samples = int(max_samples)
        self.clear()

    def clear(self) -> None:
        """Forget every sample (a jump back in time: a new timeline starts)."""
        self._stamps = np.zeros(_INITIAL_CAPACITY, dtype=np.int64)
        self._poses = np.zeros((_INITIAL_CAPACITY, 7))
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    @property
    def stamps_ns(self) -> np.ndarray:
        """Stamps (n,) int64 of the kept samples, ascending (a read-only view)."""
        view = self._stamps[self._start:self._end]
        view.flags.writeable = False
        return view

    @property
    def poses(self) -> np.ndarray:
        """Poses (n, 7) of the kept samples, in stamp order (a read-only view)."""
        view = self._poses[self._start:self._end]
        view.flags.writeable = False
        return view

    @property
    def oldest_ns(self) -> int | None:
        return int(self._stamps[self._start]) if len(self) else None

    @property
    def newest_ns(self) -> int | None:
        return int(self._stamps[self._end - 1]) if len(self) else None

    def insert(self, stamp_ns: int, pose) -> bool:
        """Add a sample; a sample at a kept stamp replaces it. Returns False (and keeps nothing)
        when the stamp is older than the kept window (newest - duration_ns)."""
        stamp = as_stamp(stamp_ns)
        pose = as_pose(pose)
        newest = self.newest_ns
        if newest is not None and stamp < newest - self.duration_ns:
            return False
        if newest is None or stamp > newest:
            self._append(stamp, pose)
            self._drop_old()
            return True
        position = self._start + int(np.searchsorted(self.stamps_ns, stamp))
        if self._stamps[position] == stamp:
            self._poses[position] = pose
            return True
        self._make_room()
        position = self._start + int(np.searchsorted(self.stamps_ns, stamp))
        self._stamps[position + 1:self._end + 1] = self._stamps[position:self._end].copy()
        self._poses[position + 1:self._end + 1] = self._poses[position:self._end].copy()
        self._stamps[position], self._poses[position] = stamp, pose
        self._end += 1
        self._drop_old()
        return True

    def _append(self, stamp: int, pose: np.ndarray) -> None:
        self._make_room()
        self._stamps[self._end], self._poses[self._end] = stamp, pose
        self._end += 1

    def _make_room(self) -> None:
        """Ensure one free slot after `end`: compact to the front, doubling capacity if needed."""
        if self._end < self._stamps.size:
            return
        count = len(self)
        capacity = self._stamps.size if count < self._stamps.size // 2 else 2 * self._stamps.size
        stamps, poses = np.zeros(capacity, dtype=np.int64), np.zeros((capacity, 7))
        stamps[:count], poses[:count] = self._stamps[self._start:self._end], self._poses[self._start:self._end]
        self._stamps, self._poses, self._start, self._end = stamps, poses, 0, count

    def _drop_old(self) -> None:
        cutoff = int(self._stamps[self._end - 1]) - self.duration_ns
        self._start += int(np.searchsorted(self.stamps_ns, cutoff))
        self._start = max(self._start, self._end - self.max_samples)

    def pose_at(self, stamp_ns: int, horizon_ns: int) -> np.ndarray:
        """(7,) pose at `stamp_ns`: interpolated between the oldest and the newest sample, continued
        at most `horizon_ns` past the newest; otherwise OutsideHistory with the reason."""
        if not len(self):
            raise OutsideHistory(OutsideHistory.EMPTY)
        if stamp_ns < self.oldest_ns:
            raise OutsideHistory(OutsideHistory.TOO_OLD)
        ahead = stamp_ns - self.newest_ns
        if ahead > horizon_ns:
            raise OutsideHistory(OutsideHistory.BEYOND_HORIZON, ahead)
        return self.interpolate(stamp_ns)[0]

    def interpolate(self, stamps_ns) -> np.ndarray:
        """Poses (m, 7) at stamps (m,) (ns), from the two neighbouring samples of each stamp.

        The caller keeps stamps within [oldest, newest + its horizon]: before the oldest sample
        this would extrapolate backwards. With one sample, that sample is the pose everywhere.
        Beyond the newest, the last two samples' motion continues (constant velocity).
        A stamp that is a sample's gets that sample as stored, whatever came after it: at the
        newest sample the formula runs from the one before with fraction 1, which rounds
        differently from the fraction-0 path it takes once a later sample has arrived, and a live
        node that looks up a cloud's stamp before or after the next /tf sample arrives must see
        the same pose (the replay assumes the arrival order of the recording).
        """
        count = len(self)
        if count == 0:
            raise LookupError("the pose history is empty")
        queries = np.atleast_1d(np.asarray(stamps_ns, dtype=np.int64))
        if count == 1:
            return np.repeat(self._poses[self._start][None, :], queries.size, axis=0)
        stamps, poses = self.stamps_ns, self.poses
        at_or_before = np.searchsorted(stamps, queries, side="right") - 1
        before = np.clip(at_or_before, 0, count - 2)
        after = before + 1
        # Integer differences first: exact for stamps far from the epoch, then one division.
        fraction = (queries - stamps[before]).astype(np.float64) / (stamps[after] - stamps[before]).astype(np.float64)
        translation = poses[before, :3] + fraction[:, None] * (poses[after, :3] - poses[before, :3])
        start = Rotation.from_quat(poses[before, 3:])
        step = (start.inv() * Rotation.from_quat(poses[after, 3:])).as_rotvec()
        rotation = start * Rotation.from_rotvec(fraction[:, None] * step)
        result = np.concatenate([translation, rotation.as_quat(canonical=False)], axis=1)
        exact = (at_or_before >= 0) & (stamps[np.maximum(at_or_before, 0)] == queries)
        result[exact] = poses[at_or_before[exact]]
        return result
