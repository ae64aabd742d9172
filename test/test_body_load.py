"""Tests of core/physics/body_load.py and its use by the prediction scheduler: the unmodelled uniform
body load is recovered from corrections (core/physics/model_fit.py), a local correction moves it little
and noise by its least-squares spread, the simulator applies it, and a new timeline forgets it."""

import numpy as np
import pytest

from meshfg_ros.core.physics.body_load import BodyLoadEstimate
from meshfg_ros.core.physics.model_fit import learn, surface_fit
from meshfg_ros.core.scheduler import PredictionScheduler
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig, SimulatorInputError
from meshfg_ros.synthetic.meshing import cube_mesh

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])
FAR_AWAY = np.concatenate([[1.0, 1.0, 1.0], IDENTITY])  # a tool that touches nothing
# A stiff 10 cm cube sags by tens of micrometres under 1 g: the small-strain response the
# estimate assumes holds to about 1e-3.
STIFF = 3.0e6
TRUE_ACCELERATION = np.array([2.0, -1.0, -9.81])


def fixed_cube():
    mesh = cube_mesh(side=0.1, divisions=4)
    return mesh.with_fixed(np.flatnonzero(mesh.vertices[:, 2] < 1e-9))


def sure_everywhere(mesh):
    """A posterior std of 1 mm on every vertex the estimate moves."""
    std = np.full(mesh.vertex_count, 1e-3)
    std[mesh.fixed_vertices] = 0.0
    return std


def settled(simulator: ElasticSimulator, start: np.ndarray, dt: float = 1.0) -> np.ndarray:
    """The simulator's equilibrium from `start` under its current load (a few predictions; xpbd
    needs steps short enough that gravity's move per sub-step, (dt / substeps)^2 g, stays far
    below an element)."""
    state = start
    for _ in range(3):
        state = simulator.predict(state, FAR_AWAY, dt=dt)
    return state


def test_the_unmodelled_load_is_recovered_from_corrections():
    mesh = fixed_cube()
    config = SimulatorConfig(youngs_modulus=STIFF, substeps=1, solver_iterations=3)
    truth = settled(ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF, substeps=1, solver_iterations=3,
                                                           gravity=tuple(TRUE_ACCELERATION))), mesh.vertices)
    model = ElasticSimulator(mesh, config)
    model.reset(FAR_AWAY)
    load = BodyLoadEstimate(model)
    first = None
    for _ in range(3):  # each correction is what the load still misses: the truth less the prediction
        predicted = settled(model, mesh.vertices)
        before = load.acceleration
        learn(mesh, load, None, predicted, truth, sure_everywhere(mesh))
        first = load.acceleration - before if first is None else first
    # One perfect correction gives the load to the model's nonlinearity; later ones add only that.
    assert np.linalg.norm(first - TRUE_ACCELERATION) < 1e-2 * np.linalg.norm(TRUE_ACCELERATION)
    assert np.linalg.norm(load.acceleration - TRUE_ACCELERATION) < 1e-3 * np.linalg.norm(TRUE_ACCELERATION)
    assert np.abs(settled(model, mesh.vertices) - truth).max() < 1e-3 * np.abs(truth - mesh.vertices).max()


def test_a_local_correction_moves_the_load_little_and_noise_by_its_least_squares_spread():
    """One vertex moved by ten times the sag moves the load by a tenth of it. White noise as
    large as the sag at every vertex moves it by the spread of a least-squares fit of three
    numbers to the surface's normal components, sigma sqrt(trace((A^T W A)^-1)): 15-45 % of the
    load on this coarse cube. The persistence share (core/estimation/persistence.py) keeps most of a
    correction's noise from the estimates this learns from."""
    mesh = fixed_cube()
    model = ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF))
    load = BodyLoadEstimate(model)
    sag = settled(ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF, gravity=tuple(TRUE_ACCELERATION))),
                  mesh.vertices) - mesh.vertices
    responses, std = load.responses(), sure_everywhere(mesh)
    top = np.argmax(mesh.vertices[:, 2] + 1e-3 * mesh.vertices[:, 0])
    local = np.zeros_like(sag)
    local[top] = sag[top] * 10
    assert np.linalg.norm(surface_fit(mesh, mesh.vertices, local, std, responses)) < 0.2 * np.linalg.norm(TRUE_ACCELERATION)
    sigma = np.sqrt(np.mean(np.sum(sag**2, axis=1)) / 3.0)  # per component
    normals = mesh.vertex_normals(mesh.vertices)
    along = np.einsum("vi,kvi->vk", normals, responses)
    weights = np.where(std > 0.0, 1.0 / np.where(std > 0.0, std, 1.0) ** 2, 0.0)
    spread = sigma * np.sqrt(np.trace(np.linalg.inv(along.T @ (weights[:, None] * along)) @ (
        along.T @ (weights[:, None] ** 2 * along)) @ np.linalg.inv(along.T @ (weights[:, None] * along))))
    rng = np.random.default_rng(3)
    fitted = []
    for _ in range(40):
        noise = rng.normal(scale=sigma, size=sag.shape)
        noise[mesh.fixed_vertices] = 0.0
        fitted.append(surface_fit(mesh, mesh.vertices, noise, std, responses))
    rms = np.sqrt(np.mean(np.sum(np.square(fitted), axis=1)))
    assert 0.7 * spread < rms < 1.3 * spread
    assert rms < 0.5 * np.linalg.norm(TRUE_ACCELERATION)


@pytest.mark.parametrize("solver", ["vbd", "xpbd"])
def test_the_simulator_applies_the_acceleration_on_top_of_its_gravity(solver):
    mesh = fixed_cube()
    gravity = np.array([0.0, 0.0, -9.81])
    with_gravity = ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF, gravity=tuple(gravity), solver=solver))
    both = ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF, gravity=tuple(gravity + TRUE_ACCELERATION),
                                                  solver=solver))
    with_gravity.body_acceleration = TRUE_ACCELERATION
    dt = 1.0 if solver == "vbd" else 1e-3
    moved = settled(with_gravity, mesh.vertices, dt)
    assert np.abs(moved - mesh.vertices).max() > 1e-7  # the loads moved the cube
    np.testing.assert_allclose(moved, settled(both, mesh.vertices, dt), rtol=0, atol=1e-12)
    with pytest.raises(SimulatorInputError, match="body_acceleration"):
        with_gravity.body_acceleration = [np.nan, 0.0, 0.0]


def test_the_scheduler_carries_the_load_into_the_next_prediction_and_forgets_it_on_a_new_timeline():
    mesh = fixed_cube()
    config = SimulatorConfig(youngs_modulus=STIFF)
    scheduler = PredictionScheduler(mesh, config)
    off = PredictionScheduler(mesh, SimulatorConfig(youngs_modulus=STIFF, estimate_body_load=False))
    sag = settled(ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF, gravity=tuple(TRUE_ACCELERATION))),
                  mesh.vertices) - mesh.vertices
    for target in (scheduler, off):
        for second in (1, 2):
            target.add_tool_pose(second * 10**9, FAR_AWAY)
        target.request(10**9 + 5)
    first, unchanged = scheduler.poll()[0], off.poll()[0]
    scheduler.add_estimate(first.stamp_ns, first.positions + sag, position_std=sure_everywhere(mesh))  # found the sag
    off.add_estimate(unchanged.stamp_ns, unchanged.positions + sag, position_std=sure_everywhere(mesh))
    assert np.linalg.norm(scheduler.simulator.body_acceleration - TRUE_ACCELERATION) < 0.05 * np.linalg.norm(TRUE_ACCELERATION)
    assert off.simulator.body_acceleration is None
    for target in (scheduler, off):
        target.request(2 * 10**9)
    carried, relaxed = scheduler.poll()[0], off.poll()[0]
    # Started from the sagged estimate, the model without the load springs back; with it, it stays.
    assert np.abs(carried.positions - (mesh.vertices + sag)).max() < 0.1 * np.abs(sag).max()
    assert np.abs(relaxed.positions - mesh.vertices).max() < 0.1 * np.abs(sag).max()
    scheduler.add_tool_pose(5 * 10**8, FAR_AWAY)  # a jump back: a new timeline
    assert np.all(scheduler.simulator.body_acceleration == 0.0)


def test_an_estimate_made_without_the_prediction_teaches_the_load_nothing():
    """A degraded update started from the copy-forward: its difference from the prediction is
    the predicted motion, not a correction of the model."""
    mesh = fixed_cube()
    scheduler = PredictionScheduler(mesh, SimulatorConfig(youngs_modulus=STIFF))
    for second in (1, 2):
        scheduler.add_tool_pose(second * 10**9, FAR_AWAY)
    scheduler.request(2 * 10**9)
    predicted = scheduler.poll()[0]
    sagged = predicted.positions + 1e-4 * np.array([0.0, 0.0, -1.0]) * (mesh.vertices[:, 2:] / 0.1)
    scheduler.add_estimate(predicted.stamp_ns, sagged, degraded=True, position_std=sure_everywhere(mesh))
    assert np.all(scheduler.simulator.body_acceleration == 0.0)
    assert scheduler.state_stamp_ns == predicted.stamp_ns  # still the start of the next prediction


def test_a_failed_prediction_forgets_the_load():
    """The load may be what made the prediction fail; kept, every later one could fail too."""
    mesh = fixed_cube()
    scheduler = PredictionScheduler(mesh, SimulatorConfig(youngs_modulus=STIFF))
    for second in (1, 2, 3):
        scheduler.add_tool_pose(second * 10**9, FAR_AWAY)
    scheduler.request(2 * 10**9)
    predicted = scheduler.poll()[0]
    scheduler.add_estimate(predicted.stamp_ns, predicted.positions + [0.0, 0.0, -1e-5], position_std=sure_everywhere(mesh))
    assert np.linalg.norm(scheduler.simulator.body_acceleration) > 0.0
    scheduler.simulator.elastic.body_acceleration = [0.0, 0.0, -1e9]  # a load that crushes the cube
    scheduler.request(3 * 10**9)
    failed = scheduler.poll()[0]
    assert failed.positions is None and "inverted" in failed.failure
    assert np.all(scheduler.simulator.body_acceleration == 0.0)
