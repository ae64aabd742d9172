"""Evaluation (the paper's metrics, observable split, calibration of the published std, tables,
JSON) and pictures of a replay."""
import dataclasses
import json

import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.colors import Normalize
from matplotlib.image import imread
from offline_helpers import tiny_scenario, write_fake_replay
from scipy.stats import chi2

from meshfg_ros import cli
from meshfg_ros.evaluation.metrics import vertex_rmse
from meshfg_ros.evaluation.evaluate import (
    CALIBRATION_SETS,
    CORRECTION_QUANTITIES,
    CORRECTION_SETS,
    EvaluationError,
    evaluate,
    evaluate_recordings,
    evaluated_faces,
    format_tables,
    load_inputs,
    write_json,
)
from meshfg_ros.io.messages import MeshState
from meshfg_ros.io.recording import RecordingReader
from meshfg_ros.topics import ESTIMATED_MESH_TOPIC
from meshfg_ros.evaluation.render import OutputDirectoryError, _estimate_figure, render, write_calibration_plot
from meshfg_ros.synthetic.recordings import write_scenario

SAMPLES = 4000
OFFSET = 1e-3  # the fake estimate is the truth shifted 1 mm up
PUBLISHED_STD = float(np.float32(1e-4))  # write_fake_replay's position_std, as the message's float32 holds it


@pytest.fixture(scope="module")
def camera_scene(tmp_path_factory):
    """(scenario, truth recording, fake replay) of the small cube seen by a camera from above."""
    scenario = tiny_scenario(steps=3, camera=True)
    root = tmp_path_factory.mktemp("camera")
    write_scenario(scenario, root / "truth")
    write_fake_replay(scenario, root / "replay", estimate_offset=OFFSET)
    return scenario, root / "truth", root / "replay"


@pytest.fixture(scope="module")
def evaluation(camera_scene):
    _, truth, replay = camera_scene
    return evaluate_recordings(replay, truth, samples=SAMPLES)


def test_fixed_faces_are_left_out(camera_scene):
    scenario = camera_scene[0]
    mesh = scenario.initial_mesh
    state = MeshState(0, "world", 0, mesh.vertices, mesh.tetrahedra, mesh.surface_triangles, mesh.fixed_vertices)
    faces = evaluated_faces(state)
    bottom = np.isclose(mesh.vertices[mesh.surface_triangles][:, :, 2], 0.0).all(axis=1)
    assert bottom.sum() == 8
    np.testing.assert_array_equal(faces, ~bottom)


def test_vertex_rmse_of_both_methods(camera_scene, evaluation):
    scenario = camera_scene[0]
    mesh = scenario.initial_mesh
    free = mesh.free_vertices
    vertex = evaluation["vertex_rmse"]
    assert vertex["factor_graph"]["all"]["per_step"] == pytest.approx([OFFSET] * 3, rel=1e-9)
    expected = [vertex_rmse(mesh.vertices, step.truth, free) for step in scenario.steps]
    assert vertex["simulation"]["all"]["per_step"] == pytest.approx(expected, rel=1e-9)
    assert vertex["simulation"]["all"]["final"] == pytest.approx(expected[-1], rel=1e-9)
    assert vertex["simulation"]["all"]["mean"] == pytest.approx(np.mean(expected), rel=1e-9)
    assert vertex["simulation"]["all"]["std"] == pytest.approx(np.std(expected), rel=1e-9)


def test_unobserved_external_vertices_are_below_the_top(camera_scene, evaluation):
    """The camera above sees only the top face: unobserved external = free surface vertices below it."""
    scenario = camera_scene[0]
    mesh, truth = scenario.initial_mesh, scenario.steps[-1].truth
    external = np.intersect1d(mesh.surface_vertices, mesh.free_vertices)
    hidden = external[mesh.vertices[external, 2] < 0.02 - 1e-9]
    expected = vertex_rmse(mesh.vertices, truth, hidden)
    assert evaluation["vertex_rmse"]["simulation"]["unobserved_external"]["final"] == pytest.approx(expected, rel=1e-9)


def test_surface_metrics_see_the_shift(evaluation):
    surface = evaluation["surface"]["factor_graph"]
    # Shifted 1 mm along z: the top moves 1 mm off; vertical sides slide onto themselves.
    assert 0.9e-3 < surface["observable"]["rmse"]["final"] < 1.1e-3
    assert surface["full"]["chamfer"]["final"] < surface["observable"]["chamfer"]["final"]
    assert evaluation["units"] == "m" and len(evaluation["stamps_ns"]) == 3


def test_measurement_row_is_the_cloud_against_the_observable_truth(camera_scene, evaluation):
    measured = evaluation["surface"]["measurements"]
    assert set(measured) == {"observable"}
    # The cloud holds +x/+y side points the camera cannot see: its one-sided RMSE to the
    # observable (top) truth is of the order of the side depth, far above the 0.2 mm noise.
    assert measured["observable"]["rmse"]["final"] > 2e-3
    assert measured["observable"]["chamfer"]["final"] > evaluation["surface"]["factor_graph"]["observable"][
        "chamfer"]["final"]


def test_camera_less_scene_splits_by_observed_faces(tmp_path):
    scenario = tiny_scenario(steps=2, camera=False)
    write_scenario(scenario, tmp_path / "truth")
    write_fake_replay(scenario, tmp_path / "replay")
    result = evaluate(load_inputs(tmp_path / "replay", tmp_path / "truth"), samples=SAMPLES)
    assert set(result["surface"]["factor_graph"]) == {"full", "unobserved", "observable"}
    assert result["vertex_rmse"]["factor_graph"]["unobserved_external"]["final"] == 0.0
    # unobserved external = the free vertices of the -x and -y faces only
    mesh, truth = scenario.initial_mesh, scenario.steps[-1].truth
    free = mesh.free_vertices
    hidden = free[(np.isclose(mesh.vertices[free, 0], 0.0) | np.isclose(mesh.vertices[free, 1], 0.0))
                  & (mesh.vertices[free, 2] < 0.02 - 1e-9) & (mesh.vertices[free, 0] < 0.02 - 1e-9)
                  & (mesh.vertices[free, 1] < 0.02 - 1e-9)]
    assert result["vertex_rmse"]["simulation"]["unobserved_external"]["final"] == pytest.approx(
        vertex_rmse(mesh.vertices, truth, hidden), rel=1e-9)


def test_correction_of_the_prediction_is_compared_with_the_truths(tmp_path):
    """Predictions off the truth by (1, 0, -2) mm. Where the scene is observed the estimate makes
    the needed correction's component along the vertex normal only; where it is not (the -x and
    -y faces of the camera-less scene), none. So: along the normal, alignment and gain 1; across
    it gain 0; on the unobserved vertices no correction (n/a). Taking the wrong vertex set or the
    wrong directions gives other values; the second step has no prediction (a degraded step)
    and keeps its place as n/a."""
    scenario = tiny_scenario(steps=2, camera=False)
    mesh = scenario.initial_mesh
    free = mesh.free_vertices
    hidden = free[(np.isclose(mesh.vertices[free, 0], 0.0) | np.isclose(mesh.vertices[free, 1], 0.0))
                  & (mesh.vertices[free, 2] < 0.02 - 1e-9) & (mesh.vertices[free, 0] < 0.02 - 1e-9)
                  & (mesh.vertices[free, 1] < 0.02 - 1e-9)]
    truth = scenario.steps[0].truth
    prediction = truth + [1e-3, 0.0, -2e-3]
    normals = mesh.vertex_normals(prediction)
    needed_along = np.einsum("ij,ij->i", truth - prediction, normals)
    estimate = prediction + needed_along[:, None] * normals
    estimate[hidden] = prediction[hidden]
    write_scenario(scenario, tmp_path / "truth")
    write_fake_replay(scenario, tmp_path / "replay", estimates=[estimate, scenario.steps[1].truth],
                      predictions=[prediction])
    evaluation = evaluate_recordings(tmp_path / "replay", tmp_path / "truth", samples=SAMPLES)
    correction = evaluation["correction"]
    assert set(correction) == set(CORRECTION_SETS)
    assert correction["observed_normal"]["alignment"]["per_step"] == [pytest.approx(1.0, abs=1e-9), None]
    assert correction["observed_normal"]["gain"]["per_step"] == [pytest.approx(1.0, abs=1e-9), None]
    # Across the normal the correction is rounding noise (its direction, the alignment, too).
    assert correction["observed_tangential"]["gain"]["per_step"] == [pytest.approx(0.0, abs=1e-9), None]
    for quantity in CORRECTION_QUANTITIES:
        assert correction["unobserved_external"][quantity]["per_step"] == [None, None], quantity
    assert "observed normal: alignment n/a (1.00), gain n/a (1.00)" in format_tables(evaluation)


def test_no_correction_without_predictions(evaluation):
    assert "correction" not in evaluation


def test_recordings_that_do_not_match_are_rejected(camera_scene, tmp_path):
    other = tiny_scenario(steps=2, camera=True)
    shifted = type(other)(**{**other.__dict__, "steps": tuple(
        type(s)(s.stamp_ns + 500_000_000, s.tool_pose, s.points, s.point_labels, s.truth) for s in other.steps)})
    write_fake_replay(shifted, tmp_path / "replay")
    with pytest.raises(EvaluationError, match="same stamp"):
        load_inputs(tmp_path / "replay", camera_scene[1])


def test_tables_and_json(evaluation, tmp_path):
    text = format_tables(evaluation)
    for expected in ("Table II", "Table III", "Factor Graph", "Simulation", "Measurements", "Unobserved d_CD",
                     "Vertex RMSE"):
        assert expected in text
    final_mm = evaluation["surface"]["factor_graph"]["observable"]["rmse"]["final"] * 1e3
    assert f"{final_mm:.2f} (" in text
    write_json(evaluation, tmp_path / "metrics.json")
    assert json.loads((tmp_path / "metrics.json").read_text()) == json.loads(json.dumps(evaluation))
    with pytest.raises(FileExistsError):
        write_json(evaluation, tmp_path / "metrics.json")


def test_render_writes_pictures(camera_scene, evaluation, tmp_path):
    _, truth, replay = camera_scene
    written = render(replay, tmp_path / "pictures", truth, evaluation)
    assert "calibration" in evaluation  # the replay publishes position_std on the truth's mesh
    assert [p.name for p in written] == ["estimate.png", "measurements.png", "error_per_step.png", "calibration.png",
                                         "convergence.png"]
    for path in written:
        image = imread(path)
        assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 300
        assert image[..., :3].std() > 0.01  # not a blank canvas


def test_render_without_truth_colours_by_std(camera_scene, tmp_path):
    written = render(camera_scene[2], tmp_path / "pictures")
    assert [p.name for p in written] == ["estimate.png", "measurements.png", "convergence.png"]
    with RecordingReader(camera_scene[2]) as reader:
        final = list(reader.records(ESTIMATED_MESH_TOPIC, MeshState))[-1]
    # A std that grows along x, so that the faces' colours must differ.
    x = final.positions[:, 0]
    final = dataclasses.replace(final, position_std=1e-4 * (1.0 + (x - x.min()) / np.ptp(x)),
                                position_covariance=np.zeros((0, 3, 3)))
    faces = final.surface_triangles[evaluated_faces(final)]
    figure = _estimate_figure({"factor graph": final}, None, faces)
    (surface,) = [c for c in figure.axes[0].collections if len(c.get_facecolor()) == len(faces)]
    face_std_mm = 1e3 * final.position_std[faces].mean(axis=1)
    expected = colormaps["coolwarm"](Normalize(0.0, 1e3 * final.position_std.max())(face_std_mm))
    assert np.ptp(expected[:, 0]) > 0.2  # from blue towards red
    # Each face's own colour: the collection keeps them in the faces' order (_facecolor3d) and
    # hands them out sorted by depth for drawing (get_facecolor).
    np.testing.assert_allclose(surface._facecolor3d, expected, atol=1e-12)
    assert figure.axes[-1].get_ylabel() == "posterior std (mm)"


def test_render_refuses_a_non_empty_directory(camera_scene, tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(OutputDirectoryError, match="not empty"):
        render(camera_scene[2], tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    assert (tmp_path / "keep.txt").read_text() == "mine"


def vertex_sets(mesh):
    """The camera scene's free vertices, free external ones on the top face (the camera's view)
    and below it (unobserved)."""
    free = mesh.free_vertices
    external = np.intersect1d(mesh.surface_vertices, free)
    top = mesh.vertices[external, 2] > 0.02 - 1e-9
    return free, external[top], external[~top]


def test_calibration_of_the_shifted_estimate(camera_scene, evaluation):
    """Every error 1 mm, every published std 0.1 mm: NEES 100 on every vertex of every set, none
    inside even its 99 % ellipsoid; the same std observed and unobserved (ratio 1)."""
    free, observed, unobserved = vertex_sets(camera_scene[0].initial_mesh)
    section = evaluation["calibration"]
    assert section["pooled_from_step"] == 3 and set(section["sets"]) == set(CALIBRATION_SETS)
    counts = {"all": len(free), "observed_external": len(observed), "unobserved_external": len(unobserved)}
    for name, sets in section["sets"].items():
        assert len(sets["per_step"]) == 3
        for summary in (sets["final"], sets["pooled"], *sets["per_step"]):
            assert summary["vertices"] == counts[name] and summary["left_out"] == 0
            assert summary["mean_nees"] == pytest.approx((OFFSET / PUBLISHED_STD) ** 2, rel=1e-9)
            assert summary["coverage_95"] == 0.0 and summary["reliability"]["empirical"][-1] == 0.0
            assert summary["median_std_m"] == pytest.approx(PUBLISHED_STD, rel=1e-12)
            assert summary["median_error_m"] == pytest.approx(OFFSET, rel=1e-9)
    assert section["std_ratio_unobserved_observed"] == {"final": 1.0, "pooled": 1.0}
    assert section["error_ratio_unobserved_observed"]["pooled"] == pytest.approx(1.0, rel=1e-12)
    text = format_tables(evaluation)
    assert "Calibration of the factor graph's position_std" in text and "(steps 3-3 pooled)" in text
    row = next(line for line in text.splitlines() if line.startswith("unobserved external "))
    assert row.split()[2:5] == [f"{len(unobserved)}", f"({len(unobserved)})", "100.00"]
    assert "100.00 (100.00)" in row and "0.000 (0.000)" in row and "0.1000 (0.1000)" in row


def test_calibration_is_per_set_at_the_final_step_and_pooled_from_the_third(tmp_path):
    """Four steps; at step k the error of every vertex is sqrt(k) published stds on the top face
    and inside, sqrt(4 k) below the top (NEES k and 4 k). Final (step 4): NEES 4 and 16; pooled
    over steps 3 and 4 (not 1 and 2): 3.5 and 14, and over all free vertices the vertex-weighted
    mean. Coverage of the 95 % ellipsoid (NEES <= 7.815): the top at every step, below the top at
    none of steps 3 and 4."""
    scenario = tiny_scenario(steps=4, camera=True)
    mesh = scenario.initial_mesh
    free, observed, unobserved = vertex_sets(mesh)
    below = np.zeros(mesh.vertex_count, bool)
    below[unobserved] = True
    estimates = []
    for k, step in enumerate(scenario.steps, start=1):
        nees = np.where(below, 4.0 * k, float(k))
        direction = np.random.default_rng(k).normal(size=(mesh.vertex_count, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        estimates.append(step.truth + direction * (PUBLISHED_STD * np.sqrt(nees))[:, None])
    write_scenario(scenario, tmp_path / "truth")
    write_fake_replay(scenario, tmp_path / "replay", estimates=estimates)
    section = evaluate_recordings(tmp_path / "replay", tmp_path / "truth", samples=SAMPLES)["calibration"]["sets"]
    others = len(free) - len(unobserved)
    expected = {"observed_external": (4.0, 3.5), "unobserved_external": (16.0, 14.0),
                "all": ((others * 4 + len(unobserved) * 16) / len(free),
                        (others * 3.5 + len(unobserved) * 14) / len(free))}
    for name, (final, pooled) in expected.items():
        assert section[name]["final"]["mean_nees"] == pytest.approx(final, rel=1e-6), name
        assert section[name]["pooled"]["mean_nees"] == pytest.approx(pooled, rel=1e-6), name
        assert section[name]["pooled"]["vertices"] == 2 * section[name]["final"]["vertices"]
        per_step = [summary["mean_nees"] for summary in section[name]["per_step"]]
        assert per_step == pytest.approx([final * k / 4 for k in range(1, 5)], rel=1e-6)
    assert section["observed_external"]["pooled"]["coverage_95"] == 1.0
    assert section["unobserved_external"]["pooled"]["coverage_95"] == 0.0
    assert section["all"]["pooled"]["coverage_95"] == pytest.approx(others / len(free))
    # Step 1 below the top: NEES 4, inside the 95 % ellipsoid, outside the 50 % one (chi2(3) median 2.37).
    reliability = section["unobserved_external"]["per_step"][0]["reliability"]
    assert chi2.ppf(0.5, 3) < 4.0 < chi2.ppf(0.95, 3)
    assert reliability["empirical"][reliability["nominal"].index(0.5)] == 0.0
    assert reliability["empirical"][reliability["nominal"].index(0.95)] == 1.0


def test_calibration_json_is_strict_and_the_plot_is_drawn(evaluation, tmp_path):
    json.dumps(evaluation["calibration"], allow_nan=False)
    path = write_calibration_plot(evaluation, tmp_path / "calibration.png")
    image = imread(path)
    assert image.ndim == 3 and image.shape[1] > 3 * image.shape[0] / 2 and image[..., :3].std() > 0.01
    with pytest.raises(FileExistsError):
        write_calibration_plot(evaluation, path)


def test_eval_command_writes_the_calibration_plot(camera_scene, tmp_path, capsys):
    _, truth, replay = camera_scene
    plot = tmp_path / "calibration.png"
    assert cli.main(["eval", str(replay), "--truth", str(truth), "--samples", "500",
                     "--calibration-plot", str(plot)]) == 0
    assert "Calibration of the factor graph's position_std" in capsys.readouterr().out
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 10_000
    assert cli.main(["eval", str(replay), "--truth", str(truth), "--calibration-plot", str(plot)]) == 1
    assert "exists" in capsys.readouterr().err
