"""Synthetic recordings: topics, stamps, labels, metadata, regeneration within a tolerance, independent decoding."""
import dataclasses
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from offline_helpers import BAGS, MESHFG, counting_progress, mkl_installed, tiny_scenario
from rosbags.highlevel import AnyReader

from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS, generate
from meshfg_ros.io.messages import MeshState, PointCloudRecord, PoseRecord, meshfg_typestore
from meshfg_ros.io.pointcloud import decode_pointcloud2
from meshfg_ros.io.recording import RecordingExistsError, RecordingReader
from meshfg_ros.io.scenario_metadata import ScenarioMetadata, read_metadata
from meshfg_ros.synthetic.recordings import scenario_metadata, write_scenario
from meshfg_ros.topics import (
    CAMERA_POSE_TOPIC,
    GROUND_TRUTH_TOPIC,
    INITIAL_MESH_TOPIC,
    POINTS_TOPIC,
    SCENARIO_TOPIC,
    TOOL_POSE_TOPIC,
)

# (bundled recording, seed) as listed in bags/README.md; the fastest one is regenerated below.
BUNDLED = {"cube-shear-spd": 0, "cao-push": 0, "liver-push": 0}
REGENERATED = "liver-push"


@pytest.fixture(scope="module")
def scenario():
    return tiny_scenario(steps=3, camera=True)


@pytest.fixture(scope="module")
def recording(scenario, tmp_path_factory):
    path = tmp_path_factory.mktemp("synth") / "tiny"
    counts = write_scenario(scenario, path)
    return path, counts


def test_topics_and_counts(recording):
    path, counts = recording
    assert counts == {SCENARIO_TOPIC: 1, INITIAL_MESH_TOPIC: 1, GROUND_TRUTH_TOPIC: 4, CAMERA_POSE_TOPIC: 1,
                      TOOL_POSE_TOPIC: 4, POINTS_TOPIC: 3}
    with RecordingReader(path) as reader:
        assert {name: info.count for name, info in reader.topics.items()} == counts


def test_initial_mesh_and_step_zero_pose(recording, scenario):
    path, _ = recording
    with RecordingReader(path) as reader:
        initial = next(reader.records(INITIAL_MESH_TOPIC, MeshState))
        poses = list(reader.records(TOOL_POSE_TOPIC, PoseRecord))
        truths = list(reader.records(GROUND_TRUTH_TOPIC, MeshState))
        camera = next(reader.records(CAMERA_POSE_TOPIC, PoseRecord))
    mesh = scenario.initial_mesh
    assert initial.stamp_ns == FIRST_STAMP_NS and initial.step == 0 and initial.frame_id == "world"
    np.testing.assert_array_equal(initial.positions, mesh.vertices)
    np.testing.assert_array_equal(initial.tetrahedra, mesh.tetrahedra)
    np.testing.assert_array_equal(initial.surface_triangles, mesh.surface_triangles)
    np.testing.assert_array_equal(initial.fixed_vertices, mesh.fixed_vertices)
    assert [p.stamp_ns for p in poses] == [FIRST_STAMP_NS] + [s.stamp_ns for s in scenario.steps]
    np.testing.assert_array_equal(poses[0].pose, scenario.initial_tool_pose)
    np.testing.assert_array_equal(poses[-1].pose, scenario.steps[-1].tool_pose)
    assert [t.step for t in truths] == [0, 1, 2, 3]
    np.testing.assert_array_equal(truths[2].positions, scenario.steps[1].truth)
    np.testing.assert_array_equal(camera.pose, scenario.camera_pose)


def test_clouds_carry_points_and_labels(recording, scenario):
    path, _ = recording
    with AnyReader([path], default_typestore=meshfg_typestore()) as reader:
        connection = next(c for c in reader.connections if c.topic == POINTS_TOPIC)
        messages = [reader.deserialize(raw, connection.msgtype) for _, _, raw in reader.messages([connection])]
    decoded = decode_pointcloud2(messages[1], extra_fields=("label",))
    step = scenario.steps[1]
    np.testing.assert_allclose(decoded.points, step.points, atol=1e-8)  # FLOAT32 at centimetre scale
    np.testing.assert_array_equal(decoded.extra["label"], step.point_labels)
    assert messages[1].header.frame_id == "world"


def test_metadata_round_trip(recording, scenario):
    path, _ = recording
    with RecordingReader(path) as reader:
        metadata = read_metadata(reader)
    assert metadata == scenario_metadata(scenario)
    assert metadata.scenario == "tiny-cube" and metadata.seed == 0
    assert metadata.simulator["tool_radius"] == scenario.simulator_config.tool_radius
    assert metadata.estimator_overrides == {"stiffness_kind": "corotational"}
    assert metadata.observed_triangles is None  # a camera scene


def test_metadata_of_camera_less_scene_lists_observed_faces():
    scenario = tiny_scenario(steps=1, camera=False)
    metadata = ScenarioMetadata.from_json(scenario_metadata(scenario).to_json())
    np.testing.assert_array_equal(metadata.observed_triangles, np.flatnonzero(scenario.observed_triangles))


@pytest.mark.parametrize("text, message", [
    ("not json", "not JSON"),
    ('{"format": 99}', "format 1"),
    ('{"format": 1, "scenario": "x"}', "lacks"),
])
def test_metadata_errors_name_the_problem(text, message):
    with pytest.raises(ValueError, match=message):
        ScenarioMetadata.from_json(text)


def test_max_points_subsamples_reproducibly(scenario, tmp_path):
    write_scenario(scenario, tmp_path / "a", max_points=100)
    write_scenario(scenario, tmp_path / "b", max_points=100)
    clouds = []
    for name in ("a", "b"):
        with RecordingReader(tmp_path / name) as reader:
            clouds.append([c.points for c in reader.records(POINTS_TOPIC, PointCloudRecord)])
            assert read_metadata(reader).max_points == 100
    assert all(len(points) == 100 for points in clouds[0])
    for first, second in zip(*clouds):
        np.testing.assert_array_equal(first, second)
    recorded = {tuple(row) for row in scenario.steps[0].points.astype(np.float32).tolist()}
    kept = [tuple(row) for row in clouds[0][0].astype(np.float32).tolist()]
    assert len(set(kept)) == 100 and set(kept) <= recorded  # distinct points of the step's cloud


def test_never_overwrites(recording, scenario):
    path, _ = recording
    before = {p.name: p.stat().st_mtime_ns for p in path.iterdir()}
    with pytest.raises(RecordingExistsError, match="exists already"):
        write_scenario(scenario, path)
    assert {p.name: p.stat().st_mtime_ns for p in path.iterdir()} == before


def test_independent_mcap_reader_decodes_every_message(recording):
    path, counts = recording
    (mcap_file,) = Path(path).glob("*.mcap")
    seen: dict[str, int] = {}
    with open(mcap_file, "rb") as stream:
        for _, channel, _, message in make_reader(stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == SCENARIO_TOPIC:
                assert json.loads(message.data)["scenario"] == "tiny-cube"
            if channel.topic == INITIAL_MESH_TOPIC:
                assert len(message.positions) == 27 * 3 and len(message.fixed_vertices) == 9
    assert seen == counts


def test_generate_reports_each_truth_step_to_its_progress():
    seen = []
    scenario = generate("cube-translate", seed=0, steps=3, progress=counting_progress(seen))
    assert len(scenario.steps) == 3
    assert seen == [3, "step", "step", "step"]
    generate("cube-translate", seed=0, steps=2)  # the progress belonged to the call that returned
    assert seen == [3, "step", "step", "step"]


def test_bundled_recordings_are_listed_and_small():
    readme = (BAGS / "README.md").read_text()
    for name, seed in BUNDLED.items():
        size = sum(f.stat().st_size for f in (BAGS / name).iterdir())
        assert size < 5 * 2**20, f"{name} is {size} bytes"
        assert f"meshfg synth {name} --out bags/{name} --seed {seed}" in readme
        with RecordingReader(BAGS / name) as reader:
            metadata = read_metadata(reader)
        assert (metadata.scenario, metadata.seed) == (name, seed)


# Geometry that `meshfg synth` computes (simulated ground truth, tool and camera poses, mesh
# vertices, ray-cast points) rounds differently on another CPU or BLAS: CHOLMOD's supernodal
# kernels and numpy's SIMD loops differ in operation order. Regenerating the bundled recordings
# here (AMD EPYC, Zen 4) moved the ground truth by at most 4.9e-16 m with MKL and 3.6e-16 m with
# cvxopt's OpenBLAS (liver-push; cao-push 8.1e-17 m, cube-shear-spd 2.2e-16 m), every other
# message identical. 1 nm allows a million times that, and is still 3e5 times below the
# smallest sensor noise of the bundled scenes (0.3 mm) and 1e3 times below the 1 um a real
# change to a scene moves anything by. Clouds are FLOAT32: a coordinate that moved by rounding
# may land on the neighbouring float32, so they get one float32 spacing more.
GEOMETRY_TOLERANCE_M = 1e-9


def regenerate_bundled(tmp_path, **environment) -> Path:
    """REGENERATED written afresh by `meshfg synth` (its command from bags/README.md)."""
    out = tmp_path / REGENERATED
    with RecordingReader(BAGS / REGENERATED) as reader:
        max_points = read_metadata(reader).max_points
    command = [MESHFG, "synth", REGENERATED, "--out", str(out), "--seed", str(BUNDLED[REGENERATED])]
    if max_points is not None:
        command += ["--max-points", str(max_points)]
    env = {key: value for key, value in os.environ.items() if key != "MESHFG_BLAS"}
    result = subprocess.run(command, check=True, capture_output=True, text=True, timeout=300,
                            env={**env, **environment})
    assert f"synth {REGENERATED} truth" in result.stderr  # its progress bar over the truth's steps
    return out


def recorded_messages(path) -> list:
    """(topic, type, log time, message) of every message, in recorded order."""
    with AnyReader([path], default_typestore=meshfg_typestore()) as reader:
        return [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def largest_differences(expected, actual, where: str, found: dict) -> None:
    """Walk two decoded messages: integers, strings, stamps, counts and labels must be equal;
    float fields may differ, and their largest absolute difference per field goes to `found`
    (clouds: their decoded points, in metres beyond one float32 spacing)."""
    if hasattr(expected, "point_step"):  # sensor_msgs/PointCloud2
        ours, theirs = (decode_pointcloud2(m, extra_fields=("label",)) for m in (expected, actual))
        assert ours.points.shape == theirs.points.shape, where
        np.testing.assert_array_equal(ours.extra["label"], theirs.extra["label"], err_msg=where)
        spacing = np.spacing(np.maximum(np.abs(ours.points), np.abs(theirs.points)).astype(np.float32))
        beyond = np.abs(ours.points - theirs.points) - spacing.astype(np.float64)
        found[f"{where}.points"] = max(found.get(f"{where}.points", 0.0), float(beyond.max(initial=0.0)))
        for name in ("header", "height", "width", "fields", "is_bigendian", "point_step", "is_dense"):
            largest_differences(getattr(expected, name), getattr(actual, name), f"{where}.{name}", found)
    elif dataclasses.is_dataclass(expected):
        for field in dataclasses.fields(expected):
            largest_differences(getattr(expected, field.name), getattr(actual, field.name),
                                f"{where}.{field.name}", found)
    elif isinstance(expected, list):
        assert len(expected) == len(actual), where
        for index, (ours, theirs) in enumerate(zip(expected, actual)):
            largest_differences(ours, theirs, f"{where}[{index}]", found)
    elif isinstance(expected, (float, np.ndarray)) and np.asarray(expected).dtype.kind == "f":
        assert np.shape(expected) == np.shape(actual), where
        difference = float(np.max(np.abs(np.asarray(expected) - np.asarray(actual)), initial=0.0))
        found[where] = max(found.get(where, 0.0), difference)
    elif isinstance(expected, np.ndarray):
        np.testing.assert_array_equal(expected, actual, err_msg=where)
    else:
        assert expected == actual, where


def assert_messages_match(bundled: list, regenerated: list) -> dict:
    """The same messages in the same order with the same stamps, integers and text; floating-point
    geometry within GEOMETRY_TOLERANCE_M. Returns the largest difference per field."""
    assert [m[:3] for m in regenerated] == [m[:3] for m in bundled] and bundled
    found: dict[str, float] = {}
    for (topic, _, _, ours), (_, _, _, theirs) in zip(bundled, regenerated):
        largest_differences(ours, theirs, topic, found)
    too_far = {field: value for field, value in found.items() if value > GEOMETRY_TOLERANCE_M}
    assert not too_far, too_far
    return found


@pytest.mark.slow
@pytest.mark.parametrize("blas", ["bundled", "mkl"])
def test_regenerated_recording_matches_the_bundled_one(tmp_path, blas):
    """`meshfg synth` gives the bundled recording again, with CHOLMOD on cvxopt's OpenBLAS or on
    MKL (MESHFG_BLAS; the default is one of the two): identical topics, stamps, counts, labels
    and text, geometry within GEOMETRY_TOLERANCE_M (1 nm; measured on an AMD EPYC: at most
    4.9e-16 m, see above)."""
    if blas == "mkl" and not mkl_installed():
        pytest.skip("the mkl package is not installed (x86-64 Linux only)")
    regenerated = recorded_messages(regenerate_bundled(tmp_path, MESHFG_BLAS=blas))
    found = assert_messages_match(recorded_messages(BAGS / REGENERATED), regenerated)
    assert f"{GROUND_TRUTH_TOPIC}.positions" in found and f"{POINTS_TOPIC}.points" in found  # compared


def test_the_comparison_catches_a_vertex_moved_by_ten_times_the_tolerance():
    bundled = recorded_messages(BAGS / REGENERATED)
    last_truth = max(index for index, message in enumerate(bundled) if message[0] == GROUND_TRUTH_TOPIC)
    moved = list(bundled)
    topic, msgtype, log_time, message = moved[last_truth]
    positions = message.positions.copy()
    positions[7] += 10 * GEOMETRY_TOLERANCE_M
    moved[last_truth] = (topic, msgtype, log_time, dataclasses.replace(message, positions=positions))
    assert assert_messages_match(bundled, bundled)[f"{GROUND_TRUTH_TOPIC}.positions"] == 0.0
    with pytest.raises(AssertionError, match="ground_truth.positions"):
        assert_messages_match(bundled, moved)
