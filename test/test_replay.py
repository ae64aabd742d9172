"""Offline replay: the nodes' loop semantics, parameters, outputs and their independent decoding."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from offline_helpers import NOISE_SIGMA, TOOL_RADIUS, tiny_scenario

from meshfg_ros.core.physics.body_load import BodyLoadEstimate
from meshfg_ros.core.physics.model_fit import learn
from meshfg_ros.core.physics.poisson_ratio import PoissonRatioEstimate
from meshfg_ros.core.estimation.estimator import SlidingWindowEstimator
from meshfg_ros.core.geometry.mesh import MeshFileError, save_mesh
from meshfg_ros.parameters import ParameterError, estimator_config, simulator_config
from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS, STEP_PERIOD_NS
from meshfg_ros.core.physics.simulator import ElasticSimulator
from meshfg_ros.io.messages import MeshState, PointCloudRecord, PoseRecord, StatusRecord, stamp_ns_from_msg
from meshfg_ros.io.recording import RecordingExistsError, RecordingReader, RecordingWriter
from meshfg_ros.markers import MAX_ELLIPSOIDS, NAMESPACE_ELLIPSOIDS, NAMESPACE_LEGEND
from meshfg_ros.replay import (
    ReplayError,
    config_overrides,
    load_inputs,
    replay_parameters,
    replay_recording,
    scenario_parameters,
    write_replay,
)
from meshfg_ros.synthetic.recordings import write_scenario
from meshfg_ros.topics import (
    BODY_ACCELERATION_TOPIC,
    CAMERA_POSE_TOPIC,
    COST_HISTORY_TOPIC,
    ESTIMATED_MESH_TOPIC,
    INITIAL_MESH_TOPIC,
    MARKERS_TOPIC,
    POINTS_TOPIC,
    PREDICTED_MESH_TOPIC,
    SCENARIO_TOPIC,
    SIMULATION_ONLY_MESH_TOPIC,
    STATUS_TOPIC,
    TOOL_POSE_TOPIC,
)

# The truth of the tiny scene is the nominal model, so every correction is noise and none persists:
# the published estimates would be the predictions (core/estimation/persistence.py), and the closed loop the
# open one. Publishing the optimum keeps the loop's semantics visible.
FAST = {"max_iterations": 3, "keep_persistent_correction": False}


@pytest.fixture(scope="module")
def scenario():
    return tiny_scenario(steps=3, camera=True)


@pytest.fixture(scope="module")
def recording(scenario, tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "tiny"
    write_scenario(scenario, path)
    return path


@pytest.fixture(scope="module")
def replayed(recording):
    return replay_recording(recording, FAST)


def test_parameters_come_from_the_recording_then_the_overrides(recording, tmp_path):
    inputs = load_inputs(recording)
    params = replay_parameters(inputs)
    assert params["tool_radius"] == TOOL_RADIUS and params["tool_mode"] == "sphere"
    assert params["measurement_sigma"] == NOISE_SIGMA
    assert params["simulator_substeps"] == 4 and params["stiffness_kind"] == "corotational"
    assert params["camera_pose"] == tuple(inputs.camera_pose.pose)
    flat = tmp_path / "flat.yaml"
    flat.write_text("measurement_sigma: 0.002\nwindow_size: 2\n")
    ros = tmp_path / "ros.yaml"
    ros.write_text("/**:\n  ros__parameters:\n    tool_radius: 0.004\n    use_sim_time: false\n")
    assert config_overrides(flat) == {"measurement_sigma": 0.002, "window_size": 2}
    assert config_overrides(ros) == {"tool_radius": 0.004}
    overridden = replay_parameters(inputs, {**config_overrides(flat), "factors": "simulation+measurement"})
    assert overridden["measurement_sigma"] == 0.002 and overridden["window_size"] == 2
    assert overridden["factors"] == "simulation+measurement" and overridden["tool_radius"] == TOOL_RADIUS
    bad = tmp_path / "bad.yaml"
    bad.write_text("measurment_sigma: 0.002\n")
    with pytest.raises(ParameterError, match="measurment_sigma"):
        config_overrides(bad)


def test_a_nominal_model_the_nodes_cannot_express_is_rejected(recording):
    metadata = load_inputs(recording).metadata
    assert scenario_parameters(metadata)["simulator_iterations"] == 4
    sagging = replace(metadata, simulator={**metadata.simulator, "gravity": [0.0, -9.81, 0.0]})
    with pytest.raises(ReplayError, match="gravity"):
        scenario_parameters(sagging)


def test_loop_matches_the_nodes_semantics(scenario, recording, replayed):
    """First pose resets; each later pose predicts from the latest estimate; the cloud at t
    pairs with the prediction and the tool pose stamped t; the estimate feeds the next prediction,
    and its correction of the prediction the body load and the Poisson ratio the next predictions
    apply."""
    inputs = load_inputs(recording)
    params = replayed.parameters
    mesh = scenario.initial_mesh
    simulator = ElasticSimulator(mesh, simulator_config(params))
    body_load, poisson_ratio = BodyLoadEstimate(simulator), PoissonRatioEstimate(simulator)
    estimator = SlidingWindowEstimator(mesh, estimator_config(params))
    simulator.reset(scenario.initial_tool_pose)
    estimate = mesh.vertices
    viewpoint = np.asarray(inputs.camera_pose.pose)[:3]  # the camera's centre: the clouds' sensor
    assert len(replayed.steps) == len(scenario.steps) == 3
    for step, cloud, replay_step in zip(scenario.steps, inputs.clouds, replayed.steps):
        predicted = simulator.predict(estimate, step.tool_pose, STEP_PERIOD_NS / 1e9)
        result = estimator.update(step.stamp_ns, cloud.points, predicted, step.tool_pose, viewpoint)
        estimate = result.positions
        # The simulator learns from the std as the estimate message carries it (float32).
        learn(mesh, body_load, poisson_ratio, predicted, estimate, result.position_std.astype(np.float32).astype(float))
        np.testing.assert_array_equal(replay_step.body_acceleration, body_load.acceleration)
        assert replay_step.stamp_ns == step.stamp_ns and not replay_step.result.degraded
        np.testing.assert_array_equal(replay_step.predicted, predicted)
        np.testing.assert_array_equal(replay_step.result.positions, result.positions)
    np.testing.assert_array_equal(replayed.final_estimate, estimate)


def test_simulation_only_runs_open_loop(scenario, replayed):
    simulator = ElasticSimulator(scenario.initial_mesh, simulator_config(replayed.parameters))
    simulator.reset(scenario.initial_tool_pose)
    state = scenario.initial_mesh.vertices
    for step, replay_step in zip(scenario.steps, replayed.steps):
        state = simulator.predict(state, step.tool_pose, 1.0)
        np.testing.assert_array_equal(replay_step.simulation_only, state)
    # the truth here is the nominal model itself: the open loop reproduces it
    np.testing.assert_allclose(replayed.steps[-1].simulation_only, scenario.steps[-1].truth, atol=1e-9)
    assert not np.array_equal(replayed.steps[-1].predicted, replayed.steps[-1].simulation_only)


def _write_inputs(path: Path, scenario, clouds_first: bool, cloud_shift_ns: int = 0, empty_step: int | None = None):
    """Tool poses and clouds of `scenario`, clouds logged before the poses of equal stamp if asked."""
    mesh = scenario.initial_mesh
    with RecordingWriter(path) as writer:
        writer.write(INITIAL_MESH_TOPIC, MeshState(FIRST_STAMP_NS, "world", 0, mesh.vertices, mesh.tetrahedra,
                                                   mesh.surface_triangles, mesh.fixed_vertices))
        writer.write(TOOL_POSE_TOPIC, PoseRecord(FIRST_STAMP_NS, "world", scenario.initial_tool_pose))
        for index, step in enumerate(scenario.steps):
            points = np.zeros((0, 3)) if index == empty_step else step.points
            records = [(POINTS_TOPIC, PointCloudRecord(step.stamp_ns + cloud_shift_ns, "world", points)),
                       (TOOL_POSE_TOPIC, PoseRecord(step.stamp_ns, "world", step.tool_pose))]
            for topic, record in (records if clouds_first else records[::-1]):
                writer.write(topic, record, step.stamp_ns)


def test_pose_before_cloud_at_equal_stamps(scenario, replayed, tmp_path):
    _write_inputs(tmp_path / "reordered", scenario, clouds_first=True)
    params = {**FAST, "tool_radius": TOOL_RADIUS, "measurement_sigma": NOISE_SIGMA, "simulator_substeps": 4,
              "simulator_iterations": 4}
    result = replay_recording(tmp_path / "reordered", params)
    assert [s.predicted is not None for s in result.steps] == [True, True, True]
    np.testing.assert_array_equal(result.steps[0].predicted, replayed.steps[0].predicted)


def test_clouds_between_tool_poses_get_the_interpolated_pose(scenario, replayed, tmp_path):
    _write_inputs(tmp_path / "offset", scenario, clouds_first=False, cloud_shift_ns=3_000_000)
    result = replay_recording(tmp_path / "offset", {**FAST, "tool_radius": TOOL_RADIUS,
                                                     "measurement_sigma": NOISE_SIGMA, "simulator_substeps": 4,
                                                     "simulator_iterations": 4})
    assert [s.predicted is not None for s in result.steps] == [True, True, True]
    assert not any(s.result.degraded for s in result.steps)
    # the tool moves little in 3 ms of a 1 s step: the estimates stay close to the exact-stamp replay
    for shifted, exact in zip(result.steps, replayed.steps):
        assert 0 < np.abs(shifted.predicted - exact.predicted).max() < 1e-4


def test_a_cloud_beyond_the_tool_pose_horizon_runs_degraded(scenario, tmp_path):
    _write_inputs(tmp_path / "late", scenario, clouds_first=False, cloud_shift_ns=STEP_PERIOD_NS // 2)
    result = replay_recording(tmp_path / "late", FAST)
    # the first two clouds lie between two tool poses; the last is 0.5 s past the newest one
    assert [s.predicted is None for s in result.steps] == [False, False, True]
    assert [s.result.degraded for s in result.steps] == [False, False, True]


def test_empty_clouds_are_skipped(scenario, tmp_path):
    _write_inputs(tmp_path / "empty", scenario, clouds_first=False, empty_step=1)
    result = replay_recording(tmp_path / "empty", FAST)
    assert [s.stamp_ns for s in result.steps] == [scenario.steps[0].stamp_ns, scenario.steps[2].stamp_ns]
    assert [s.result.step for s in result.steps] == [1, 2]


def test_mesh_file_replaces_the_recorded_mesh(scenario, recording, replayed, tmp_path):
    save_mesh(scenario.initial_mesh.with_fixed(scenario.initial_mesh.fixed_vertices), tmp_path / "cube.vtu")
    result = replay_recording(recording, FAST, mesh_path=tmp_path / "cube.vtu")
    np.testing.assert_allclose(result.final_estimate, replayed.final_estimate, atol=1e-12)
    (tmp_path / "surface.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshFileError, match="not a tetrahedral mesh"):
        load_inputs(recording, tmp_path / "surface.obj")


@pytest.fixture(scope="module")
def output(recording, tmp_path_factory):
    out = tmp_path_factory.mktemp("replay_out") / "out"
    counts = write_replay(recording, out, FAST)
    return out, counts


def test_outputs_and_copies(output, replayed, scenario):
    out, counts = output
    assert counts == {SCENARIO_TOPIC: 1, CAMERA_POSE_TOPIC: 1, INITIAL_MESH_TOPIC: 1, TOOL_POSE_TOPIC: 4,
                      POINTS_TOPIC: 3, PREDICTED_MESH_TOPIC: 3, SIMULATION_ONLY_MESH_TOPIC: 3,
                      ESTIMATED_MESH_TOPIC: 3, STATUS_TOPIC: 3, COST_HISTORY_TOPIC: 3, MARKERS_TOPIC: 3,
                      BODY_ACCELERATION_TOPIC: 3}
    with RecordingReader(out) as reader:
        estimates = list(reader.records(ESTIMATED_MESH_TOPIC, MeshState))
        statuses = list(reader.records(STATUS_TOPIC, StatusRecord))
        histories = [m.data.data for m in reader.messages([COST_HISTORY_TOPIC])]
        loads = [m.data for m in reader.messages([BODY_ACCELERATION_TOPIC])]
    final = replayed.steps[-1].result
    assert [stamp_ns_from_msg(load.header.stamp) for load in loads] == [step.stamp_ns for step in replayed.steps]
    np.testing.assert_array_equal([[load.vector.x, load.vector.y, load.vector.z] for load in loads],
                                  [step.body_acceleration for step in replayed.steps])
    np.testing.assert_array_equal(estimates[-1].positions, final.positions)
    np.testing.assert_allclose(estimates[-1].position_std, final.position_std)
    # Every estimate with its covariance, as float32: each entry within float32's rounding of the
    # estimator's (24 bits), symmetric, zero on the fixed vertices only.
    assert len(estimates) == len(replayed.steps)
    for estimate, step in zip(estimates, replayed.steps, strict=True):
        expected = step.result.position_covariance
        assert estimate.position_covariance.shape == expected.shape == (scenario.initial_mesh.vertex_count, 3, 3)
        np.testing.assert_allclose(estimate.position_covariance, expected, rtol=2**-24, atol=0.0)
        np.testing.assert_array_equal(estimate.position_covariance, estimate.position_covariance.transpose(0, 2, 1))
        variances = np.einsum("vii->vi", estimate.position_covariance)
        fixed = np.isin(np.arange(len(variances)), scenario.initial_mesh.fixed_vertices)
        assert not variances[fixed].any() and (variances[~fixed] > 0.0).all()
    assert estimates[-1].stamp_ns == scenario.steps[-1].stamp_ns and estimates[-1].step == final.step
    assert [s.iterations for s in statuses] == [s.result.iterations for s in replayed.steps]
    np.testing.assert_array_equal(histories[-1], final.cost_history)
    assert statuses[-1].final_cost == final.final_cost and statuses[-1].num_points == final.num_points


def test_outputs_decode_with_an_independent_reader(output, scenario):
    out, counts = output
    (mcap_file,) = Path(out).glob("*.mcap")
    seen: dict[str, int] = {}
    log_times = []
    with open(mcap_file, "rb") as stream:
        for _, channel, message, decoded in make_reader(stream, decoder_factories=[DecoderFactory()]) \
                .iter_decoded_messages(log_time_order=False):
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            log_times.append(message.log_time)
            if channel.topic == MARKERS_TOPIC:
                surface, wireframe, cloud = decoded.markers[:3]
                assert len(surface.points) == 3 * len(scenario.initial_mesh.surface_triangles)
                assert len(cloud.points) == len(scenario.steps[0].points)
                ellipsoids = [m for m in decoded.markers if m.ns == NAMESPACE_ELLIPSOIDS]
                free_surface = np.setdiff1d(scenario.initial_mesh.surface_vertices,
                                            scenario.initial_mesh.fixed_vertices)
                assert len(ellipsoids) == min(len(free_surface), MAX_ELLIPSOIDS)
                assert any(m.ns == NAMESPACE_LEGEND and m.text.endswith(" mm") for m in decoded.markers)
            if channel.topic == ESTIMATED_MESH_TOPIC:
                assert len(decoded.position_covariance) == 6 * scenario.initial_mesh.vertex_count
            if channel.topic == POINTS_TOPIC:
                assert [f.name for f in decoded.fields] == ["x", "y", "z", "label"]  # copied verbatim
    assert seen == counts
    assert log_times == sorted(log_times)  # written in time order


def test_existing_output_is_never_overwritten(recording, output):
    out, _ = output
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(RecordingExistsError, match="exists already"):
        write_replay(recording, out, FAST)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
