"""Tests of core/physics/model_fit.py: the body load and the Poisson ratio are fitted jointly to the
normal components of a correction at the surface, each vertex weighted by the estimate's
information about it."""

import numpy as np

from meshfg_ros.core.physics.body_load import BodyLoadEstimate
from meshfg_ros.core.physics.model_fit import learn, surface_fit
from meshfg_ros.core.physics.poisson_ratio import PoissonRatioEstimate
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig
from meshfg_ros.synthetic.meshing import cube_mesh

FAR_AWAY = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0])  # a tool that touches nothing
STIFF = 3.0e6  # a 10 cm cube sags by tens of micrometres under 1 g: small strain to about 1e-3
TRUE_ACCELERATION = np.array([2.0, -1.0, -9.81])


def fixed_cube():
    mesh = cube_mesh(side=0.1, divisions=4)
    return mesh.with_fixed(np.flatnonzero(mesh.vertices[:, 2] < 1e-9))


def model(mesh, poisson_ratio=0.45, gravity=(0.0, 0.0, 0.0)):
    built = ElasticSimulator(mesh, SimulatorConfig(youngs_modulus=STIFF, poisson_ratio=poisson_ratio,
                                                   gravity=tuple(gravity), substeps=1, solver_iterations=3))
    built.reset(FAR_AWAY)
    return built


def settled(simulator):
    state = simulator.rest_mesh.vertices
    for _ in range(3):
        state = simulator.predict(state, FAR_AWAY, 1.0)
    return state


def sure_everywhere(mesh):
    std = np.full(mesh.vertex_count, 1e-3)
    std[mesh.fixed_vertices] = 0.0
    return std


def test_a_load_and_a_compressibility_are_told_apart():
    """A truth that sags under another load and is less compressible: fitted jointly, both are
    recovered; the load alone would take up part of the compressibility's error, and the
    reverse."""
    mesh = fixed_cube()
    truth = settled(model(mesh, 0.48, TRUE_ACCELERATION))
    simulator = model(mesh)
    load, ratio = BodyLoadEstimate(simulator), PoissonRatioEstimate(simulator)
    for _ in range(6):  # each correction is what the model still misses
        learn(mesh, load, ratio, settled(simulator), truth, sure_everywhere(mesh))
    assert np.linalg.norm(load.acceleration - TRUE_ACCELERATION) < 1e-2 * np.linalg.norm(TRUE_ACCELERATION)
    assert abs(ratio.poisson_ratio - 0.48) < 1e-3
    assert np.abs(settled(simulator) - truth).max() < 1e-2 * np.abs(truth - mesh.vertices).max()
    alone = model(mesh)
    only_load = BodyLoadEstimate(alone)
    for _ in range(6):
        learn(mesh, only_load, None, settled(alone), truth, sure_everywhere(mesh))
    assert np.abs(settled(alone) - truth).max() > 10 * np.abs(settled(simulator) - truth).max()


def test_the_tangential_part_of_a_correction_teaches_nothing():
    """Point-to-surface factors measure the normal component; the rest of a correction is the
    prior's extension of it through the very model being fitted."""
    mesh = fixed_cube()
    simulator = model(mesh)
    predicted = settled(simulator)
    correction = settled(model(mesh, 0.48, TRUE_ACCELERATION)) - predicted
    normals = mesh.vertex_normals(predicted)
    tangential = correction - normals * np.einsum("ij,ij->i", normals, correction)[:, None]
    responses = np.stack([*BodyLoadEstimate(simulator).responses(), PoissonRatioEstimate(simulator).sensitivity(predicted)])
    assert np.abs(surface_fit(mesh, predicted, correction, sure_everywhere(mesh), responses)).max() > 1e-3
    np.testing.assert_allclose(surface_fit(mesh, predicted, tangential, sure_everywhere(mesh), responses), 0.0,
                               rtol=0, atol=1e-12)


def test_a_vertex_the_estimate_is_unsure_of_weighs_less():
    mesh = fixed_cube()
    simulator = model(mesh)
    predicted = settled(simulator)
    correction = settled(model(mesh, gravity=TRUE_ACCELERATION)) - predicted
    responses = BodyLoadEstimate(simulator).responses()
    normals = mesh.vertex_normals(predicted)
    top = np.flatnonzero(normals[:, 2] > 0.99)[0]
    disturbed = correction.copy()
    disturbed[top] += 0.01 * normals[top]  # a correction 10 mm out of the body at one vertex
    std = sure_everywhere(mesh)
    clean = surface_fit(mesh, predicted, correction, std, responses)
    sure = surface_fit(mesh, predicted, disturbed, std, responses)
    std[top] = 1e3  # the estimate knows next to nothing of that vertex (a weight 1e-12 of the others)
    unsure = surface_fit(mesh, predicted, disturbed, std, responses)
    assert np.linalg.norm(clean - TRUE_ACCELERATION) < 1e-2 * np.linalg.norm(TRUE_ACCELERATION)
    assert np.linalg.norm(sure - clean) > 0.1 * np.linalg.norm(clean)
    assert np.linalg.norm(unsure - clean) < 1e-6 * np.linalg.norm(clean)


def test_no_weighted_surface_teaches_nothing():
    mesh = fixed_cube()
    simulator = model(mesh)
    predicted = settled(simulator)
    responses = BodyLoadEstimate(simulator).responses()
    nowhere = np.zeros(mesh.vertex_count)
    nowhere[0] = np.nan
    assert np.all(surface_fit(mesh, predicted, np.ones_like(predicted), nowhere, responses) == 0.0)
