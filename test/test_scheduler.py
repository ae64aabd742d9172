"""The one step loop (core/scheduler.py) with an injected clock: pairing, waits, timeouts,
failures, the stamp rule and the registration check, as the nodes and the replay run it."""
import numpy as np
import pytest
from offline_helpers import NOISE_SIGMA, TOOL_RADIUS, tiny_scenario

from meshfg_ros.core.estimation.estimator import EstimatorConfig
from meshfg_ros.core.scheduler import (
    MAX_PREDICTION_WAIT_S,
    PREDICTION_TIMES_KEPT,
    EstimationScheduler,
    OfflinePipeline,
    Prediction,
    PredictionScheduler,
    SchedulingTimeouts,
)
from meshfg_ros.core.physics.simulator import SimulatorConfig
from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS

S = 1_000_000_000
TIMEOUTS = SchedulingTimeouts(prediction_timeout=0.5, estimate_timeout=2.0, tool_pose_timeout=0.2)


@pytest.fixture(scope="module")
def scenario():
    return tiny_scenario(steps=3)


def estimation(scenario) -> EstimationScheduler:
    config = EstimatorConfig(measurement_sigma=NOISE_SIGMA, tool_radius=TOOL_RADIUS, max_iterations=3)
    return EstimationScheduler(scenario.initial_mesh, config, timeouts=TIMEOUTS)


def prediction(scenario) -> PredictionScheduler:
    model = SimulatorConfig(**{**scenario.simulator_config.__dict__, "tool_radius": TOOL_RADIUS})
    return PredictionScheduler(scenario.initial_mesh, model, timeouts=TIMEOUTS)


def test_a_cloud_waits_for_its_prediction_until_the_timeout(scenario):
    scheduler = estimation(scenario)
    step = scenario.steps[0]
    assert scheduler.add_cloud(step.stamp_ns, step.points, now_s=10.0) == []
    assert scheduler.next_step(now_s=10.4) is None  # waits for the prediction
    ready = scheduler.next_step(now_s=10.5)
    assert ready is not None and ready.predicted is None and ready.stamp_ns == step.stamp_ns
    outcome = scheduler.run(ready)
    assert outcome.result is not None and outcome.result.degraded


def test_clouds_wait_for_a_simulator_that_is_there_until_its_prediction_times_are_known():
    """A simulator that is there: until PREDICTION_TIMES_KEPT prediction times are measured, a
    cloud waits for its prediction up to MAX_PREDICTION_WAIT_S, beyond prediction_timeout (the
    first prediction includes the simulator's set-up) and beyond 1.5x the times measured so far
    (the second here takes twice the first); then the measured times set the wait. A simulator
    that never answers costs the first cloud MAX_PREDICTION_WAIT_S, once; without a simulator the
    first cloud waits prediction_timeout."""
    scenario = tiny_scenario(steps=PREDICTION_TIMES_KEPT + 1)
    config = EstimatorConfig(measurement_sigma=NOISE_SIGMA, tool_radius=TOOL_RADIUS, max_iterations=3)
    present = EstimationScheduler(scenario.initial_mesh, config, timeouts=TIMEOUTS, simulator_present=lambda: True)
    start_s = 0.0
    for step, took_s in zip(scenario.steps, [1.0] + [2.0] * (PREDICTION_TIMES_KEPT - 1)):
        present.add_cloud(step.stamp_ns, step.points, now_s=start_s)
        assert present.next_step(now_s=start_s + took_s - 0.05) is None  # still waiting
        present.add_prediction(Prediction(step.stamp_ns, step.truth), now_s=start_s + took_s)
        paired = present.next_step(now_s=start_s + took_s)
        assert paired.stamp_ns == step.stamp_ns and np.array_equal(paired.predicted, step.truth)
        clock = iter((start_s + took_s, start_s + took_s + 0.1))
        assert not present.run(paired, now=lambda: next(clock)).result.degraded
        start_s += 10.0
    last = scenario.steps[PREDICTION_TIMES_KEPT]  # the times are known: 1.5 x 2 s
    present.add_cloud(last.stamp_ns, last.points, now_s=start_s)
    assert present.next_step(now_s=start_s + 1.5 * 2.0 - 0.05) is None
    assert present.next_step(now_s=start_s + 1.5 * 2.0).predicted is None
    first, second = scenario.steps[:2]
    silent = EstimationScheduler(scenario.initial_mesh, config, timeouts=TIMEOUTS, simulator_present=lambda: True)
    silent.add_cloud(first.stamp_ns, first.points, now_s=0.0)
    assert silent.next_step(now_s=MAX_PREDICTION_WAIT_S - 0.05) is None
    ran = silent.next_step(now_s=MAX_PREDICTION_WAIT_S)
    assert ran.stamp_ns == first.stamp_ns and ran.predicted is None
    clock = iter((MAX_PREDICTION_WAIT_S, MAX_PREDICTION_WAIT_S + 0.1))
    silent.run(ran, now=lambda: next(clock))
    silent.add_cloud(second.stamp_ns, second.points, now_s=10.0)
    assert silent.next_step(now_s=10.0 + TIMEOUTS.prediction_timeout).predicted is None
    absent = EstimationScheduler(scenario.initial_mesh, config, timeouts=TIMEOUTS, simulator_present=lambda: False)
    absent.add_cloud(first.stamp_ns, first.points, now_s=0.0)
    assert absent.next_step(now_s=TIMEOUTS.prediction_timeout).predicted is None


def test_an_answer_or_a_later_answer_releases_a_cloud_at_once(scenario):
    scheduler = estimation(scenario)
    first, second = scenario.steps[:2]
    scheduler.add_cloud(first.stamp_ns, first.points, now_s=0.0)
    scheduler.add_cloud(second.stamp_ns, second.points, now_s=0.0)
    assert scheduler.add_prediction(Prediction(second.stamp_ns, second.truth)) is None
    released = scheduler.next_step(now_s=0.0)  # a later answer came: the first cloud will get none
    assert released.stamp_ns == first.stamp_ns and released.predicted is None
    paired = scheduler.next_step(now_s=0.0)
    assert paired.stamp_ns == second.stamp_ns and np.array_equal(paired.predicted, second.truth)
    failed = estimation(scenario)
    failed.add_cloud(first.stamp_ns, first.points, now_s=0.0)
    failed.add_prediction(Prediction(first.stamp_ns, None, "inverted elements"))
    assert failed.next_step(now_s=0.0).predicted is None  # the simulator said it cannot: no wait


def test_stale_stamps_are_rejected_and_a_jump_back_restarts(scenario):
    scheduler = estimation(scenario)
    step = scenario.steps[1]
    assert scheduler.add_cloud(step.stamp_ns, step.points) == []
    [stale] = scheduler.add_cloud(step.stamp_ns, step.points)
    assert stale.counter == "clouds_rejected_stamp" and "is not newer than" in stale.reason
    assert scheduler.add_cloud(step.stamp_ns + 10 * S, step.points) == []
    [jump] = scheduler.add_cloud(step.stamp_ns, step.points)  # a looped recording
    assert jump.counter == "clock_jumps_back" and "restarting from the initial mesh" in jump.reason
    assert [scheduler.next_step(flush=True).restart for _ in range(3)] == [False, False, True]


def test_a_mesh_in_millimetres_rejects_the_clouds_with_the_reason(scenario):
    scheduler = EstimationScheduler(scenario.initial_mesh.with_vertices(1e3 * scenario.initial_mesh.vertices),
                                    EstimatorConfig(measurement_sigma=NOISE_SIGMA))
    step = scenario.steps[0]
    [rejection] = scheduler.add_cloud(step.stamp_ns, step.points)
    assert rejection.counter == "clouds_rejected_registration"
    assert "larger than the clouds" in rejection.reason and "mesh_scale 0.001" in rejection.reason
    assert scheduler.queued == 0


def test_predictions_wait_for_the_previous_estimate_and_a_covering_tool_pose(scenario):
    simulation = prediction(scenario)
    first, second = scenario.steps[:2]
    assert simulation.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose) is None
    simulation.request(first.stamp_ns, now_s=0.0)
    assert simulation.poll(now_s=0.0) == []  # no tool pose at or after the cloud's stamp yet
    simulation.add_tool_pose(first.stamp_ns, first.tool_pose)
    [answer] = simulation.poll(now_s=0.0)
    assert answer.stamp_ns == first.stamp_ns and answer.positions is not None and answer.failure == ""
    simulation.add_tool_pose(second.stamp_ns, second.tool_pose)
    simulation.request(second.stamp_ns, now_s=1.0)
    assert simulation.poll(now_s=2.9) == []  # waits for the estimate of the first cloud
    estimate = answer.positions + 1e-5
    assert simulation.add_estimate(first.stamp_ns, estimate) is None
    [later] = simulation.poll(now_s=2.9)
    simulation_again = prediction(scenario)
    simulation_again.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    simulation_again.add_tool_pose(first.stamp_ns, first.tool_pose)
    simulation_again.request(first.stamp_ns)
    simulation_again.poll()
    simulation_again.add_tool_pose(second.stamp_ns, second.tool_pose)
    simulation_again.request(second.stamp_ns, now_s=1.0)
    [from_old_state] = simulation_again.poll(now_s=3.0)  # estimate_timeout: from the newest state
    assert not np.allclose(later.positions, from_old_state.positions, atol=1e-7)


def test_a_request_before_any_tool_pose_fails_after_the_tool_pose_timeout(scenario):
    """A tool pose stream that never starts: each request is answered, after tool_pose_timeout,
    with the reason, so that its cloud runs at once (degraded) and the node can publish why."""
    simulation = prediction(scenario)
    simulation.request(FIRST_STAMP_NS + S, now_s=0.0)
    assert simulation.poll(now_s=0.1) == []
    [answer] = simulation.poll(now_s=0.2)
    assert answer.positions is None and answer.failure.startswith("no tool pose received yet")
    assert simulation.tool_pose_unavailable == {"empty": 1}
    # the stream starts: later requests are predicted as usual
    simulation.add_tool_pose(FIRST_STAMP_NS + S, scenario.initial_tool_pose)
    simulation.add_tool_pose(FIRST_STAMP_NS + 3 * S, scenario.initial_tool_pose)
    simulation.request(FIRST_STAMP_NS + 2 * S, now_s=1.0)
    [predicted] = simulation.poll(now_s=1.0)
    assert predicted.positions is not None and np.isfinite(predicted.positions).all()


def test_a_request_beyond_the_tool_pose_horizon_is_answered_with_the_reason(scenario):
    simulation = prediction(scenario)
    simulation.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    simulation.request(FIRST_STAMP_NS + S, now_s=0.0)
    assert simulation.poll(now_s=0.1) == []
    [answer] = simulation.poll(now_s=0.2)  # tool_pose_timeout: extrapolation is not allowed that far
    assert answer.positions is None and "beyond the newest" in answer.failure
    assert simulation.tool_pose_unavailable == {"beyond_horizon": 1}  # the simulation node's counter


def test_the_offline_pipeline_requests_no_prediction_for_a_cloud_it_did_not_queue(scenario):
    """A first cloud two mesh diagonals off the mesh (a wrong registration, near enough not to be
    dropped as far) fails the registration check: no prediction is requested for it (as the
    estimator node does), so the next clouds' predictions need no estimate of it and
    each step is estimated when its cloud and tool pose are in, not only when the input ends."""
    model = SimulatorConfig(**{**scenario.simulator_config.__dict__, "tool_radius": TOOL_RADIUS})
    config = EstimatorConfig(measurement_sigma=NOISE_SIGMA, tool_radius=TOOL_RADIUS, max_iterations=3)
    pipeline = OfflinePipeline(scenario.initial_mesh, model, config)
    first, *rest = scenario.steps
    pipeline.tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    pipeline.tool_pose(first.stamp_ns, first.tool_pose)
    diagonal = float(np.linalg.norm(np.ptp(scenario.initial_mesh.vertices, axis=0)))
    assert pipeline.cloud(first.stamp_ns, first.points + [2.0 * diagonal, 0.0, 0.0]) == []
    for step in rest:
        pipeline.tool_pose(step.stamp_ns, step.tool_pose)
        [estimated] = pipeline.cloud(step.stamp_ns, step.points)
        assert estimated.stamp_ns == step.stamp_ns and estimated.predicted is not None
    assert pipeline.finish() == []


def test_after_a_request_without_a_tool_pose_the_tool_moves_from_where_the_simulator_left_it(scenario):
    """The time steps of a prediction run from the simulator's last tool pose, through the request
    it could not predict (no tool pose within the horizon: a stalled stream), with the tool
    interpolated between the two poses it has; the degraded estimate of that request is no start
    state (the simulator keeps the one it had)."""
    simulation = prediction(scenario)
    steps = []
    predict = simulation.simulator.predict
    simulation.simulator.predict = lambda state, pose, dt: steps.append((dt, pose, state)) or predict(state, pose, dt)
    simulation.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    simulation.request(FIRST_STAMP_NS + S, now_s=0.0)
    [unavailable] = simulation.poll(now_s=1.0)
    assert unavailable.positions is None and steps == []
    degraded = scenario.initial_mesh.vertices + 1e-3
    assert simulation.add_estimate(FIRST_STAMP_NS + S, degraded, degraded=True) is None
    simulation.add_tool_pose(FIRST_STAMP_NS + 3 * S, scenario.steps[0].tool_pose)
    simulation.request(FIRST_STAMP_NS + 2 * S, now_s=1.0)
    # the degraded estimate settled the skipped request; the stamp passed is answered too, first
    [caught_up, answer] = simulation.poll(now_s=1.0)
    assert answer.positions is not None and [dt for dt, _, _ in steps] == [1.0, 1.0]
    assert (caught_up.stamp_ns, caught_up.catch_up, answer.catch_up) == (FIRST_STAMP_NS + S, True, False)
    (_, passed_pose, start), (_, last_pose, _) = steps
    np.testing.assert_array_equal(start, scenario.initial_mesh.vertices)  # not the degraded estimate
    halfway = scenario.initial_tool_pose[:3] + (scenario.steps[0].tool_pose[:3] - scenario.initial_tool_pose[:3]) / 3
    np.testing.assert_allclose(passed_pose[:3], halfway, rtol=0.0, atol=1e-15)  # a third of the way at 1 of 3 s
    np.testing.assert_allclose(last_pose[:3], halfway + (halfway - scenario.initial_tool_pose[:3]), rtol=0.0,
                               atol=1e-15)
    np.testing.assert_array_equal(caught_up.tool_pose, passed_pose)
    np.testing.assert_array_equal(steps[1][2], caught_up.positions)  # the stamp's own prediction starts there


def stall_then_resume(scheduler: EstimationScheduler, steps, clock=None):
    """The first step runs with its prediction, the next two without a tool pose, their
    predictions failed (a stall); their catch-up predictions come after they ran, then the
    fourth step's cloud and prediction: (the fourth step's outcome, what add_prediction said of
    the catch-up predictions)."""
    first, *stalled, resumed = steps[:4]
    scheduler.add_tool_pose(first.stamp_ns, first.tool_pose)  # poses came, then stop
    scheduler.add_cloud(first.stamp_ns, first.points)
    scheduler.add_prediction(Prediction(first.stamp_ns, first.truth, tool_pose=first.tool_pose))
    scheduler.run(scheduler.next_step(flush=True), clock)
    for step in stalled:
        scheduler.add_cloud(step.stamp_ns, step.points)
        scheduler.add_prediction(Prediction(step.stamp_ns, None, "no tool pose within the horizon"))
        ready = scheduler.next_step(flush=True)
        assert ready.stalled and ready.predicted is None
        outcome = scheduler.run(ready, clock)
        assert outcome.result.degraded and outcome.reruns == ()
    said = [scheduler.add_prediction(Prediction(step.stamp_ns, step.truth, tool_pose=step.tool_pose, catch_up=True))
            for step in stalled]
    scheduler.add_cloud(resumed.stamp_ns, resumed.points)
    scheduler.add_prediction(Prediction(resumed.stamp_ns, resumed.truth, tool_pose=resumed.tool_pose))
    ready = scheduler.next_step(flush=True)
    assert not ready.stalled
    return scheduler.run(ready, clock), said


@pytest.fixture(scope="module")
def longer_scenario():
    return tiny_scenario(steps=4)


def test_clouds_of_a_stalled_tool_stream_run_again_with_the_catch_up_predictions(longer_scenario):
    """Clouds that ran degraded for want of a tool pose are held with the estimator as it was
    before them; the simulator's catch-up predictions for them, which come after they ran, are
    taken (not rejected as late), and the next step first runs them again from that estimator:
    the window it then holds is the one a run without the stall would have."""
    scenario = longer_scenario
    steps = scenario.steps
    outcome, said = stall_then_resume(estimation(scenario), steps)
    assert said == [None, None]  # taken, not rejected as late
    again = [(run.step.stamp_ns, run.result.degraded) for run in outcome.reruns]
    assert again == [(steps[1].stamp_ns, False), (steps[2].stamp_ns, False)] and not outcome.result.degraded
    clean = estimation(scenario)
    for step in steps:
        clean.add_cloud(step.stamp_ns, step.points)
        clean.add_prediction(Prediction(step.stamp_ns, step.truth, tool_pose=step.tool_pose))
        expected = clean.run(clean.next_step()).result
    assert outcome.result.step == expected.step
    # The same window and inputs; PCG's preconditioner factors may differ (the solver is the
    # stalled run's), within LM's stopping tolerance.
    np.testing.assert_allclose(outcome.result.positions, expected.positions, rtol=0.0, atol=1e-6)
    # A failure is no stall with a tool pose at its stamp, nor where no tool pose ever came (the
    # estimator does not see the tool, as with a sim_bridge simulator that moves its own).
    posed, unposed = estimation(scenario), estimation(scenario)
    posed.add_tool_pose(steps[0].stamp_ns, steps[0].tool_pose)
    for scheduler in (posed, unposed):
        scheduler.add_cloud(steps[0].stamp_ns, steps[0].points)
        scheduler.add_prediction(Prediction(steps[0].stamp_ns, None, "inverted elements"))
        assert not scheduler.next_step().stalled


@pytest.mark.parametrize("update_periods, again", [(0.3, 1), (0.6, 0)])
def test_only_the_stalled_clouds_whose_updates_fit_in_half_a_cloud_period_run_again(longer_scenario, update_periods,
                                                                                  again):
    """The held clouds run again only as far as their updates (at the longest recent one with a
    prediction) fit in half the clouds' period, the newest first: none where an update takes
    half the period or more (organ scale); then nothing is held and the late answers are
    rejected as any late answer is."""
    steps = longer_scenario.steps
    period_s = (steps[1].stamp_ns - steps[0].stamp_ns) / S
    ticks = iter(np.arange(0.0, 100.0, update_periods * period_s))  # the time each update takes
    outcome, said = stall_then_resume(estimation(longer_scenario), steps, lambda: float(next(ticks)))
    assert [run.step.stamp_ns for run in outcome.reruns] == [steps[2].stamp_ns][:again]
    assert all(not run.result.degraded for run in outcome.reruns) and not outcome.result.degraded
    assert [rejection is None for rejection in said] == [bool(again)] * 2


def test_every_held_cloud_runs_again_also_one_without_a_prediction_after_the_stall():
    """Three clouds held: two stalled, and one after them that ran without any answer (its
    prediction came after the catch-up's); with time for all, all three run again from the
    snapshot, with the settings reconfigured during the stall."""
    scenario = tiny_scenario(steps=5)
    first, stalled, unanswered, resumed = scenario.steps[0], scenario.steps[1:3], scenario.steps[3], scenario.steps[4]
    scheduler = estimation(scenario)
    scheduler.add_tool_pose(first.stamp_ns, first.tool_pose)
    scheduler.add_cloud(first.stamp_ns, first.points)
    scheduler.add_prediction(Prediction(first.stamp_ns, first.truth, tool_pose=first.tool_pose))
    scheduler.run(scheduler.next_step(flush=True))
    for step in stalled:
        scheduler.add_cloud(step.stamp_ns, step.points)
        scheduler.add_prediction(Prediction(step.stamp_ns, None, "no tool pose within the horizon"))
        assert scheduler.run(scheduler.next_step(flush=True)).result.degraded
    scheduler.reconfigure({"simulation_sigma": 2e-4})
    scheduler.add_tool_pose(unanswered.stamp_ns, unanswered.tool_pose)  # poses again
    scheduler.add_cloud(unanswered.stamp_ns, unanswered.points)
    ready = scheduler.next_step(flush=True)  # its prediction has not come: it runs without one
    assert not ready.stalled and ready.predicted is None and scheduler.run(ready).result.degraded
    for step in [*stalled, unanswered]:
        assert scheduler.add_prediction(Prediction(step.stamp_ns, step.truth, tool_pose=step.tool_pose,
                                                   catch_up=step is not unanswered)) is None
    scheduler.add_cloud(resumed.stamp_ns, resumed.points)
    scheduler.add_prediction(Prediction(resumed.stamp_ns, resumed.truth, tool_pose=resumed.tool_pose))
    outcome = scheduler.run(scheduler.next_step(flush=True))
    assert [run.step.stamp_ns for run in outcome.reruns] == [step.stamp_ns for step in [*stalled, unanswered]]
    assert not any(run.result.degraded for run in outcome.reruns) and not outcome.result.degraded
    assert scheduler.estimator.config.simulation_sigma == 2e-4  # the snapshot took the live settings


def test_the_simulator_learns_from_a_stalled_cloud_run_again_once(scenario):
    simulation = prediction(scenario)
    simulation.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    simulation.request(FIRST_STAMP_NS + S, now_s=0.0)
    simulation.poll(now_s=1.0)  # no tool pose within the horizon: a stall
    simulation.add_estimate(FIRST_STAMP_NS + S, scenario.initial_mesh.vertices, degraded=True)
    simulation.add_tool_pose(FIRST_STAMP_NS + 2 * S, scenario.steps[0].tool_pose)
    simulation.request(FIRST_STAMP_NS + 2 * S, now_s=1.0)
    [caught_up, _] = simulation.poll(now_s=1.0)
    load = simulation.simulator.body_acceleration.copy()
    std = np.full(scenario.initial_mesh.vertex_count, 1e-4)
    pushed = caught_up.positions - [0.0, 0.0, 2e-4]  # the tissue sank further than predicted
    assert simulation.learn_from_catch_up(FIRST_STAMP_NS + 2 * S, pushed, std) is False  # not caught up
    far = simulation.learn_from_catch_up(FIRST_STAMP_NS + S, caught_up.positions + 10.0, std)
    assert far.counter == "estimates_ignored"
    # a degraded estimate (the estimator set the prediction aside) teaches nothing either
    assert simulation.learn_from_catch_up(FIRST_STAMP_NS + S, pushed, std, degraded=True) is False
    np.testing.assert_array_equal(simulation.simulator.body_acceleration, load)
    assert simulation.learn_from_catch_up(FIRST_STAMP_NS + S, pushed, std) is True
    learnt = simulation.simulator.body_acceleration.copy()
    assert learnt[2] < load[2] - 1e-3  # a load along -z
    assert simulation.learn_from_catch_up(FIRST_STAMP_NS + S, pushed, std) is False  # learnt once only
    np.testing.assert_array_equal(simulation.simulator.body_acceleration, learnt)


def test_a_tool_pose_with_a_zero_quaternion_is_set_aside_with_the_reason(scenario):
    simulation = prediction(scenario)
    broken = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    rejection = simulation.add_tool_pose(FIRST_STAMP_NS, broken)
    assert rejection.counter == "tool_poses_rejected_malformed" and "zero norm" in rejection.reason
    scheduler = estimation(scenario)
    scheduler.add_tool_pose(FIRST_STAMP_NS, broken)  # the estimator's side ignores it, no error
    scheduler.add_cloud(FIRST_STAMP_NS, scenario.steps[0].points)
    assert scheduler.next_step(flush=True).tool_pose is None  # nothing was buffered


def test_a_pipeline_behind_the_clouds_predicts_the_newest_cloud_and_skips_the_one_between(scenario):
    """Newest first: the request waiting for the previous estimate when a newer cloud comes is
    superseded; the simulator predicts the newest cloud from the newest estimate (the tool moved
    from the first cloud's pose), and the estimator drops the skipped cloud with the reason."""
    simulation, estimator = prediction(scenario), estimation(scenario)
    first, second, third = scenario.steps[:3]
    simulation.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    for step in (first, second, third):
        simulation.add_tool_pose(step.stamp_ns, step.tool_pose)
    simulation.request(first.stamp_ns, now_s=0.0)
    estimator.add_cloud(first.stamp_ns, first.points, now_s=0.0)
    [answer] = simulation.poll(now_s=0.1)
    assert estimator.add_prediction(answer, now_s=0.1) is None
    clock = iter((0.1, 1.7))  # the update's start and end: longer than the clouds' period
    run = estimator.run(estimator.next_step(now_s=0.1), now=lambda: next(clock))
    assert run.result is not None and not run.result.degraded
    for step, now in ((second, 1.0), (third, 1.5)):  # both come while the first estimate is awaited
        estimator.add_cloud(step.stamp_ns, step.points, now_s=now)
        simulation.request(step.stamp_ns, now_s=now)
    [skipped] = simulation.poll(now_s=1.5)  # answered at once, the simulator not moved
    assert skipped.stamp_ns == second.stamp_ns and skipped.superseded and skipped.positions is None
    [rejection] = [estimator.add_prediction(skipped, now_s=1.5)]
    assert rejection.counter == "clouds_skipped_behind" and "the update 1600 ms" in rejection.reason
    assert "the prediction takes 100 ms" in rejection.reason
    assert "clouds come every 1000 ms" in rejection.reason and "voxel filter" in rejection.reason
    assert estimator.queued == 1
    simulation.add_estimate(first.stamp_ns, run.result.positions)
    [newest] = simulation.poll(now_s=1.7)
    assert newest.stamp_ns == third.stamp_ns and newest.positions is not None and not newest.superseded
    reference = prediction(scenario)  # the same simulator, asked for the third cloud from the first estimate
    reference.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    reference.add_tool_pose(first.stamp_ns, first.tool_pose)
    reference.request(first.stamp_ns)
    reference.poll()
    reference.add_estimate(first.stamp_ns, run.result.positions)
    reference.add_tool_pose(third.stamp_ns, third.tool_pose)
    reference.request(third.stamp_ns)
    [expected] = reference.poll()
    np.testing.assert_allclose(newest.positions, expected.positions, rtol=0.0, atol=1e-12)
    estimator.add_prediction(newest, now_s=1.7)
    paired = estimator.next_step(now_s=1.7)
    assert paired.stamp_ns == third.stamp_ns and paired.predicted is not None


def test_a_pipeline_that_keeps_up_never_supersedes(scenario):
    simulation = prediction(scenario)
    first, second = scenario.steps[:2]
    simulation.add_tool_pose(FIRST_STAMP_NS, scenario.initial_tool_pose)
    simulation.add_tool_pose(first.stamp_ns, first.tool_pose)
    simulation.request(first.stamp_ns, now_s=0.0)
    [answer] = simulation.poll(now_s=0.1)
    simulation.add_estimate(first.stamp_ns, answer.positions)  # the estimate came before the next cloud
    simulation.add_tool_pose(second.stamp_ns, second.tool_pose)
    simulation.request(second.stamp_ns, now_s=1.0)
    [later] = simulation.poll(now_s=1.1)
    assert not later.superseded and later.positions is not None


def test_a_cloud_waits_as_long_as_the_simulator_recently_took(scenario):
    """A slow simulator (a large mesh) still pairs its predictions: the wait follows the measured
    prediction times instead of running every step degraded after prediction_timeout."""
    scheduler = estimation(scenario)
    first, second = scenario.steps[:2]
    assert scheduler.prediction_wait_s == TIMEOUTS.prediction_timeout
    scheduler.add_cloud(first.stamp_ns, first.points, now_s=0.0)
    scheduler.add_prediction(Prediction(first.stamp_ns, first.truth), now_s=1.2)  # took 1.2 s
    clock = iter((1.2, 1.3))
    scheduler.run(scheduler.next_step(now_s=1.2), now=lambda: next(clock))
    assert scheduler.prediction_wait_s == pytest.approx(1.5 * 1.2)
    scheduler.add_cloud(second.stamp_ns, second.points, now_s=2.0)
    assert scheduler.next_step(now_s=2.0 + 1.5 * 1.2 - 0.05) is None  # beyond prediction_timeout, still waiting
    assert scheduler.next_step(now_s=2.0 + 1.5 * 1.2).predicted is None  # the learnt wait is over
    late = scheduler.add_prediction(Prediction(second.stamp_ns, second.truth), now_s=4.0)
    # The late prediction is measured too (2 s from the cloud's arrival): the next cloud waits for it.
    # The warning names the wait the cloud had, not the longer one the late prediction sets.
    assert late.counter == "predictions_rejected" and "prediction takes 2000 ms" in late.reason
    assert f"it waited {1.5 * 1.2:.2f} s" in late.reason
    assert scheduler.prediction_wait_s == pytest.approx(1.5 * 2.0)
