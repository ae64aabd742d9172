"""The nodes' health (nodes/diagnostics.py). The estimator node's: OK only while recent steps are
estimated from most of their points, with a prediction, converged and in time; the simulation
node's: OK only while it has its mesh and tool poses, uses what it receives and its newest
prediction succeeded; otherwise the reason."""
from diagnostic_msgs.msg import DiagnosticStatus

from meshfg_ros.nodes.diagnostics import (HEALTH_WINDOW, EstimatorCounters, EstimatorHealth, SimulatorCounters,
                                          SimulatorHealth, with_setup_problems)

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


def healthy_steps(health: EstimatorHealth, count: int = HEALTH_WINDOW) -> EstimatorCounters:
    for _ in range(count):
        health.record(degraded=False, converged=True, points_used=900, points_set_aside=100)
    return EstimatorCounters(clouds_received=count, steps=count)


def assess_when_most_steps_are(**flag) -> tuple:
    """(level, message) once one step more than half of the window carries `flag`; half of them
    is not most, and still OK."""
    health = EstimatorHealth(stalled_after_s=2.0)
    counters = healthy_steps(health, HEALTH_WINDOW // 2)
    for _ in range(HEALTH_WINDOW // 2):
        health.record(degraded=False, converged=True, points_used=900, points_set_aside=100, **flag)
    assert health.assess(counters, False, 0.0) == (OK, "estimating")
    health.record(degraded=False, converged=True, points_used=900, points_set_aside=100, **flag)
    return health.assess(counters, False, 0.0)


def test_healthy_steps_are_ok_and_waiting_for_the_mesh_is_a_warning_then_an_error():
    health = EstimatorHealth(stalled_after_s=2.0)
    assert health.assess(EstimatorCounters(), waiting_for_mesh=True, unanswered_s=0.0) == (
        WARN, "waiting for initial_mesh")
    level, message = health.assess(EstimatorCounters(clouds_received=30), True, 3.0)
    assert level == ERROR and "there is no mesh" in message
    assert health.assess(healthy_steps(health), False, 0.0) == (OK, "estimating")


def test_every_cloud_rejected_is_an_error_that_names_the_reason():
    health = EstimatorHealth(stalled_after_s=2.0)
    counters = EstimatorCounters(clouds_received=20, clouds_rejected_registration=20)
    reason = "the mesh is ~1000x larger than the clouds: is it in millimetres? set mesh_scale 0.001"
    assert health.assess(counters, False, 1.0, reason)[0] == WARN  # not yet stalled: rejections so far
    level, message = health.assess(counters, False, 2.5, reason)
    assert level == ERROR and message.endswith(reason) and "every cloud is rejected" in message


def test_degraded_gated_unconverged_and_lagging_steps_are_warnings():
    health = EstimatorHealth(stalled_after_s=2.0)
    counters = healthy_steps(health, HEALTH_WINDOW // 2 - 1)
    for _ in range(HEALTH_WINDOW // 2 + 1):
        health.record(degraded=True, converged=True, points_used=900, points_set_aside=100)
    level, message = health.assess(counters, False, 0.0)
    assert level == WARN and message.startswith(f"{HEALTH_WINDOW // 2 + 1} of the last {HEALTH_WINDOW} steps ran "
                                                "without a simulator prediction")

    health = EstimatorHealth(stalled_after_s=2.0)
    for _ in range(HEALTH_WINDOW):
        health.record(degraded=False, converged=True, points_used=100, points_set_aside=900)
    level, message = health.assess(counters, False, 0.0)
    assert level == WARN and f"{900 * HEALTH_WINDOW} of {1000 * HEALTH_WINDOW} points" in message
    assert "check units" in message

    health = EstimatorHealth(stalled_after_s=2.0)
    for _ in range(HEALTH_WINDOW):
        health.record(degraded=False, converged=False, points_used=900, points_set_aside=100)
    assert health.assess(counters, False, 0.0) == (WARN, f"{HEALTH_WINDOW} of the last {HEALTH_WINDOW} updates "
                                                         "did not converge")

    level, message = assess_when_most_steps_are(noise_off_nominal=True)
    assert level == WARN and message.startswith(f"in {HEALTH_WINDOW // 2 + 1} of the last {HEALTH_WINDOW} updates the "
                                                "cloud spread more than 10x above or below measurement_sigma")
    assert message.endswith("check it and its units")

    health = EstimatorHealth(stalled_after_s=2.0)
    lagging = healthy_steps(health)
    lagging.queued_clouds, lagging.median_latency_ms = 7, 2400.0
    level, message = health.assess(lagging, False, 0.0)
    assert level == WARN and message.startswith("lagging: 7 clouds wait (median latency 2400 ms)")


def test_new_failures_and_rejections_warn_once_per_report():
    health = EstimatorHealth(stalled_after_s=2.0)
    counters = healthy_steps(health)
    counters.failed_steps = 2
    assert health.assess(counters, False, 0.0) == (WARN, "2 updates failed since the last report")
    counters.clouds_rejected_frame = 3
    assert health.assess(counters, False, 0.0) == (WARN, "3 clouds rejected since the last report")
    assert health.assess(counters, False, 0.0) == (OK, "estimating")
    counters.clouds_rejected_frame = 4
    assert health.assess(counters, False, 0.0, "cloud rejected: no transform") == (
        WARN, "1 clouds rejected since the last report; the last: cloud rejected: no transform")


def test_clouds_rejected_before_any_estimate_keep_a_warning_with_the_last_reason():
    health = EstimatorHealth(stalled_after_s=12.0)
    counters = EstimatorCounters(clouds_received=2, clouds_rejected_registration=2)
    reason = "cloud at 1 ns rejected: the clouds do not overlap the mesh, but would with mesh_scale 0.1 times its value"
    for _ in range(3):  # every report until the stall's ERROR, not only the first after a rejection
        assert health.assess(counters, False, 2.0, reason) == (WARN, f"no estimate yet: 2 clouds rejected; the last: "
                                                                     f"{reason}")


def test_clouds_seen_from_implausible_angles_warn_to_check_camera_frame():
    level, message = assess_when_most_steps_are(view_implausible=True)
    assert level == WARN and message.startswith(f"in {HEALTH_WINDOW // 2 + 1} of the last {HEALTH_WINDOW} clouds more "
                                                "than 5 % of the points face away from camera_frame's origin")
    assert "check camera_frame and its transform on /tf (or camera_pose)" in message


def test_wiring_problems_come_first():
    assert with_setup_problems(OK, "estimating", ["tool_pose from /driver never arrives: ...", "x"], []) == (
        ERROR, "tool_pose from /driver never arrives: ... (and 1 more such publishers)")
    assert with_setup_problems(WARN, "lagging", [], ["parameters file f sets nothing"]) == (
        WARN, "parameters file f sets nothing")
    assert with_setup_problems(WARN, "lagging", [], []) == (WARN, "lagging")


def test_the_simulation_node_warns_of_what_it_could_not_use_once_per_report_and_of_its_last_failure():
    health = SimulatorHealth()
    assert health.assess(SimulatorCounters(inputs_held_before_mesh=2), waiting_for_mesh=True) == (
        WARN, "waiting for initial_mesh; 2 inputs held until it comes")
    level, message = health.assess(SimulatorCounters(requests=3), False)
    assert level == WARN and message.startswith("3 prediction requests but no tool pose received")
    counters = SimulatorCounters(requests=3, tool_poses_received=5, tool_poses_rejected_stamp=2, estimates_ignored=1)
    assert health.assess(counters, False) == (WARN, "2 tool poses rejected since the last report")
    assert health.assess(counters, False) == (OK, "predicting")  # the estimate ignored was in the same report
    health.record("the predicted positions are not finite")
    assert health.assess(counters, False) == (WARN, "the last prediction failed: the predicted positions are not finite")
    health.record(None)
    assert health.assess(counters, False) == (OK, "predicting")
