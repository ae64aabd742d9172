"""Recovery from a stalled tool pose stream (issue 44): the bundled airway push, its tool poses
re-sampled at 20 Hz as a robot sends them, run through the two schedulers on the nodes' clock
(their 20 ms polls, the clouds 50 ms after their stamps, the timeouts of the recording's
parameters), once clean and once with the pose stream stalled for 5 s.

While it stalls, the clouds run degraded and the estimate drifts from the truth (the hidden
tissue does not follow the tool). Once poses come again, the simulator restarts from its state
before the stall and moves the tool through the stamps it missed (PredictionScheduler._catch_up),
instead of jumping from the last degraded estimate.
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


def live_errors(inputs, params, truth, stall_ns=None) -> list[tuple[float, bool]]:
    """(vertex RMSE to the truth in mm, degraded) of each estimate, the poses in [stall_ns) dropped."""
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
    results = {}

    def pump(now_s):
        while True:
            answers = simulation.poll(now_s)
            for answer in answers:
                estimation.add_prediction(answer, now_s)
            step = estimation.next_step(now_s)
            if step is None and not answers:
                return
            if step is not None:
                result = estimation.run(step).result
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
    return [(1e3 * vertex_rmse(results[s].positions, truth[s], free), results[s].degraded) for s in sorted(results)]


@pytest.fixture(scope="module")
def runs():
    inputs = load_inputs(BAGS / "cao-push")
    params = replay_parameters(inputs, None)
    with RecordingReader(BAGS / "cao-push") as reader:
        truth = {state.stamp_ns: state.positions for state in reader.records(GROUND_TRUTH_TOPIC, MeshState)}
    stall_start = inputs.clouds[2].stamp_ns - 500_000_000
    return (live_errors(inputs, params, truth),
            live_errors(inputs, params, truth, (stall_start, stall_start + 5_000_000_000)))


def test_a_stalled_tool_stream_runs_degraded_then_recovers_near_the_clean_run(runs):
    clean, stalled = runs
    assert len(clean) == len(stalled) == 10 and not any(degraded for _, degraded in clean)
    assert [degraded for _, degraded in stalled] == [False] * 2 + [True] * 5 + [False] * 3
    # the stall costs accuracy while it lasts
    assert stalled[6][0] > 2.0 * clean[6][0]
    # Resumed: the bounds hold the recovery the catch-up gives (the prediction from the state
    # before the stall, the tool interpolated over it); the error left is the Poisson ratio the
    # stall's clouds did not teach (docs/design-notes.md, "A stalled tool stream").
    for after, bound in ((7, 1.15), (8, 1.25), (9, 1.25)):
        assert stalled[after][0] < bound * clean[after][0], (after, stalled[after][0], clean[after][0])
