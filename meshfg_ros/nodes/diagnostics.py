"""Counters of the estimator and simulation nodes and their diagnostic_msgs/DiagnosticArray.

The counters say what happened to the input (clouds received and rejected, and why; stamps
out of order or invalid; clock jumps; input far outside the scene or contradicted by the cloud,
core/input_checks.py) and to the steps (degraded, failed, non-finite, solve time and latency),
so that a robot's diagnostic aggregator shows why estimates are missing or poor.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from meshfg_ros.io.messages import RclpyMessageFactory, header_msg

_RCLPY = RclpyMessageFactory()


@dataclass
class EstimatorCounters:
    """What the estimator node has seen since it started (the values of its diagnostics)."""

    clouds_received: int = 0
    clouds_rejected_malformed: int = 0
    clouds_rejected_empty: int = 0
    clouds_rejected_frame: int = 0
    clouds_rejected_stamp: int = 0  # out of order, repeated or invalid (negative) stamps
    clouds_dropped_backlog: int = 0
    nan_points_dropped: int = 0
    clock_jumps_back: int = 0
    predictions_received: int = 0
    predictions_rejected: int = 0
    predictions_failed: int = 0  # the simulator reported it could not predict a stamp
    # Steps whose input the estimator set aside (the keys of core.input_checks.REJECTIONS).
    clouds_with_far_points: int = 0
    predictions_rejected_far: int = 0
    predictions_rejected_inverted: int = 0
    predictions_rejected_innovation: int = 0
    tool_poses_ignored_far: int = 0
    steps: int = 0
    degraded_steps: int = 0
    failed_steps: int = 0
    nonfinite_estimates: int = 0
    last_solve_time_ms: float = float("nan")
    last_latency_ms: float = float("nan")
    median_latency_ms: float = float("nan")

    @property
    def clouds_rejected(self) -> int:
        """Clouds that did not become a step, whatever the reason."""
        return (self.clouds_rejected_malformed + self.clouds_rejected_empty + self.clouds_rejected_frame
                + self.clouds_rejected_stamp + self.clouds_dropped_backlog)

    def values(self) -> dict[str, str]:
        """Counter name -> text value (the rejected total included)."""
        values = {name: _text(value) for name, value in asdict(self).items()}
        values["clouds_rejected"] = str(self.clouds_rejected)
        return values


@dataclass
class SimulatorCounters:
    """What the simulation node has seen since it started (the values of its diagnostics)."""

    tool_poses_received: int = 0
    tool_poses_rejected_malformed: int = 0
    tool_poses_rejected_frame: int = 0
    tool_poses_rejected_stamp: int = 0  # out of order, repeated or invalid (negative) stamps
    tool_poses_rejected_far: int = 0    # far outside the scene (core/input_checks.py)
    clock_jumps_back: int = 0
    predictions: int = 0
    predictions_failed: int = 0
    estimates_ignored: int = 0          # wrong vertex count, not finite, or far outside the scene

    @property
    def tool_poses_rejected(self) -> int:
        """Tool poses that were not predicted, whatever the reason."""
        return (self.tool_poses_rejected_malformed + self.tool_poses_rejected_frame + self.tool_poses_rejected_stamp
                + self.tool_poses_rejected_far)

    def values(self) -> dict[str, str]:
        """Counter name -> text value (the rejected total included)."""
        values = {name: _text(value) for name, value in asdict(self).items()}
        values["tool_poses_rejected"] = str(self.tool_poses_rejected)
        return values


def _text(value) -> str:
    if isinstance(value, float):
        return "n/a" if not np.isfinite(value) else f"{value:.3f}"
    return str(value)


def diagnostic_array(
    name: str, level: bytes, message: str, counters: EstimatorCounters | SimulatorCounters, stamp_ns: int
) -> DiagnosticArray:
    """DiagnosticArray with one status `name` (level: DiagnosticStatus.OK / WARN / ERROR)."""
    status = DiagnosticStatus(
        level=level, name=name, message=message, hardware_id="meshfg",
        values=[KeyValue(key=key, value=value) for key, value in counters.values().items()],
    )
    return DiagnosticArray(header=header_msg(stamp_ns, "", _RCLPY), status=[status])
