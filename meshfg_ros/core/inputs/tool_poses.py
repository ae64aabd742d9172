"""Tool poses at the stamps where they are needed, from a pose stream of any rate. ROS-free.

A robot reports its tool at its own rate (a dVRK arm at ~100 Hz to 1 kHz); the simulator needs
the tool where it was when a cloud was taken. `ToolPoseBuffer` keeps the stream (stamp_ns, pose
[x, y, z, qx, qy, qz, qw]) in stamp order, whatever order it arrives in, and `pose_at(stamp_ns)`
interpolates between the two neighbouring samples (position linear, rotation slerp).

Past the newest sample it extrapolates at the last two samples' constant velocity, but only up
to `extrapolation_horizon_s`. The default, 50 ms, covers a 20 Hz pose stream (one period) plus
its transport delay, while the guess stays below the clouds' noise: a tool moving 5 cm/s that
accelerates at 0.5 m/s^2 drifts 0.5 a t^2 = 0.6 mm from a constant-velocity guess in 50 ms
(2.5 mm in 100 ms). A gap longer than that is a stalled stream, reported rather than guessed.

A pose that cannot be given raises PoseUnavailable with a `reason` (EMPTY, BEFORE_FIRST,
BEYOND_HORIZON) that the buffer also counts in `unavailable`, for diagnostics. Memory is bounded:
`buffer_duration_s` of history and at most `max_samples`. A stamp older than the kept window is
dropped (insert returns False); after a jump back of the clock (a looped recording, a restarted
robot) the caller calls `clear()`.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from meshfg_ros.core.inputs.input_checks import NS_PER_S
from meshfg_ros.core.inputs.pose_history import OutsideHistory, PoseHistory, ReasonedLookupError, seconds

__all__ = ["DEFAULT_EXTRAPOLATION_HORIZON_S", "PoseUnavailable", "ToolPoseBuffer"]

DEFAULT_EXTRAPOLATION_HORIZON_S = 0.05
# Clouds may arrive seconds after the poses of their stamp (a slow segmentation): keep 5 s.
DEFAULT_BUFFER_DURATION_S = 5.0
DEFAULT_MAX_SAMPLES = 10_000  # 5 s at 2 kHz


class PoseUnavailable(ReasonedLookupError):
    """No tool pose at the asked stamp; `reason` says which case, the message why."""

    EMPTY = "empty"
    BEFORE_FIRST = "before_first"
    BEYOND_HORIZON = "beyond_horizon"


class ToolPoseBuffer:
    """Buffered tool poses, interpolated (and briefly extrapolated) to any stamp (module doc)."""

    def __init__(self, extrapolation_horizon_s: float = DEFAULT_EXTRAPOLATION_HORIZON_S,
                 buffer_duration_s: float = DEFAULT_BUFFER_DURATION_S, max_samples: int = DEFAULT_MAX_SAMPLES):
        if not extrapolation_horizon_s >= 0.0:
            raise ValueError(f"extrapolation_horizon_s must be >= 0, got {extrapolation_horizon_s}")
        if not buffer_duration_s > 0.0:
            raise ValueError(f"buffer_duration_s must be > 0, got {buffer_duration_s}")
        self.extrapolation_horizon_ns = round(extrapolation_horizon_s * NS_PER_S)
        self._history = PoseHistory(round(buffer_duration_s * NS_PER_S), max_samples)
        self.unavailable: Counter[str] = Counter()  # PoseUnavailable.reason -> how often

    def __len__(self) -> int:
        return len(self._history)

    @property
    def newest_ns(self) -> int | None:
        return self._history.newest_ns

    def insert(self, stamp_ns: int, pose) -> bool:
        """Add a pose (7 values); False when its stamp is older than the kept window (dropped)."""
        return self._history.insert(stamp_ns, pose)

    def clear(self) -> None:
        """Forget every pose (the clock jumped back); the counters stay."""
        self._history.clear()

    def pose_at(self, stamp_ns: int) -> np.ndarray:
        """(7,) float64 pose at `stamp_ns`, or PoseUnavailable (counted in `unavailable`)."""
        stamp, history = int(stamp_ns), self._history
        try:
            return history.pose_at(stamp, self.extrapolation_horizon_ns)
        except OutsideHistory as outside:
            if outside.reason == OutsideHistory.EMPTY:
                reason, message = PoseUnavailable.EMPTY, f"no tool pose received yet (asked at {seconds(stamp)})"
            elif outside.reason == OutsideHistory.TOO_OLD:
                reason, message = PoseUnavailable.BEFORE_FIRST, (
                    f"tool pose asked at {seconds(stamp)}, before the first buffered one "
                    f"({seconds(history.oldest_ns)})")
            else:
                reason, message = PoseUnavailable.BEYOND_HORIZON, (
                    f"tool pose asked at {seconds(stamp)}, {outside.ahead_ns / 1e6:.3g} ms beyond the newest "
                    f"({seconds(history.newest_ns)}): more than the extrapolation horizon "
                    f"{self.extrapolation_horizon_ns / 1e6:.3g} ms")
        self.unavailable[reason] += 1
        raise PoseUnavailable(reason, message)
