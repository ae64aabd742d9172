"""Counters and health of the estimator and simulation nodes, as diagnostic_msgs/DiagnosticArray.

The counters say what happened to the input (clouds received and rejected, and why; stamps
out of order or invalid; clock jumps; input far outside the scene or contradicted by the cloud,
core/inputs/input_checks.py) and to the steps (degraded, failed, non-finite, points gated out, the time
of each stage), so that a robot's diagnostic aggregator shows why estimates are missing or poor.
`EstimatorHealth` turns them into a level and a one-line reason (the README's "Wire it to your
robot" lists them): it is OK only while recent steps are estimated from most of their points,
with a prediction, converged, and in time. `SimulatorHealth` does the same for the simulation
node: OK only while it has its mesh and tool poses, uses what it receives, and its newest
prediction succeeded; `BridgeServerHealth` for sim_bridge_server: OK only while it has its mesh
and takes the tool poses and cuts it receives, and its steps succeed.
"""

from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from meshfg_ros.core.inputs.camera_check import GRAZING_LIMIT_DEGREES, IMPLAUSIBLE_SHARE
from meshfg_ros.core.inputs.input_checks import rejections_in
from meshfg_ros.core.estimation.weights import NOISE_BOUNDS
from meshfg_ros.io.messages import RclpyMessageFactory, header_msg

_RCLPY = RclpyMessageFactory()


class Counters:
    """Base of a node's counters (a dataclass of them): the values of its diagnostics."""

    def count(self, counter: str) -> None:
        """One more of `counter` (a field name)."""
        setattr(self, counter, getattr(self, counter) + 1)

    def values(self) -> dict[str, str]:
        """Counter name -> text value."""
        return {name: _text(value) for name, value in asdict(self).items()}


@dataclass
class EstimatorCounters(Counters):
    """What the estimator node has seen since it started (the values of its diagnostics)."""

    clouds_received: int = 0
    clouds_rejected_malformed: int = 0
    clouds_rejected_empty: int = 0
    clouds_rejected_frame: int = 0
    clouds_rejected_stamp: int = 0  # out of order, repeated or invalid (negative) stamps
    clouds_rejected_registration: int = 0  # the mesh and the cloud differ in size or place
    clouds_dropped_backlog: int = 0
    clouds_skipped_behind: int = 0  # superseded by a newer cloud while the pipeline was behind (core/scheduler.py)
    nan_points_dropped: int = 0
    clock_jumps_back: int = 0
    predictions_received: int = 0
    predictions_rejected: int = 0
    predictions_failed: int = 0  # the simulator reported it could not predict a stamp
    # Steps whose input the estimator set aside (the keys of core.inputs.input_checks.REJECTIONS).
    clouds_with_far_points: int = 0
    predictions_rejected_far: int = 0
    predictions_rejected_inverted: int = 0
    predictions_rejected_innovation: int = 0
    tool_poses_ignored_far: int = 0
    inputs_held_before_mesh: int = 0    # clouds and tool poses kept until the mesh came
    inputs_dropped_before_mesh: int = 0  # the oldest of those, beyond what is kept (nodes/held_inputs.py)
    initial_meshes_rejected: int = 0     # initial_mesh messages refused (malformed, another frame, unusable)
    # prediction_source sim_bridge (nodes/sim_bridge_client.py, core/physics/external_prior.py): calls made,
    # answers missing or refused (the step runs without a prediction), stiffness repaired or refused.
    sim_bridge_calls: int = 0
    sim_bridge_unavailable: int = 0
    sim_bridge_busy: int = 0
    sim_bridge_late: int = 0
    sim_bridge_rejected_malformed: int = 0
    sim_bridge_rejected_mesh: int = 0
    sim_bridge_rejected_frame: int = 0
    sim_bridge_stiffness_repaired: int = 0
    sim_bridge_stiffness_rejected: int = 0
    steps: int = 0
    degraded_steps: int = 0
    # a stalled tool stream's clouds run again with the simulator's catch-up predictions, their
    # estimates sent on catch_up_estimate for it to learn from (core/scheduler.py)
    clouds_run_again: int = 0
    failed_steps: int = 0
    nonfinite_estimates: int = 0
    unconverged_steps: int = 0
    steps_noise_off_nominal: int = 0    # the cloud spread beyond NOISE_BOUNDS x measurement_sigma about the estimate
    steps_view_implausible: int = 0     # over IMPLAUSIBLE_SHARE of the cloud at angles camera_frame cannot see
    points_used: int = 0
    points_set_aside: int = 0           # on the tool, far, non-finite or gated out
    queued_clouds: int = 0              # waiting for a prediction or the solver
    last_wait_ms: float = float("nan")  # stage times of the last step: arrival to solver start,
    last_solve_time_ms: float = float("nan")  # the update itself,
    last_publish_ms: float = float("nan")     # and publishing its outputs
    last_latency_ms: float = float("nan")     # arrival of the cloud to its estimate published
    median_latency_ms: float = float("nan")

    def record_step(self, result, wait_ms: float, publish_ms: float, latencies_ms: list[float]) -> None:
        """Count a published step (a core.estimation.estimator.StepResult) and its stage times."""
        self.steps += 1
        self.degraded_steps += int(result.degraded)
        self.unconverged_steps += int(not result.converged)
        self.steps_noise_off_nominal += int(result.noise_off_nominal)
        self.points_used += result.num_points
        self.points_set_aside += result.num_points_rejected
        for counter in rejections_in(result.message):
            self.count(counter)
        self.last_wait_ms, self.last_solve_time_ms, self.last_publish_ms = wait_ms, float(result.solve_time_ms), publish_ms
        self.last_latency_ms, self.median_latency_ms = latencies_ms[-1], float(np.median(latencies_ms))

    # The counters of clouds that did not become a step, whatever the reason.
    CLOUD_REJECTIONS = ("clouds_rejected_malformed", "clouds_rejected_empty", "clouds_rejected_frame",
                        "clouds_rejected_stamp", "clouds_rejected_registration", "clouds_dropped_backlog",
                        "clouds_skipped_behind")

    @property
    def clouds_rejected(self) -> int:
        """Clouds that did not become a step, whatever the reason."""
        return sum(getattr(self, counter) for counter in self.CLOUD_REJECTIONS)

    def values(self) -> dict[str, str]:
        """Counter name -> text value (the rejected total included)."""
        values = super().values()
        values["clouds_rejected"] = str(self.clouds_rejected)
        return values


@dataclass
class SimulatorCounters(Counters):
    """What the simulation node has seen since it started (the values of its diagnostics)."""

    tool_poses_received: int = 0
    tool_poses_rejected_malformed: int = 0
    tool_poses_rejected_frame: int = 0
    tool_poses_rejected_stamp: int = 0  # out of order, repeated or invalid (negative) stamps
    tool_poses_rejected_far: int = 0    # far outside the scene (core/inputs/input_checks.py)
    clock_jumps_back: int = 0
    requests: int = 0                   # prediction requests (one per accepted cloud)
    predictions: int = 0
    catch_up_predictions: int = 0       # of them, for a stalled tool stream's stamps once poses came (core/scheduler.py)
    catch_up_estimates_learnt: int = 0  # the estimates of those stamps' clouds run again, learnt from
    predictions_failed: int = 0
    predictions_superseded: int = 0     # requests skipped for a newer cloud's while behind (core/scheduler.py)
    estimates_ignored: int = 0          # wrong vertex count, not finite, or far outside the scene
    estimate_std_ignored: int = 0       # an estimate's position_std malformed (count, NaN, < 0): not learnt from
    elements_removed: int = 0           # element slots cut away so far (blade or remove_elements; core/geometry/topology.py)
    cuts_rejected: int = 0              # remove_elements requests or blade cuts the simulator could not take
    inputs_held_before_mesh: int = 0    # tool poses, requests and estimates kept until the mesh came
    inputs_dropped_before_mesh: int = 0  # the oldest of those, beyond what is kept (nodes/held_inputs.py)
    initial_meshes_rejected: int = 0     # initial_mesh messages refused (malformed, another frame, unusable)
    last_prediction_ms: float = float("nan")
    # the unmodelled uniform body load the predictions apply, m/s^2 (core/physics/body_load.py; 0 when off)
    body_acceleration_x: float = 0.0
    body_acceleration_y: float = 0.0
    body_acceleration_z: float = 0.0
    # the Poisson ratio the predictions use (core/physics/poisson_ratio.py; NaN until a mesh is set)
    poisson_ratio: float = float("nan")
    # requests answered without a prediction for want of a tool pose, by reason (core/inputs/tool_poses.py)
    tool_pose_unavailable_empty: int = 0
    tool_pose_unavailable_before_first: int = 0
    tool_pose_unavailable_beyond_horizon: int = 0

    @property
    def tool_poses_rejected(self) -> int:
        """Tool poses that were not predicted, whatever the reason."""
        return (self.tool_poses_rejected_malformed + self.tool_poses_rejected_frame + self.tool_poses_rejected_stamp
                + self.tool_poses_rejected_far)

    def values(self) -> dict[str, str]:
        """Counter name -> text value (the rejected total included)."""
        values = super().values()
        values["tool_poses_rejected"] = str(self.tool_poses_rejected)
        return values


@dataclass
class BridgeServerCounters(Counters):
    """What sim_bridge_server has seen since it started (the values of its diagnostics)."""

    tool_poses_received: int = 0
    tool_poses_rejected_malformed: int = 0
    tool_poses_rejected_frame: int = 0        # not in world_frame: the server places nothing through /tf
    tool_poses_rejected_before_mesh: int = 0  # before mesh_file or initial_mesh gave the simulator its mesh
    initial_meshes_rejected: int = 0          # initial_mesh messages refused (malformed, another frame, unusable)
    tool_poses_stamped_back: int = 0          # before the previous pose: the tool put there without a step
    steps_failed: int = 0                     # simulation steps that raised: the state before them kept
    cuts_rejected: int = 0                    # remove_elements before the mesh or that the simulator could not take

    @property
    def tool_poses_rejected(self) -> int:
        """Tool poses that did not move the simulator, whatever the reason."""
        return (self.tool_poses_rejected_malformed + self.tool_poses_rejected_frame
                + self.tool_poses_rejected_before_mesh)

    def values(self) -> dict[str, str]:
        """Counter name -> text value (the rejected total included)."""
        values = super().values()
        values["tool_poses_rejected"] = str(self.tool_poses_rejected)
        return values


def waiting_for_mesh_message(counters: EstimatorCounters | SimulatorCounters, last_mesh_rejection: str = "") -> str:
    """What a node without its mesh says, with the inputs it holds until the mesh comes and the
    initial_mesh messages it refused (the newest one's reason: `last_mesh_rejection`)."""
    held, dropped = counters.inputs_held_before_mesh, counters.inputs_dropped_before_mesh
    message = "waiting for initial_mesh"
    if held:
        message += f"; {held} inputs held until it comes" + (f", {dropped} dropped" if dropped else "")
    return message + mesh_rejections_text(counters.initial_meshes_rejected, last_mesh_rejection)


def mesh_rejections_text(rejected: int, last_mesh_rejection: str) -> str:
    """The part of a waiting message that names the refused initial_mesh messages ("" for none)."""
    if not rejected:
        return ""
    return f"; {rejected} initial_mesh rejected" + (f", the last: {last_mesh_rejection}" if last_mesh_rejection else "")


def _text(value) -> str:
    if isinstance(value, float):
        return "n/a" if not np.isfinite(value) else f"{value:.3f}"
    return str(value)


def diagnostic_array(
    name: str, level: bytes, message: str, counters: Counters, stamp_ns: int
) -> DiagnosticArray:
    """DiagnosticArray with one status `name` (level: DiagnosticStatus.OK / WARN / ERROR)."""
    status = DiagnosticStatus(
        level=level, name=name, message=message, hardware_id="meshfg",
        values=[KeyValue(key=key, value=value) for key, value in counters.values().items()],
    )
    return DiagnosticArray(header=header_msg(stamp_ns, "", _RCLPY), status=[status])


def with_setup_problems(level: bytes, message: str, unmatched_publishers: list[str],
                        setup_warnings: list[str]) -> tuple[bytes, str]:
    """A node's (level, message) with what its wiring says first: an input publisher whose QoS
    cannot match (ERROR: nothing it sends arrives; nodes/publisher_qos.py), then a set-up warning
    (a parameters file that sets nothing: WARN), else the node's own."""
    if unmatched_publishers:
        more = len(unmatched_publishers) - 1
        return ERROR, unmatched_publishers[0] + (f" (and {more} more such publishers)" if more else "")
    if setup_warnings:
        return WARN, setup_warnings[0]
    return level, message


# Health thresholds: over the last HEALTH_WINDOW steps.
HEALTH_WINDOW = 10
MOSTLY = 0.5              # "most": more than this share
LAG_CLOUDS = 3            # queued clouds beyond which the estimator lags its input
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


class _StepOutcome(NamedTuple):
    degraded: bool
    converged: bool
    points_used: int
    points_set_aside: int
    noise_off_nominal: bool
    view_implausible: bool


class EstimatorHealth:
    """The estimator node's level and reason from its recent steps and counters (module docstring)."""

    def __init__(self, stalled_after_s: float) -> None:
        self.stalled_after_s = stalled_after_s
        self._recent: deque[_StepOutcome] = deque(maxlen=HEALTH_WINDOW)
        self._failed_seen = 0
        self._rejected_seen = 0
        self._stiffness_rejected_seen = 0
        # What went wrong with the newest prediction the sim_bridge service did not give (the fix
        # the degraded-steps warning names); "" with the simulation node.
        self.prediction_problem = ""
        self.last_mesh_rejection = ""  # why the newest initial_mesh was refused

    def record(self, degraded: bool, converged: bool, points_used: int, points_set_aside: int,
               noise_off_nominal: bool = False, view_implausible: bool = False) -> None:
        """One step's outcome (view_implausible: more than IMPLAUSIBLE_SHARE of its cloud at angles
        no camera at camera_frame's origin sees, core/inputs/camera_check.py)."""
        self._recent.append(_StepOutcome(degraded, converged, points_used, points_set_aside, noise_off_nominal,
                                         view_implausible))

    def assess(self, counters: EstimatorCounters, waiting_for_mesh: bool, unanswered_s: float,
               last_rejection: str = "") -> tuple[bytes, str]:
        """(level, reason). unanswered_s: how long clouds have arrived without an estimate (0: none);
        last_rejection: why the newest cloud set aside was (its log line)."""
        new_failures, self._failed_seen = counters.failed_steps - self._failed_seen, counters.failed_steps
        new_rejections, self._rejected_seen = counters.clouds_rejected - self._rejected_seen, counters.clouds_rejected
        new_stiffness_rejections = counters.sim_bridge_stiffness_rejected - self._stiffness_rejected_seen
        self._stiffness_rejected_seen = counters.sim_bridge_stiffness_rejected
        if waiting_for_mesh:
            if unanswered_s > self.stalled_after_s:
                return ERROR, (f"clouds arrive for {unanswered_s:.0f} s but there is no mesh: set mesh_file "
                               "or publish initial_mesh")
            return WARN, waiting_for_mesh_message(counters, self.last_mesh_rejection)
        if unanswered_s > self.stalled_after_s:
            if new_rejections or counters.steps == 0 and counters.clouds_rejected:
                why = f"every cloud is rejected; the last: {last_rejection}" if last_rejection else (
                    "every cloud is rejected")
            else:
                why = "the solver is stuck or every update fails"
            return ERROR, f"no estimate for the clouds of the last {unanswered_s:.0f} s: {why}"
        if counters.steps == 0 and counters.clouds_rejected:
            return WARN, (f"no estimate yet: {counters.clouds_rejected} clouds rejected"
                          + (f"; the last: {last_rejection}" if last_rejection else ""))
        if new_failures:
            return WARN, f"{new_failures} updates failed since the last report"
        if new_stiffness_rejections:
            return WARN, (f"{new_stiffness_rejections} of the simulator's stiffness matrices refused since the last "
                          f"report (the estimator's own stiffness used): {self.prediction_problem}")
        if counters.queued_clouds > LAG_CLOUDS:
            return WARN, (f"lagging: {counters.queued_clouds} clouds wait (median latency "
                          f"{counters.median_latency_ms:.0f} ms); lower the cloud rate or max_iterations")
        recent = list(self._recent)
        if recent:
            degraded = sum(step.degraded for step in recent)
            if degraded > MOSTLY * len(recent):
                return WARN, (f"{degraded} of the last {len(recent)} steps ran without a simulator prediction: "
                              + (self.prediction_problem or "check tool_pose stamps and frames and the simulation node"))
            used, set_aside = sum(step.points_used for step in recent), sum(step.points_set_aside for step in recent)
            if set_aside > MOSTLY * (used + set_aside):
                return WARN, (f"{set_aside} of {used + set_aside} points of the last {len(recent)} clouds were set "
                              "aside (tool, gate, far): check units, frames and the mesh registration")
            unconverged = sum(not step.converged for step in recent)
            if unconverged > MOSTLY * len(recent):
                return WARN, f"{unconverged} of the last {len(recent)} updates did not converge"
            off_nominal = sum(step.noise_off_nominal for step in recent)
            if off_nominal > MOSTLY * len(recent):
                return WARN, (f"in {off_nominal} of the last {len(recent)} updates the cloud spread more than "
                              f"{NOISE_BOUNDS:g}x above or below measurement_sigma about the estimate: check it and "
                              "its units")
            implausible = sum(step.view_implausible for step in recent)
            if implausible > MOSTLY * len(recent):
                return WARN, (f"in {implausible} of the last {len(recent)} clouds more than {100 * IMPLAUSIBLE_SHARE:g} % "
                              "of the points face away from camera_frame's origin or meet its rays beyond "
                              f"{GRAZING_LIMIT_DEGREES:g} degrees: it is not the depth camera's optical centre; check "
                              "camera_frame and its transform on /tf (or camera_pose)")
        if new_rejections:
            the_last = f"; the last: {last_rejection}" if last_rejection else ""
            return WARN, f"{new_rejections} clouds rejected since the last report{the_last}"
        if counters.steps == 0:
            return OK, "waiting for clouds"
        return OK, "estimating"


class SimulatorHealth:
    """The simulation node's level and reason from its counters and its newest answer (module docstring)."""

    def __init__(self) -> None:
        self._rejected_seen = 0
        self._ignored_seen = 0
        self._std_ignored_seen = 0
        self.last_failure: str | None = None  # why the newest answer gave no prediction; None: it gave one
        self.last_mesh_rejection = ""  # why the newest initial_mesh was refused

    def record(self, failure: str | None) -> None:
        """The newest answer: the reason it gave no prediction, or None for a prediction."""
        self.last_failure = failure

    def assess(self, counters: SimulatorCounters, waiting_for_mesh: bool) -> tuple[bytes, str]:
        """(level, reason): waiting for the mesh, requests without any tool pose, tool poses rejected,
        estimates or their std ignored since the last report, the newest prediction failed."""
        new_rejections, self._rejected_seen = counters.tool_poses_rejected - self._rejected_seen, counters.tool_poses_rejected
        new_ignored, self._ignored_seen = counters.estimates_ignored - self._ignored_seen, counters.estimates_ignored
        new_std_ignored = counters.estimate_std_ignored - self._std_ignored_seen
        self._std_ignored_seen = counters.estimate_std_ignored
        if waiting_for_mesh:
            return WARN, waiting_for_mesh_message(counters, self.last_mesh_rejection)
        if counters.requests and not counters.tool_poses_received:
            return WARN, (f"{counters.requests} prediction requests but no tool pose received: every step runs "
                          "without a prediction; publish tool_pose (geometry_msgs/PoseStamped) in this node's "
                          "namespace, with a QoS it matches")
        if new_rejections:
            return WARN, f"{new_rejections} tool poses rejected since the last report"
        if new_ignored:
            return WARN, f"{new_ignored} estimates ignored since the last report: predicting from the newest usable state"
        if new_std_ignored:
            return WARN, (f"{new_std_ignored} estimates' position_std malformed since the last report: the model is "
                          "not learnt from them")
        if self.last_failure is not None:
            return WARN, f"the last prediction failed: {self.last_failure}"
        return OK, "predicting"


class BridgeServerHealth:
    """sim_bridge_server's level and reason from its counters and its newest problem (module docstring)."""

    # What went wrong, by the counter (or total) that counts it, as the report names it.
    PROBLEMS = {"tool_poses_rejected": "tool poses rejected", "tool_poses_stamped_back": "tool poses stamped back",
                "steps_failed": "simulation steps failed", "cuts_rejected": "cuts rejected"}

    def __init__(self) -> None:
        self._seen = dict.fromkeys(self.PROBLEMS, 0)
        self.last_problem = ""  # the newest rejection or failure (its log line)
        self.last_mesh_rejection = ""  # why the newest initial_mesh was refused

    def assess(self, counters: BridgeServerCounters, waiting_for_mesh: bool) -> tuple[bytes, str]:
        """(level, reason): waiting for the mesh, then the tool poses rejected or stamped back, steps
        failed and cuts rejected since the last report with the newest reason, else whether tool
        poses come."""
        new = {problem: getattr(counters, problem) - seen for problem, seen in self._seen.items()}
        self._seen = {problem: getattr(counters, problem) for problem in self.PROBLEMS}
        if waiting_for_mesh:
            ignored, cuts = counters.tool_poses_rejected_before_mesh, counters.cuts_rejected
            return WARN, ("waiting for initial_mesh" + (f"; {ignored} tool poses ignored before it" if ignored else "")
                          + (f"; {cuts} cuts ignored before it" if cuts else "")
                          + mesh_rejections_text(counters.initial_meshes_rejected, self.last_mesh_rejection))
        news = [f"{new[problem]} {what}" for problem, what in self.PROBLEMS.items() if new[problem]]
        if news:
            return WARN, f"{', '.join(news)} since the last report; the last: {self.last_problem}"
        return OK, "simulating" if counters.tool_poses_received else "waiting for tool_pose"
