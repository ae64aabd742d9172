"""The `meshfg` console script on bad input: one line on stderr, exit code 1, no traceback,
nothing existing overwritten; and each command end to end on small and bundled recordings."""
import json
import os
import shutil
import subprocess

import pytest
from offline_helpers import BAGS, MESHFG, tiny_scenario, write_fake_replay

from meshfg_ros.io.messages import PoseRecord, RosbagsMessageFactory
from meshfg_ros.io.recording import RecordingWriter
from meshfg_ros.synthetic.recordings import write_scenario
from meshfg_ros.topics import POINTS_TOPIC, TOOL_POSE_TOPIC

pytestmark = pytest.mark.slow  # each case runs the meshfg command as a process


def meshfg(*args, timeout=120):
    return subprocess.run([MESHFG, *map(str, args)], capture_output=True, text=True, timeout=timeout)


def assert_one_line_error(completed, command: str, *fragments: str):
    assert completed.returncode == 1, completed.stderr
    assert "Traceback" not in completed.stderr
    lines = [line for line in completed.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, completed.stderr
    assert lines[0].startswith(f"meshfg {command}: error: ")
    for fragment in fragments:
        assert fragment in lines[0]


def snapshot(path):
    """{relative path: bytes} of everything under path."""
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A small truth recording, a fake replay of it, and bad recordings."""
    root = tmp_path_factory.mktemp("cli")
    scenario = tiny_scenario(steps=2, camera=True)
    write_scenario(scenario, root / "truth")
    write_fake_replay(scenario, root / "replay")
    with RecordingWriter(root / "empty"):
        pass
    with RecordingWriter(root / "no_points") as writer:
        writer.write(TOOL_POSE_TOPIC, PoseRecord(1, "world", [0, 0, 0, 0, 0, 0, 1]))
    factory = RosbagsMessageFactory()
    with RecordingWriter(root / "wrong_type") as writer:
        writer.write(TOOL_POSE_TOPIC, factory.make("std_msgs/msg/String", data="not a pose"), 1)
        writer.write(POINTS_TOPIC, factory.make("std_msgs/msg/String", data="not a cloud"), 1)
    shutil.copytree(root / "truth", root / "corrupt")
    (mcap_file,) = (root / "corrupt").glob("*.mcap")
    mcap_file.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)
    (root / "plain_dir").mkdir()
    (root / "surface.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (root / "bad.yaml").write_text("measurment_sigma: 0.001\n")
    return root


@pytest.mark.parametrize("case, fragments", [
    ("missing", ("does not exist",)),
    ("plain_dir", ("is not a rosbag2 recording",)),
    ("empty", ("holds no messages",)),
    ("corrupt", ("corrupt",)),
    ("no_points", ("topic /meshfg/points is not in",)),
    ("wrong_type", ("holds std_msgs/msg/String", "expected geometry_msgs/msg/PoseStamped")),
])
def test_replay_rejects_bad_recordings(recordings, case, fragments):
    completed = meshfg("replay", recordings / case, "--out", recordings / f"out_{case}")
    assert_one_line_error(completed, "replay", *fragments)
    assert not (recordings / f"out_{case}").exists()


def test_replay_rejects_a_mesh_that_is_not_tetrahedral(recordings):
    completed = meshfg("replay", recordings / "truth", "--out", recordings / "out_mesh",
                       "--mesh", recordings / "surface.obj")
    assert_one_line_error(completed, "replay", "surface.obj", "not a tetrahedral mesh")
    assert not (recordings / "out_mesh").exists()


def test_replay_rejects_unknown_parameters(recordings):
    completed = meshfg("replay", recordings / "truth", "--out", recordings / "out_config",
                       "--config", recordings / "bad.yaml")
    assert_one_line_error(completed, "replay", "unknown parameter measurment_sigma (did you mean measurement_sigma?)")
    completed = meshfg("replay", recordings / "truth", "--out", recordings / "out_factors", "--factors", "magic")
    assert_one_line_error(completed, "replay", "factors", "magic")


def test_replay_never_overwrites(recordings):
    before = snapshot(recordings / "replay")
    completed = meshfg("replay", recordings / "truth", "--out", recordings / "replay")
    assert_one_line_error(completed, "replay", "exists already")
    assert snapshot(recordings / "replay") == before


def test_eval_errors(recordings, tmp_path):
    completed = meshfg("eval", recordings / "replay", "--truth", recordings / "replay")
    assert_one_line_error(completed, "eval", "topic /meshfg/ground_truth is not in")
    existing = tmp_path / "metrics.json"
    existing.write_text("keep")
    completed = meshfg("eval", recordings / "replay", "--truth", recordings / "truth", "--json", existing)
    assert_one_line_error(completed, "eval", "File exists", str(existing))
    assert existing.read_text() == "keep"


def test_render_errors(recordings, tmp_path):
    (tmp_path / "mine.png").write_bytes(b"keep")
    completed = meshfg("render", recordings / "replay", "--out", tmp_path)
    assert_one_line_error(completed, "render", "not empty")
    assert snapshot(tmp_path) == {tmp_path.joinpath("mine.png").relative_to(tmp_path): b"keep"}
    completed = meshfg("render", recordings / "corrupt", "--out", tmp_path / "pictures")
    assert_one_line_error(completed, "render", "corrupt")


def test_synth_errors(recordings):
    assert_one_line_error(meshfg("synth", "cube-spin", "--out", recordings / "spin"), "synth",
                          "unknown scenario 'cube-spin'")
    before = snapshot(recordings / "truth")
    assert_one_line_error(meshfg("synth", "cube-translate", "--out", recordings / "truth"), "synth",
                          "exists already")
    assert snapshot(recordings / "truth") == before


def test_demo_refuses_a_non_empty_output(tmp_path):
    (tmp_path / "notes.txt").write_text("keep")
    assert_one_line_error(meshfg("demo", "--out", tmp_path), "demo", "not empty")
    assert (tmp_path / "notes.txt").read_text() == "keep"


def test_a_bad_worker_thread_count_is_refused_before_any_work(tmp_path):
    completed = subprocess.run([MESHFG, "demo", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                               timeout=120, env={**os.environ, "MESHFG_WORKER_THREADS": "0"})
    assert_one_line_error(completed, "demo", "MESHFG_WORKER_THREADS must be a positive integer", "'0'")
    assert not (tmp_path / "out").exists()


def test_usage_error_exits_2():
    completed = meshfg("replay")
    assert completed.returncode == 2 and "Traceback" not in completed.stderr
    assert "the following arguments are required: bag, --out" in completed.stderr


def test_eval_and_render_end_to_end(recordings, tmp_path):
    completed = meshfg("eval", recordings / "replay", "--truth", recordings / "truth", "--json", tmp_path / "m.json",
                       "--samples", "2000")
    assert completed.returncode == 0, completed.stderr
    assert "Table II" in completed.stdout and "Factor Graph" in completed.stdout
    assert json.loads((tmp_path / "m.json").read_text())["scenario"] == "tiny-cube"
    completed = meshfg("render", recordings / "replay", "--out", tmp_path / "pictures", "--truth", recordings / "truth")
    assert completed.returncode == 0, completed.stderr
    assert sorted(p.name for p in (tmp_path / "pictures").iterdir()) == [
        "calibration.png", "convergence.png", "error_per_step.png", "estimate.png", "measurements.png"]


def test_replay_of_a_bundled_recording(tmp_path):
    """The bundled liver recording (the smallest) replayed, evaluated and rendered by the CLI."""
    bag = BAGS / "liver-push"
    config = tmp_path / "fast.yaml"
    config.write_text("max_iterations: 2\nwindow_size: 2\n")
    completed = meshfg("replay", bag, "--out", tmp_path / "out", "--config", config, "--factors", "full",
                       timeout=300)
    assert completed.returncode == 0, completed.stderr
    assert "/meshfg/estimated_mesh x10" in completed.stdout
    completed = meshfg("eval", tmp_path / "out", "--truth", bag, "--samples", "2000", timeout=300)
    assert completed.returncode == 0, completed.stderr
    assert "Scenario liver-push" in completed.stdout and "Measurements" in completed.stdout
    completed = meshfg("render", tmp_path / "out", "--out", tmp_path / "pictures")
    assert completed.returncode == 0, completed.stderr
    assert (tmp_path / "pictures" / "estimate.png").stat().st_size > 10_000
    assert all(line.startswith("wrote ") for line in completed.stdout.splitlines())
