"""Tests of core/physics/poisson_ratio.py and its use by the prediction scheduler: the sensitivity is
the derivative of the small-strain equilibrium, the ratio learnt from a truth's corrections is
the truth's, less or more compressible, a changed ratio predicts as a simulator built with it,
and a new timeline forgets it."""

import numpy as np
import pytest

from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.physics.model_fit import learn
from meshfg_ros.core.physics.poisson_ratio import CEILING, FLOOR, PoissonRatioEstimate
from meshfg_ros.core.scheduler import PredictionScheduler
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig
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


def sure_everywhere(mesh):
    """A posterior std of 1 mm on every vertex the estimate moves."""
    std = np.full(mesh.vertex_count, 1e-3)
    std[mesh.fixed_vertices] = 0.0
    return std


def learnt_ratio(truth_nu, updates):
    mesh, top = grasped_cube()
    truth = pressed(simulator(mesh, top, truth_nu), mesh.vertices)
    model = simulator(mesh, top, NOMINAL)
    estimate = PoissonRatioEstimate(model)
    ratios = []
    for _ in range(updates):  # each correction is what the model still misses
        model.reset(START)
        predicted = pressed(model, mesh.vertices)
        learn(mesh, None, estimate, predicted, truth, sure_everywhere(mesh))
        ratios.append(model.poisson_ratio)
    model.reset(START)
    return ratios, np.abs(pressed(model, mesh.vertices) - truth).max(), np.abs(truth - mesh.vertices).max()


@pytest.mark.parametrize("truth_nu", [0.47, 0.40])
def test_the_learnt_ratio_is_the_truths(truth_nu):
    ratios, error, motion = learnt_ratio(truth_nu, updates=6)
    # The first step is linear in nu and overshoots a little when the truth is less
    # compressible (lambda grows faster than linearly towards 0.5); the next corrections, which
    # measure what is left, take it there, each update's error about a fifth of the last's.
    assert abs(ratios[0] - truth_nu) < 0.01 and (ratios[0] - NOMINAL) * (truth_nu - NOMINAL) > 0
    assert abs(ratios[-1] - truth_nu) < 1e-4
    assert error < 1e-5 * motion


def test_the_ratio_stays_within_its_bounds():
    mesh, top = grasped_cube()
    model = simulator(mesh, top, NOMINAL)
    estimate = PoissonRatioEstimate(model)
    assert estimate.add(1.0) == CEILING and model.poisson_ratio == CEILING
    assert estimate.add(-1.0) == FLOOR
    estimate.reset()
    assert model.poisson_ratio == NOMINAL


@pytest.mark.parametrize("solver", ["vbd", "xpbd"])
def test_a_changed_ratio_predicts_as_a_simulator_built_with_it(solver):
    """The solver's moduli are rescaled in place and its rest factor refactored: the same
    predictions, to rounding, and the same small-strain response."""
    mesh, top = grasped_cube()

    def model(nu):
        built = ElasticSimulator(mesh, SimulatorConfig(poisson_ratio=nu, tool_mode="grasp", solver=solver,
                                                       solver_iterations=20), grasped_vertices=top)
        built.reset(START)
        return built

    changed = model(NOMINAL)
    load = np.tile([0.0, 0.0, -1e-3], changed.movable_vertices.size)
    held = changed.movable_vertices[::5]
    changed.rest_response(load, held=held)  # the rest factor and its held columns exist before the change
    changed.poisson_ratio = 0.47
    changed.reset(START)
    built = model(0.47)
    np.testing.assert_allclose(pressed(changed, mesh.vertices), pressed(built, mesh.vertices), rtol=0, atol=1e-12)
    np.testing.assert_allclose(changed.rest_response(load), built.rest_response(load), rtol=1e-10, atol=0)
    held_response = built.rest_response(load, held=held)
    np.testing.assert_allclose(changed.rest_response(load, held=held), held_response, rtol=0,
                               atol=1e-10 * np.abs(held_response).max())


def test_the_scheduler_learns_the_ratio_from_estimates_and_forgets_it_on_a_new_timeline():
    mesh, top = grasped_cube()
    config = SimulatorConfig(poisson_ratio=NOMINAL, tool_mode="grasp", solver_iterations=20)
    scheduler = PredictionScheduler(mesh, config, top)
    off = PredictionScheduler(mesh, SimulatorConfig(poisson_ratio=NOMINAL, tool_mode="grasp", solver_iterations=20,
                                                    estimate_poisson_ratio=False), top)
    truth = pressed(simulator(mesh, top, 0.47), mesh.vertices)
    without_std = PredictionScheduler(mesh, config, top)
    for target in (scheduler, off, without_std):
        target.add_tool_pose(10**9, START)
        target.add_tool_pose(2 * 10**9, PRESSED)
        target.request(2 * 10**9)
        assert target.poll()[0].positions is not None
        target.add_estimate(2 * 10**9, truth, position_std=None if target is without_std else sure_everywhere(mesh))
    assert scheduler.simulator.poisson_ratio > NOMINAL + 0.01
    assert off.simulator.poisson_ratio_estimate is None and off.simulator.poisson_ratio == NOMINAL
    # An estimate without its std cannot weigh the fit: it teaches the model nothing.
    assert without_std.simulator.poisson_ratio == NOMINAL
    assert np.all(without_std.simulator.body_acceleration == 0.0)
    scheduler.add_tool_pose(5 * 10**8, START)  # a jump back: a new timeline
    assert scheduler.simulator.poisson_ratio == NOMINAL


def test_the_rest_response_holds_the_vertices_asked_for():
    """The Schur complement on the rest factor equals a solve with the held vertices removed."""
    mesh, top = grasped_cube()
    model = simulator(mesh, top, NOMINAL)
    movable = model.movable_vertices
    held = movable[::7]
    rng = np.random.default_rng(3)
    forces = rng.normal(size=(3 * movable.size, 2))
    response = model.rest_response(forces, held=held)
    stiffness = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, NOMINAL).stiffness(kind="linear").toarray()
    free = np.setdiff1d(movable, held)
    dofs = (3 * free[:, None] + np.arange(3)).reshape(-1)
    rows = (3 * np.searchsorted(movable, free)[:, None] + np.arange(3)).reshape(-1)
    expected = np.zeros_like(forces)
    expected[rows] = np.linalg.solve(stiffness[np.ix_(dofs, dofs)], forces[rows])
    np.testing.assert_allclose(response, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
