"""Acceptance of the ROS 2 shell: the live pipeline reproduces the offline replay.

simulation_node, estimator_node, bag_player and a downstream recorder run as separate
processes over real DDS (loopback) on a recording; the recorder must receive an estimate for
every cloud, and the last one must equal the offline replay's (same recording, same
parameters) to 1e-9 m. Clouds are played 4x faster than recorded: the estimator then runs
back to back, and the pairing of clouds with predictions must still be exact.
"""
from pathlib import Path

import numpy as np
import pytest

from meshfg_ros.synthetic.scenarios import generate
from meshfg_ros.io.messages import PointCloudRecord
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.benchmarks.latency import LIVE_OVERRIDES, run_live_pipeline
from meshfg_ros.replay import replay_recording
from meshfg_ros.synthetic.recordings import write_scenario
from meshfg_ros.topics import POINTS_TOPIC

pytestmark = pytest.mark.slow  # node processes over DDS

BUNDLED = Path(__file__).resolve().parents[1] / "bags" / "cube-shear-spd"
RATE = 4.0


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """The bundled cube recording, or the same scenario with fewer steps if none is bundled."""
    if (BUNDLED / "metadata.yaml").is_file():
        return BUNDLED
    path = tmp_path_factory.mktemp("bag") / "cube-shear-spd"
    write_scenario(generate("cube-shear-spd", seed=0, steps=6), path, max_points=500)
    return path


@pytest.fixture(scope="module")
def live(recording, tmp_path_factory):
    return run_live_pipeline(recording, tmp_path_factory.mktemp("live"), rate=RATE)


def test_every_cloud_gives_an_estimate_equal_to_the_offline_replay(recording, live):
    with RecordingReader(recording) as reader:
        cloud_stamps = [cloud.stamp_ns for cloud in reader.records(POINTS_TOPIC, PointCloudRecord)]
    replay = replay_recording(recording, LIVE_OVERRIDES)
    assert live.parameters == replay.parameters
    assert live.stamps_ns.tolist() == cloud_stamps == [step.stamp_ns for step in replay.steps]
    assert live.steps.tolist() == list(range(1, len(cloud_stamps) + 1))
    assert not live.degraded.any()  # every cloud was paired with its prediction
    np.testing.assert_allclose(live.final_estimate, replay.final_estimate, rtol=0.0, atol=1e-9)
    for received, step in zip(live.positions, replay.steps, strict=True):
        np.testing.assert_allclose(received, step.result.positions, rtol=0.0, atol=1e-9)
    for received, step in zip(live.position_std, replay.steps, strict=True):  # float32 on the wire
        np.testing.assert_allclose(received, step.result.position_std, rtol=1e-6, atol=1e-12)
    # The estimate moved: the tool sheared the cube.
    assert np.abs(live.final_estimate - replay.initial_mesh.vertices).max() > 5e-3


def test_processes_ran_cleanly_and_latency_was_measured(live):
    assert set(live.exit_codes.values()) == {0}
    for name, log in live.logs.items():
        for sign_of_trouble in ("Traceback", "ERROR", "never retrieved", "never awaited"):
            assert sign_of_trouble not in log, f"{name}:\n{log}"
    assert np.isfinite(live.latency_ms).all() and (live.latency_ms > 0.0).all()
    assert (live.solve_time_ms > 0.0).all()
