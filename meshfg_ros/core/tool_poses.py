"""Tool poses at any rate: a buffer that gives the pose at a cloud's stamp.

Position is interpolated linearly and rotation by slerp between the two buffered poses around
the stamp; past the newest pose it is extrapolated (constant velocity) within a bounded horizon
only. A pose is (7,): position xyz [m] and unit quaternion xyzw, as geometry_msgs/Pose.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

MAX_POSES = 1000  # the buffer keeps the newest poses only


class ToolPoseUnavailable(LookupError):
    """No tool pose can be given for a stamp; the message says why."""


class ToolPoseBuffer:
    """Stamped tool poses, interpolated at any stamp within their span (module docstring)."""

    def __init__(self, extrapolation_s: float = 0.1) -> None:
        self.extrapolation_ns = int(extrapolation_s * 1e9)
        self.clear()

    def clear(self) -> None:
        self._stamps = np.zeros(0, dtype=np.int64)
        self._poses = np.zeros((0, 7))

    def add(self, stamp_ns: int, pose: np.ndarray) -> None:
        """Insert a pose (any order; a repeated stamp replaces the pose it had)."""
        index = int(np.searchsorted(self._stamps, stamp_ns))
        pose = np.asarray(pose, dtype=np.float64)[None, :]
        if index < len(self._stamps) and self._stamps[index] == stamp_ns:
            self._poses[index] = pose
            return
        self._stamps = np.insert(self._stamps, index, stamp_ns)[-MAX_POSES:]
        self._poses = np.insert(self._poses, index, pose, axis=0)[-MAX_POSES:]

    def pose_at(self, stamp_ns: int) -> np.ndarray:
        """The pose (7,) at `stamp_ns`, or ToolPoseUnavailable."""
        stamps = self._stamps
        if not len(stamps):
            raise ToolPoseUnavailable("no tool pose received yet")
        if stamp_ns < stamps[0]:
            raise ToolPoseUnavailable(f"stamp {stamp_ns} ns is older than the oldest buffered tool pose "
                                      f"({stamps[0]} ns)")
        index = int(np.searchsorted(stamps, stamp_ns))
        if index < len(stamps) and stamps[index] == stamp_ns:
            return self._poses[index].copy()
        if index == len(stamps):
            ahead = stamp_ns - stamps[-1]
            if ahead > self.extrapolation_ns or len(stamps) < 2:
                raise ToolPoseUnavailable(f"no tool pose within {self.extrapolation_ns / 1e9:g} s before stamp "
                                          f"{stamp_ns} ns (the newest is {ahead / 1e9:.3f} s older)")
            index = len(stamps) - 1  # extrapolate along the last two poses
        return _between(self._poses[index - 1], self._poses[index], stamps[index - 1], stamps[index], stamp_ns)


def _between(first: np.ndarray, second: np.ndarray, first_ns: int, second_ns: int, stamp_ns: int) -> np.ndarray:
    """Linear position and slerp rotation at stamp_ns (fraction > 1: extrapolated)."""
    fraction = (stamp_ns - first_ns) / (second_ns - first_ns)
    position = first[:3] + fraction * (second[:3] - first[:3])
    rotations = Rotation.from_quat(np.stack([first[3:], second[3:]]))
    if fraction <= 1.0:
        rotation = Slerp([0.0, 1.0], rotations)([fraction])[0]
    else:
        step = rotations[0].inv() * rotations[1]
        rotation = rotations[0] * Rotation.from_rotvec(step.as_rotvec() * fraction)
    return np.concatenate([position, rotation.as_quat()])
