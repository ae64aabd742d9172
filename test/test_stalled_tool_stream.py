"""Recovery from a stalled tool pose stream (issue 44): the bundled airway push, its tool poses
re-sampled at 20 Hz as a robot sends them, run through the two schedulers on the nodes' clock
(their 20 ms polls, the clouds 50 ms after their stamps, the timeouts of the recording's
parameters), once clean and once with the pose stream stalled for 5 s.

While it stalls, the clouds run degraded and the estimate drifts from the truth (the hidden
tissue does not follow the tool). Once poses come again, the simulator restarts from its state
before the stall and moves the tool through the stamps it missed (PredictionScheduler._catch_up),
instead of jumping from the last degraded estimate; the estimator runs the stalled clouds again
with those predictions (EstimationScheduler.run), and the simulator learns from those estimates
what the stall kept from it (PredictionScheduler.learn_from_catch_up).
"""
import numpy as np
import pytest
from offline_helpers import BAGS

from meshfg_ros.core.scheduler import EstimationScheduler, PredictionScheduler, SchedulingTimeouts, cloud_queued
from meshfg_ros.evaluation.metrics import vertex_rmse
from meshfg_ros.io.messages import MeshState
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.parameters import estimator_config, simulator_config
from meshfg_ros.replay import load_inputs, replay_parameters
from meshfg_ros.topics import GROUND_TRUTH_TOPIC
from test_robot_wiring import tool_poses_at

POSE_PERIOD_NS = 50_000_000  # 20 Hz
POSE_LATENCY_S, CLOUD_LATENCY_S, POLL_S = 0.003, 0.05, 0.02


def live_errors(inputs, params, truth, stall_ns=None) -> tuple[list[tuple[float, bool]], list[tuple[int, bool]]]:
    """(vertex RMSE to the truth in mm, degraded) of each estimate, the poses in [stall_ns) dropped,
    and (stamp, degraded) of each cloud run again after the stall."""
    timeouts = SchedulingTimeouts(prediction_timeout=params["prediction_timeout"],
                                  estimate_timeout=params["estimate_timeout"],
                                  tool_pose_timeout=params["tool_pose_timeout"])
    simulation = PredictionScheduler(inputs.initial_mesh, simulator_config(params), timeouts=timeouts,
                                     tool_pose_extrapolation=params["tool_pose_horizon"])
    estimation = EstimationScheduler(inputs.initial_mesh, estimator_config(params), timeouts=timeouts,
                                     tool_pose_extrapolation=params["tool_pose_horizon"])
    known_ns = np.array([pose.stamp_ns for pose in inputs.poses])
    known = np.array([pose.pose for pose in inputs.poses])
    stamps = np.arange(known_ns[0], inputs.clouds[-1].stamp_ns + 10**9, POSE_PERIOD_NS)
    events = [(stamp / 1e9 + POSE_LATENCY_S, 0, int(stamp), pose)
              for stamp, pose in zip(stamps, tool_poses_at(stamps, known_ns, known))
              if stall_ns is None or not stall_ns[0] <= stamp < stall_ns[1]]
    events += [(cloud.stamp_ns / 1e9 + CLOUD_LATENCY_S, 1, cloud.stamp_ns, cloud.points) for cloud in inputs.clouds]
    results, again_run = {}, []

    def pump(now_s):
        while True:
            answers = simulation.poll(now_s)
            for answer in answers:
                estimation.add_prediction(answer, now_s)
            step = estimation.next_step(now_s)
            if step is None and not answers:
                return
            if step is not None:
                outcome = estimation.run(step)
                for again in outcome.reruns:
                    again_run.append((again.step.stamp_ns, again.result.degraded))
                    simulation.learn_from_catch_up(again.step.stamp_ns, again.result.positions,
                                                   again.result.position_std.astype(np.float32).astype(np.float64),
                                                   again.result.degraded)
                result = outcome.result
                simulation.add_estimate(step.stamp_ns, result.positions, degraded=result.degraded,
                                        position_std=result.position_std.astype(np.float32).astype(np.float64))
                results[step.stamp_ns] = result

    now_s = min(events)[0]
    for when, kind, stamp, data in sorted(events, key=lambda event: event[:2]):
        while now_s < when:
            pump(now_s)
            now_s += POLL_S
        if kind == 0:
            simulation.add_tool_pose(stamp, data)
            estimation.add_tool_pose(stamp, data)
        elif cloud_queued(estimation.add_cloud(stamp, data, when)):
            simulation.request(stamp, when)
        pump(now_s)
    for _ in range(100):
        pump(now_s)
        now_s += POLL_S
    free = inputs.initial_mesh.free_vertices
    errors = [(1e3 * vertex_rmse(results[s].positions, truth[s], free), results[s].degraded) for s in sorted(results)]
    return errors, again_run


@pytest.fixture(scope="module")
def runs():
    inputs = load_inputs(BAGS / "cao-push")
    params = replay_parameters(inputs, None)
    with RecordingReader(BAGS / "cao-push") as reader:
        truth = {state.stamp_ns: state.positions for state in reader.records(GROUND_TRUTH_TOPIC, MeshState)}
    stall_start = inputs.clouds[2].stamp_ns - 500_000_000
    return (inputs, live_errors(inputs, params, truth),
            live_errors(inputs, params, truth, (stall_start, stall_start + 5_000_000_000)))


def test_a_stalled_tool_stream_runs_degraded_then_recovers_to_the_clean_run(runs):
    inputs, (clean, clean_again), (stalled, stalled_again) = runs
    assert len(clean) == len(stalled) == 10 and not any(degraded for _, degraded in clean)
    assert [degraded for _, degraded in stalled] == [False] * 2 + [True] * 5 + [False] * 3
    # the five stalled clouds ran again, with predictions, once poses came; the clean run had none
    assert stalled_again == [(cloud.stamp_ns, False) for cloud in inputs.clouds[2:7]] and clean_again == []
    # the stall costs accuracy while it lasts
    assert stalled[6][0] > 2.0 * clean[6][0]
    # Resumed: the first cloud's prediction was made before the simulator learnt from the
    # stalled clouds run again; from the second on the error is the clean run's (issue 44:
    # within two clouds; docs/design-notes.md, "A stalled tool stream").
    assert stalled[7][0] < 1.2 * clean[7][0], (stalled[7][0], clean[7][0])
    for after in (8, 9):
        assert stalled[after][0] < 1.05 * clean[after][0], (after, stalled[after][0], clean[after][0])
