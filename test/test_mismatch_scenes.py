"""Mismatch scenes: determinism, sensor realism, truth validity and its departure from the
estimator's nominal model (two-step versions of the ten-step scenes)."""

from dataclasses import asdict

import numpy as np
import pytest
from offline_helpers import counting_progress

from meshfg_ros.core.geometry.mesh import signed_volumes
from meshfg_ros.synthetic.scenarios import MISMATCH_SCENARIOS, SCENARIOS, ScenarioError, generate
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig
from meshfg_ros.replay import scenario_parameters
from meshfg_ros.synthetic.recordings import scenario_metadata
from meshfg_ros.synthetic import mismatch_scenes
from meshfg_ros.synthetic.mismatch_scenes import build_scene, radius_ratios

SEED = 3
STEPS = 2
MESH_CACHES = (mismatch_scenes._slab_mesh, mismatch_scenes._dome_mesh, mismatch_scenes._liver_mesh,
               mismatch_scenes._kidney_mesh, mismatch_scenes._flap_mesh)


@pytest.fixture(scope="module", params=MISMATCH_SCENARIOS)
def scene_pair(request):
    """The scene built twice from the same seed, re-meshing in between."""
    first = generate(request.param, seed=SEED, steps=STEPS)
    for cached in MESH_CACHES:
        cached.cache_clear()
    return first, generate(request.param, seed=SEED, steps=STEPS)


@pytest.fixture(scope="module")
def scene(scene_pair):
    return scene_pair[0]


@pytest.fixture(scope="module")
def open_loop(scene):
    """The nominal simulator driven by the reported tool poses from the initial mesh, as the
    replay's 'simulation alone' baseline."""
    simulator = ElasticSimulator(scene.initial_mesh, scene.simulator_config)
    simulator.reset(scene.initial_tool_pose)
    state, states = scene.initial_mesh.vertices, []
    for step in scene.steps:
        state = simulator.predict(state, step.tool_pose, 1.0)
        states.append(state)
    return states


def test_scenes_are_registered():
    assert set(MISMATCH_SCENARIOS) <= set(SCENARIOS)
    assert len(set(SCENARIOS)) == len(SCENARIOS) == 12


def test_the_hyperelastic_truth_reports_each_step_to_the_progress():
    seen = []
    generate("dome-tilted", seed=SEED, steps=STEPS, progress=counting_progress(seen))
    assert seen == [STEPS] + ["step"] * STEPS


def test_same_seed_gives_equal_scenes(scene_pair):
    first, second = scene_pair
    for name in ("vertices", "tetrahedra", "fixed_vertices"):
        np.testing.assert_array_equal(getattr(first.initial_mesh, name), getattr(second.initial_mesh, name))
    np.testing.assert_array_equal(first.initial_tool_pose, second.initial_tool_pose)
    np.testing.assert_array_equal(first.camera_pose, second.camera_pose)
    assert len(first.steps) == len(second.steps) == STEPS
    for one, other in zip(first.steps, second.steps):
        assert one.stamp_ns == other.stamp_ns
        for name in ("tool_pose", "points", "point_labels", "truth"):
            np.testing.assert_array_equal(getattr(one, name), getattr(other, name))
    assert first.description == second.description


def test_mesh_size_and_quality_are_realistic(scene):
    mesh = scene.initial_mesh
    assert 1000 <= mesh.vertex_count <= 2000
    quality = radius_ratios(mesh.vertices, mesh.tetrahedra)
    assert 0.2 <= quality.min() < 0.5  # slivers of a light optimisation, none degenerate
    assert np.median(quality) > 0.7
    assert f"min {quality.min():.2f} median {np.median(quality):.2f}" in scene.description
    assert 0.03 * mesh.vertex_count < mesh.fixed_vertices.size < 0.4 * mesh.vertex_count


def test_clouds_have_realistic_size_and_segmentation_leaks(scene):
    for step in scene.steps:
        labels = step.point_labels
        assert 1000 <= np.count_nonzero(labels == 0) <= 2200
        assert 0.10 <= np.mean(labels > 0) <= 0.25
        assert np.count_nonzero(labels == mismatch_scenes.TOOL_LABEL) > 0
        assert np.count_nonzero(labels == mismatch_scenes.SURROUNDINGS_LABEL) > 0


def test_truth_keeps_volumes_positive_and_fixed_vertices_fixed(scene):
    mesh = scene.initial_mesh
    previous = mesh.vertices
    for step in scene.steps:
        assert np.all(signed_volumes(step.truth, mesh.tetrahedra) > 0.0)
        np.testing.assert_array_equal(step.truth[mesh.fixed_vertices], mesh.vertices[mesh.fixed_vertices])
        assert np.linalg.norm(step.truth - previous, axis=1).max() > 2e-4  # the tissue moves every step
        previous = step.truth


def test_truth_departs_from_the_nominal_open_loop_simulation(scene, open_loop):
    errors = [np.linalg.norm(state - step.truth, axis=1) for state, step in zip(open_loop, scene.steps)]
    assert max(error.max() for error in errors) > scene.noise_sigma_m / 4
    assert errors[-1].max() > errors[0].max()  # the departure grows with the loading


def test_nominal_model_holds_only_what_a_user_knows(scene):
    assert scene.estimator_overrides == {}
    config = scene.simulator_config
    assert (config.poisson_ratio, config.tool_mode, config.tool_contact) == (0.45, "sphere", "stick")
    changed = {key for key, value in asdict(config).items() if value != asdict(SimulatorConfig())[key]}
    assert changed <= {"youngs_modulus", "poisson_ratio", "tool_radius"}
    parameters = scenario_parameters(scenario_metadata(scene))  # the replay accepts the nominal model
    assert parameters["measurement_sigma"] == scene.noise_sigma_m
    assert 0.3e-3 <= scene.noise_sigma_m <= 1.0e-3


def test_unknown_scene_and_bad_step_count_raise():
    with pytest.raises(ScenarioError, match="unknown mismatch scene"):
        build_scene("slab")
    with pytest.raises(ScenarioError, match="steps"):
        build_scene("slab-inclusion", steps=0)


def test_radius_ratio_of_reference_tetrahedra():
    regular = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
    corner = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    sliver = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 1e-3]])
    ratios = radius_ratios(np.concatenate([regular, corner, sliver]), np.arange(12).reshape(3, 4))
    # Corner tetrahedron: r_in = 3V / area = 1 / (3 + sqrt 3), r_circ = sqrt(3) / 2.
    np.testing.assert_allclose(ratios[:2], [1.0, 3.0 / (3.0 + np.sqrt(3.0)) / (np.sqrt(3.0) / 2.0)], rtol=1e-12)
    assert ratios[2] < 0.01
