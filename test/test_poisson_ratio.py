"""Tests of core/poisson_ratio.py and its use by the prediction scheduler: the sensitivity is
the derivative of the small-strain equilibrium, a less compressible truth raises the model's
Poisson ratio to it, a more compressible one leaves the user's, and a new timeline forgets it."""

import numpy as np

from meshfg_ros.core.fem import ElasticModel
from meshfg_ros.core.poisson_ratio import PoissonRatioEstimate
from meshfg_ros.core.scheduler import PredictionScheduler
from meshfg_ros.core.simulator import ElasticSimulator, SimulatorConfig
from meshfg_ros.synthetic.meshing import cube_mesh

START = np.array([0.05, 0.05, 0.1, 0.0, 0.0, 0.0, 1.0])
PRESSED = START + np.array([0.0, 0.0, -0.004, 0.0, 0.0, 0.0, 0.0])  # the top face 4 mm down
NOMINAL = 0.45


def grasped_cube():
    mesh = cube_mesh(side=0.1, divisions=4)
    mesh = mesh.with_fixed(np.flatnonzero(mesh.vertices[:, 2] < 1e-9))
    return mesh, np.flatnonzero(mesh.vertices[:, 2] > 0.1 - 1e-9)


def simulator(mesh, top, nu):
    config = SimulatorConfig(poisson_ratio=nu, tool_mode="grasp", solver_iterations=20)
    model = ElasticSimulator(mesh, config, grasped_vertices=top)
    model.reset(START)
    return model


def pressed(model, start):
    """The model's equilibrium with the top face pressed down (a few predictions)."""
    state = start
    for _ in range(3):
        state = model.predict(state, PRESSED, 1.0)
    return state


def test_the_sensitivity_is_the_derivative_of_the_small_strain_equilibrium():
    mesh, top = grasped_cube()
    held = np.union1d(mesh.fixed_vertices, top)
    free = np.setdiff1d(np.arange(mesh.vertex_count), held)
    f = (3 * free[:, None] + np.arange(3)).reshape(-1)
    h = (3 * held[:, None] + np.arange(3)).reshape(-1)
    prescribed = np.zeros((mesh.vertex_count, 3))
    prescribed[top, 2] = -0.004

    def equilibrium(nu):
        stiffness = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, nu).stiffness(kind="linear").toarray()
        displacement = prescribed.copy().reshape(-1)
        displacement[f] = -np.linalg.solve(stiffness[np.ix_(f, f)], stiffness[np.ix_(f, h)] @ displacement[h])
        return displacement.reshape(-1, 3)

    estimate = PoissonRatioEstimate(simulator(mesh, top, NOMINAL))
    sensitivity = estimate.sensitivity(mesh.vertices + equilibrium(NOMINAL))
    step = 1e-5
    difference = (equilibrium(NOMINAL + step) - equilibrium(NOMINAL - step)) / (2 * step)
    assert np.abs(difference).max() > 1e-3  # the bulge changes with nu
    np.testing.assert_allclose(sensitivity, difference, rtol=0, atol=1e-6 * np.abs(difference).max())
    assert np.all(sensitivity[held] == 0.0)


def learnt_ratio(truth_nu, updates=4):
    mesh, top = grasped_cube()
    truth = pressed(simulator(mesh, top, truth_nu), mesh.vertices)
    model = simulator(mesh, top, NOMINAL)
    estimate = PoissonRatioEstimate(model)
    ratios = []
    for _ in range(updates):  # each correction is what the model still misses
        model.reset(START)
        predicted = pressed(model, mesh.vertices)
        ratios.append(estimate.update(predicted, truth - predicted))
    model.reset(START)
    return ratios, np.abs(pressed(model, mesh.vertices) - truth).max(), np.abs(truth - mesh.vertices).max()


def test_a_less_compressible_truth_raises_the_ratio_to_it():
    ratios, error, motion = learnt_ratio(0.47)
    # The first step is linear in nu and overshoots a little (lambda grows faster than linearly
    # towards 0.5); the next corrections, which measure what is left, take it there.
    assert 0.47 < ratios[0] < 0.48
    assert abs(ratios[-1] - 0.47) < 1e-4
    assert error < 1e-5 * motion


def test_a_more_compressible_truth_leaves_the_users_ratio():
    ratios, _, _ = learnt_ratio(0.40)
    assert ratios == [NOMINAL] * len(ratios)


def test_a_changed_ratio_predicts_as_a_simulator_built_with_it():
    mesh, top = grasped_cube()
    changed = simulator(mesh, top, NOMINAL)
    changed.poisson_ratio = 0.47
    changed.reset(START)
    np.testing.assert_allclose(pressed(changed, mesh.vertices), pressed(simulator(mesh, top, 0.47), mesh.vertices),
                               rtol=0, atol=1e-12)


def test_the_scheduler_learns_the_ratio_from_estimates_and_forgets_it_on_a_new_timeline():
    mesh, top = grasped_cube()
    config = SimulatorConfig(poisson_ratio=NOMINAL, tool_mode="grasp", solver_iterations=20)
    scheduler = PredictionScheduler(mesh, config, top)
    off = PredictionScheduler(mesh, SimulatorConfig(poisson_ratio=NOMINAL, tool_mode="grasp", solver_iterations=20,
                                                    estimate_poisson_ratio=False), top)
    truth = pressed(simulator(mesh, top, 0.47), mesh.vertices)
    for target in (scheduler, off):
        target.add_tool_pose(10**9, START)
        target.add_tool_pose(2 * 10**9, PRESSED)
        target.request(2 * 10**9)
        assert target.poll()[0].positions is not None
        target.add_estimate(2 * 10**9, truth)
    assert scheduler.simulator.poisson_ratio > NOMINAL + 0.01
    assert off.poisson_ratio is None and off.simulator.poisson_ratio == NOMINAL
    scheduler.add_tool_pose(5 * 10**8, START)  # a jump back: a new timeline
    assert scheduler.simulator.poisson_ratio == NOMINAL
