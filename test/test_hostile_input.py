"""Hostile but well-formed input: the estimator's documented errors and roll-back, stamps, input far
outside the scene, the innovation test, the per-update time budget, and the replay's stamp rule."""
import itertools
import time
from dataclasses import replace

import numpy as np
import pytest
from offline_helpers import BAGS, tiny_scenario

import meshfg_ros.core.estimation.estimator as estimator_module
from meshfg_ros.core.geometry.closest_point import ClosestPointIndex, InvalidGeometryError
from meshfg_ros.core.estimation.estimator import (
    EstimatorConfig,
    EstimatorConfigError,
    EstimatorInputError,
    EstimatorStampError,
    EstimatorStepError,
    SlidingWindowEstimator,
)
from meshfg_ros.core.physics.fem import ElasticModel, InvalidStateError, polar_rotations
from meshfg_ros.core.inputs.input_checks import (
    INVALID,
    JUMP_BACK,
    NEWER,
    REJECTIONS,
    STALE,
    SceneError,
    StampError,
    check_initial_mesh,
    check_stamp,
    flat_elements,
    rejections_in,
    stamp_order,
)
from meshfg_ros.core.solvers.levenberg_marquardt import NonFiniteCostError
from meshfg_ros.parameters import estimator_config, load_parameters
from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS, STEP_PERIOD_NS
from meshfg_ros.io.messages import MeshState, PointCloudRecord, PoseRecord
from meshfg_ros.io.recording import RecordingWriter
from meshfg_ros.replay import ReplayError, iterate_replay, load_inputs, replay_parameters, replay_recording
from meshfg_ros.topics import INITIAL_MESH_TOPIC, POINTS_TOPIC, TOOL_POSE_TOPIC

S = 1_000_000_000


@pytest.fixture(scope="module")
def cao():
    """The bundled airway push: inputs, parameters and the fault-free replay."""
    inputs = load_inputs(BAGS / "cao-push")
    params = replay_parameters(inputs)
    return inputs, params, tuple(iterate_replay(inputs, params))


def fresh(cao, **changes) -> SlidingWindowEstimator:
    inputs, params, _ = cao
    return SlidingWindowEstimator(inputs.initial_mesh, replace(estimator_config(params), **changes))


def rms(a, b) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


# ---------------------------------------------------------------------------- input_checks
def test_stamp_checks_and_order():
    assert check_stamp(5) == 5 and check_stamp(np.int64(7)) == 7 and check_stamp(2**63 - 1) == 2**63 - 1
    for bad in (-1, 2**63, 2**70, 1.0, True, np.bool_(True), "5", None, np.uint64(2**64 - 1)):
        with pytest.raises(StampError):
            check_stamp(bad)
    assert stamp_order(None, 0, S) == NEWER and stamp_order(10 * S, 10 * S + 1, S) == NEWER
    assert stamp_order(10 * S, 10 * S, S) == STALE and stamp_order(10 * S, 9 * S, S) == STALE
    assert stamp_order(10 * S, 9 * S - 1, S) == JUMP_BACK
    assert stamp_order(10 * S, -1, S) == INVALID and stamp_order(None, 2**63, S) == INVALID


def test_initial_mesh_must_be_finite_near_the_origin_and_have_an_extent(cao):
    vertices = cao[0].initial_mesh.vertices
    scene = check_initial_mesh(vertices)
    assert scene.diagonal == pytest.approx(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    assert not scene.far(vertices).any() and scene.far(vertices + [0.0, 0.0, 11 * scene.diagonal]).all()
    for bad, message in ((vertices + 2e3, "from the world origin"), (np.zeros((4, 3)), "no extent"),
                         (np.full((4, 3), np.nan), "finite")):
        with pytest.raises(SceneError, match=message):
            check_initial_mesh(bad)


# ---------------------------------------------------------------------------- numerics at the edge
@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # overflow on the way to the refusal
def test_projection_and_stiffness_refuse_coordinates_they_cannot_represent(cao):
    mesh = cao[0].initial_mesh
    index = ClosestPointIndex(mesh.vertices, mesh.surface_triangles)
    for value in (1e200, 1e308):
        with pytest.raises(InvalidGeometryError, match="beyond"):
            index.associate(np.full((5, 3), value))
    far = index.associate(np.random.default_rng(0).normal(size=(50, 3)) * 1e60)
    assert far.triangle.min() >= 0 and far.triangle.max() < len(mesh.surface_triangles)
    model = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45)
    state = mesh.vertices.copy()
    state[5] = 1e308  # the deformation gradients overflow: LAPACK's SVD never returned on them
    with pytest.raises(InvalidStateError, match="not finite"):
        model.stiffness(state, kind="corotational")
    rotations = polar_rotations(np.random.default_rng(1).normal(size=(20, 3, 3)) * 1e307)
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (20, 3, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0)


# ---------------------------------------------------------------------------- update(): errors
def test_stamps_are_integer_nanoseconds_in_range_and_increasing(cao):
    step = cao[2][0]
    estimator = fresh(cao)
    for bad in (-1, 2**63, 2**70, float(step.stamp_ns), True, str(step.stamp_ns), None):
        with pytest.raises(EstimatorStampError):
            estimator.update(bad, step.points, step.predicted)
    assert estimator.update(np.int64(step.stamp_ns), step.points, step.predicted).stamp_ns == step.stamp_ns
    for bad in (step.stamp_ns, step.stamp_ns - 1):
        with pytest.raises(EstimatorStampError, match="not newer"):
            estimator.update(bad, step.points, step.predicted)
    assert estimator.step == 1 and len(estimator.graph.keys) == 1


@pytest.mark.parametrize("name, value, message", [
    ("points", [[0.0, 0.0, 0.0], [1.0, 2.0]], "not an array of numbers"),
    ("points", "0 0 0", "real numbers"),
    ("points", [[None, 1.0, 2.0]], "real numbers"),
    ("points", np.ones((4, 3), dtype=complex), "real numbers"),
    ("points", np.ones((4, 3), dtype=bool), "real numbers"),
    ("points", [[10**30, 0, 0]], "real numbers"),
    ("points", np.zeros((4, 2)), "shape"),
    ("predicted", "mesh", "real numbers"),
    ("predicted", [[0.0, 0.0, 0.0], [0.0]], "not an array of numbers"),
    ("predicted", np.zeros((3, 3)), "shape"),
    ("tool_pose", np.zeros(3), "7 finite values"),
    ("tool_pose", np.full(7, np.nan), "7 finite values"),
    ("tool_pose", "tool", "real numbers"),
])
def test_malformed_input_raises_estimator_input_error(cao, name, value, message):
    step = cao[2][0]
    arguments = dict(stamp_ns=step.stamp_ns, points=step.points, predicted=step.predicted, tool_pose=None)
    arguments[name] = value
    estimator = fresh(cao)
    with pytest.raises(EstimatorInputError, match=message):
        estimator.update(**arguments)
    assert estimator.step == 0 and estimator.last_stamp_ns is None


@pytest.mark.parametrize("failure", [NonFiniteCostError("the cost at the starting point is inf"),
                                     IndexError("index 32655 is out of bounds"), KeyboardInterrupt()])
def test_a_failed_update_leaves_the_window_as_it_was(cao, monkeypatch, failure):
    steps = cao[2]
    failing, reference = fresh(cao), fresh(cao)
    for step in steps[:3]:
        failing.update(step.stamp_ns, step.points, step.predicted)
        reference.update(step.stamp_ns, step.points, step.predicted)
    before = (failing.step, failing.last_estimate.copy(), list(failing.graph.keys),
              {key: state.copy() for key, state in failing.graph.states.items()}, failing.anchor.copy(),
              failing.noise.sigma, failing.last_stamp_ns, len(failing.graph.factors))

    def fail(*args, **kwargs):
        raise failure

    monkeypatch.setattr(estimator_module, "levenberg_marquardt", fail)
    step = steps[3]
    expected = KeyboardInterrupt if isinstance(failure, KeyboardInterrupt) else EstimatorStepError
    with pytest.raises(expected, match=None if expected is KeyboardInterrupt else type(failure).__name__):
        failing.update(step.stamp_ns, step.points, step.predicted)
    after = (failing.step, failing.last_estimate, list(failing.graph.keys), failing.graph.states, failing.anchor,
             failing.noise.sigma, failing.last_stamp_ns, len(failing.graph.factors))
    assert after[0] == before[0] and after[2] == before[2] and after[5:] == before[5:]
    np.testing.assert_array_equal(after[1], before[1])
    np.testing.assert_array_equal(after[4], before[4])
    for key in before[2]:
        np.testing.assert_array_equal(after[3][key], before[3][key])
    monkeypatch.undo()
    # The same update again, and the next ones, as if the failure never happened.
    for step in steps[3:6]:
        result = failing.update(step.stamp_ns, step.points, step.predicted)
        expected_result = reference.update(step.stamp_ns, step.points, step.predicted)
        assert result.step == expected_result.step
        np.testing.assert_allclose(result.positions, expected_result.positions, rtol=0.0, atol=1e-7)


# ---------------------------------------------------------------------------- update(): set aside
def test_far_points_prediction_and_tool_pose_are_set_aside_and_said(cao):
    inputs, _, steps = cao
    step = steps[1]
    estimator = fresh(cao)
    estimator.update(steps[0].stamp_ns, steps[0].points, steps[0].predicted)
    points = np.concatenate([step.points, np.full((5, 3), 1e308)])
    predicted = step.predicted.copy()
    predicted[7] = 1e20
    tool_pose = np.array(inputs.poses[2].pose)
    tool_pose[:3] = 1e20
    result = estimator.update(step.stamp_ns, points, predicted, tool_pose)
    assert sorted(rejections_in(result.message)) == ["clouds_with_far_points", "predictions_rejected_far",
                                                     "tool_poses_ignored_far"]
    assert f"5 {REJECTIONS['clouds_with_far_points']}" in result.message
    assert result.degraded and result.num_points_rejected >= 5 and np.isfinite(result.positions).all()
    # All points far: a step without measurements, not an error.
    result = estimator.update(steps[2].stamp_ns, np.full((100, 3), 1e200), steps[2].predicted)
    assert result.num_points == 0 and result.num_points_rejected == 100 and not result.degraded


def test_an_inverted_prediction_is_rejected(cao):
    step = cao[2][0]
    mirrored = step.predicted.copy()
    mirrored[:, 0] = 2.0 * mirrored[:, 0].mean() - mirrored[:, 0]
    tetrahedra = cao[0].initial_mesh.tetrahedra
    assert flat_elements(step.predicted, tetrahedra) == 0 and flat_elements(mirrored, tetrahedra) == len(tetrahedra)
    result = fresh(cao).update(step.stamp_ns, step.points, mirrored)
    assert rejections_in(result.message) == ["predictions_rejected_inverted"] and result.degraded


@pytest.mark.parametrize("bag, shift, reason", [("cube-shear-spd", 0.15, "predictions_rejected_innovation"),
                                                ("cao-push", 1.0, "predictions_rejected_far")])
def test_a_prediction_the_cloud_contradicts_is_rejected_and_not_followed(bag, shift, reason):
    """Shifted by 15 cm along the diagonal, the 1 m cube's prediction fails the innovation test (the
    airway's inverts elements against its fixed ends before); by 1 m the airway's is far outside
    the scene. Either way the step runs on the copy-forward and stays within a fraction of a
    millimetre of the fault-free one, and the next step is as if nothing happened."""
    inputs = load_inputs(BAGS / bag)
    params = replay_parameters(inputs)
    steps = tuple(iterate_replay(inputs, params))[:3]
    estimator = SlidingWindowEstimator(inputs.initial_mesh, estimator_config(params))
    estimator.update(steps[0].stamp_ns, steps[0].points, steps[0].predicted)
    step = steps[1]
    result = estimator.update(step.stamp_ns, step.points, step.predicted + shift)
    assert rejections_in(result.message) == [reason] and result.degraded
    assert rms(result.positions, step.result.positions) < 0.5e-3
    later = estimator.update(steps[2].stamp_ns, steps[2].points, steps[2].predicted)
    assert not rejections_in(later.message) and rms(later.positions, steps[2].result.positions) < 0.5e-3


@pytest.mark.parametrize("bag", ["cao-push", "liver-push", "cube-shear-spd"])
def test_the_input_checks_never_fire_on_the_bundled_scenes(bag):
    result = replay_recording(BAGS / bag)
    assert [rejections_in(step.result.message) for step in result.steps] == [[]] * len(result.steps)
    assert all(step.result.degraded == (step.predicted is None) for step in result.steps)


# ---------------------------------------------------------------------------- time budget
def test_the_time_budget_stops_levenberg_marquardt_between_iterations(cao, monkeypatch):
    step = cao[2][0]
    estimator = fresh(cao, update_time_budget=1e-3)
    # a clock on which every reading is a second later: the budget is spent before LM's first iteration
    readings = itertools.count()
    with monkeypatch.context() as patched:
        patched.setattr(time, "perf_counter", lambda: float(next(readings)))
        result = estimator.update(step.stamp_ns, step.points, step.predicted)
    assert result.iterations == 0 and "time budget" in result.message and not result.converged
    assert np.isfinite(result.positions).all()
    unlimited = fresh(cao, update_time_budget=None).update(step.stamp_ns, step.points, step.predicted)
    assert unlimited.iterations > 0 and "time budget" not in unlimited.message
    with pytest.raises(EstimatorConfigError, match="update_time_budget"):
        EstimatorConfig(update_time_budget=0.0)
    assert estimator_config(load_parameters({"update_time_budget": 2.5})).update_time_budget == 2.5


# ---------------------------------------------------------------------------- replay
def _write(path, scenario, clouds, poses=None):
    """A recording of `scenario`'s mesh with `poses` (default: its own) and `clouds`, each a list of
    (log time, record), logged in that order."""
    mesh = scenario.initial_mesh
    poses = poses if poses is not None else (
        [(FIRST_STAMP_NS, PoseRecord(FIRST_STAMP_NS, "world", scenario.initial_tool_pose))]
        + [(step.stamp_ns, PoseRecord(step.stamp_ns, "world", step.tool_pose)) for step in scenario.steps])
    with RecordingWriter(path) as writer:
        writer.write(INITIAL_MESH_TOPIC, MeshState(FIRST_STAMP_NS, "world", 0, mesh.vertices, mesh.tetrahedra,
                                                   mesh.surface_triangles, mesh.fixed_vertices))
        entries = [(TOOL_POSE_TOPIC, pose) for pose in poses] + [(POINTS_TOPIC, cloud) for cloud in clouds]
        for topic, (log_ns, record) in sorted(entries, key=lambda entry: (entry[1][0], entry[0] == POINTS_TOPIC)):
            writer.write(topic, record, log_ns)


def test_the_replay_follows_the_stamp_rule_of_the_nodes(tmp_path):
    """Clouds in log-time order: stale and negative stamps and unknown frames are skipped, a jump
    back restarts the estimator (step numbers start again); repeated tool-pose stamps are dropped."""
    scenario = tiny_scenario(steps=3)
    s1, s2, s3 = (step.stamp_ns for step in scenario.steps)
    cloud = [PointCloudRecord(step.stamp_ns, "world", step.points) for step in scenario.steps]
    late = s3 + STEP_PERIOD_NS
    clouds = [(s1, cloud[0]), (s2, cloud[1]),
              (s2 + 1, replace(cloud[1], stamp_ns=s2)),              # repeated
              (s2 + 2, replace(cloud[0], stamp_ns=s1 + 1)),          # older, within clock_jump_threshold
              (s2 + 3, replace(cloud[1], stamp_ns=-S)),              # negative
              (s2 + 4, replace(cloud[1], stamp_ns=s2 + 5, frame_id="map")),
              (s3, cloud[2]),
              (late, replace(cloud[0], stamp_ns=s3 - 2 * S))]        # looped back
    poses = ([(FIRST_STAMP_NS, PoseRecord(FIRST_STAMP_NS, "world", scenario.initial_tool_pose))]
             + [(step.stamp_ns, PoseRecord(step.stamp_ns, "world", step.tool_pose)) for step in scenario.steps]
             + [(s3 + 1, PoseRecord(s3, "world", scenario.steps[0].tool_pose))])  # repeated pose stamp
    _write(tmp_path / "rule", scenario, clouds, poses)
    steps = replay_recording(tmp_path / "rule", {"max_iterations": 3}).steps
    assert [step.stamp_ns for step in steps] == [s1, s2, s3, s3 - 2 * S]
    assert [step.result.step for step in steps] == [1, 2, 3, 1]
    assert [step.predicted is not None for step in steps] == [True, True, True, False]


def test_a_far_tool_pose_is_not_simulated_and_a_far_initial_mesh_is_refused(tmp_path):
    scenario = tiny_scenario(steps=2)
    s1, s2 = (step.stamp_ns for step in scenario.steps)
    far = np.array(scenario.steps[0].tool_pose)
    far[:3] = 1e20
    poses = [(FIRST_STAMP_NS, PoseRecord(FIRST_STAMP_NS, "world", scenario.initial_tool_pose)),
             (s1, PoseRecord(s1, "world", far)), (s2, PoseRecord(s2, "world", scenario.steps[1].tool_pose))]
    clouds = [(step.stamp_ns, PointCloudRecord(step.stamp_ns, "world", step.points)) for step in scenario.steps]
    _write(tmp_path / "far", scenario, clouds, poses)
    steps = replay_recording(tmp_path / "far", {"max_iterations": 3}).steps
    # the far pose is dropped: the cloud at s1 is predicted with the pose interpolated between its
    # neighbours, and the tool gate uses that pose too
    assert [step.predicted is not None for step in steps] == [True, True]
    assert not any(step.result.degraded for step in steps)
    assert all(rejections_in(step.result.message) == [] for step in steps)
    _write(tmp_path / "without", scenario, clouds, [poses[0], poses[2]])  # the recording without the far pose
    without = replay_recording(tmp_path / "without", {"max_iterations": 3}).steps
    for step, reference in zip(steps, without, strict=True):
        np.testing.assert_allclose(step.predicted, reference.predicted, rtol=0, atol=1e-12)
        np.testing.assert_allclose(step.result.positions, reference.result.positions, rtol=0, atol=1e-12)
    moved = replace(scenario, initial_mesh=scenario.initial_mesh.with_vertices(scenario.initial_mesh.vertices + 2e3))
    _write(tmp_path / "moved", moved, clouds)
    with pytest.raises(ReplayError, match="from the world origin"):
        load_inputs(tmp_path / "moved")
