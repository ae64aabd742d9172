"""Ground-truth solver: neo-Hookean residual/tangent consistency, small-strain limit,
equilibrium under body load, sticky sphere contact, errors."""

import numpy as np
import pytest
import scipy.sparse

from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.geometry.mesh import signed_volumes
from meshfg_ros.synthetic.meshing import structured_box_mesh
from meshfg_ros.synthetic import hyperelastic
from meshfg_ros.synthetic.hyperelastic import (
    EquilibriumError,
    HyperelasticInputError,
    NeoHookeanSolid,
    StickySphereContact,
    lame_fields,
)

GRAVITY_LOAD = np.array([0.0, 0.0, -1000.0 * 9.81])  # N/m^3


def block(divisions=(3, 3, 2), size=(0.02, 0.02, 0.01)):
    """Box with its bottom (z = 0) fixed."""
    mesh = structured_box_mesh(size, divisions)
    return mesh.with_fixed(np.flatnonzero(mesh.vertices[:, 2] == 0.0))


def heterogeneous_solid(mesh, seed=0):
    rng = np.random.default_rng(seed)
    return NeoHookeanSolid(mesh, 3e3 * (1.0 + rng.random(mesh.tetrahedron_count)),
                           0.3 + 0.18 * rng.random(mesh.tetrahedron_count))


def deformed(mesh, seed=1, scale=6e-4):
    """A random smooth-ish deformation (strains of several per cent) with positive volumes."""
    rng = np.random.default_rng(seed)
    positions = mesh.vertices + rng.normal(scale=scale, size=mesh.vertices.shape)
    assert np.all(signed_volumes(positions, mesh.tetrahedra) > 0.0)
    return positions


def test_residual_is_the_energy_gradient_and_tangent_its_derivative():
    mesh = block()
    solid = heterogeneous_solid(mesh)
    positions = deformed(mesh)
    rng = np.random.default_rng(2)
    residual = solid.residual(positions, GRAVITY_LOAD)
    tangent = solid.tangent(positions)
    step = 1e-8
    for _ in range(3):
        direction = rng.normal(size=positions.shape)
        energy_slope = (solid.energy(positions + step * direction, GRAVITY_LOAD)
                        - solid.energy(positions - step * direction, GRAVITY_LOAD)) / (2 * step)
        assert energy_slope == pytest.approx(residual @ direction.ravel(), rel=1e-6)
        residual_slope = (solid.residual(positions + step * direction, GRAVITY_LOAD)
                          - solid.residual(positions - step * direction, GRAVITY_LOAD)) / (2 * step)
        applied = tangent @ direction.ravel()
        assert np.linalg.norm(residual_slope - applied) < 1e-6 * np.linalg.norm(applied)
    assert abs(tangent - tangent.T).max() <= 1e-12 * abs(tangent).max()


def test_energy_is_infinite_on_an_inverted_state_and_residual_refuses_it():
    mesh = block()
    solid = heterogeneous_solid(mesh)
    flattened = mesh.vertices * np.array([1.0, 1.0, 0.0])
    assert solid.elastic_energy(flattened) == np.inf
    with pytest.raises(HyperelasticInputError, match="non-positive volume"):
        solid.residual(flattened)


def test_tangent_at_rest_is_the_linear_fem_stiffness():
    mesh = block()
    solid = NeoHookeanSolid(mesh, 4.5e3, 0.45)
    linear = ElasticModel(mesh.vertices, mesh.tetrahedra, 4.5e3, 0.45).stiffness(kind="linear")
    difference = abs(solid.tangent(mesh.vertices) - linear).max()
    assert difference < 1e-9 * abs(linear).max()
    force_scale = abs(linear).max() * 0.02  # stiffness times the block's size
    np.testing.assert_allclose(solid.residual(mesh.vertices), 0.0, rtol=0, atol=1e-14 * force_scale)


def test_lame_fields_match_the_isotropic_formulas_and_reject_bad_materials():
    mu, lam = lame_fields([2.6e3, 5.2e3], 0.3, 2)
    np.testing.assert_allclose(mu, [1e3, 2e3])
    np.testing.assert_allclose(lam, [1.5e3, 3e3])
    with pytest.raises(HyperelasticInputError, match="youngs_modulus"):
        lame_fields([1e3, -1.0], 0.3, 2)
    with pytest.raises(HyperelasticInputError, match="poisson_ratio"):
        lame_fields(1e3, 0.5, 2)


def test_equilibrium_under_body_load_balances_the_supports():
    mesh = block()
    solid = heterogeneous_solid(mesh)
    result = solid.equilibrium(mesh.vertices, body_force=GRAVITY_LOAD)
    free = np.setdiff1d(np.arange(mesh.vertex_count), mesh.fixed_vertices)
    free_dofs = (3 * free[:, None] + np.arange(3)).ravel()
    residual = solid.residual(result.positions, GRAVITY_LOAD)
    assert np.linalg.norm(residual[free_dofs]) <= result.tolerance
    assert result.residual_norm <= result.tolerance < 1e-6 * np.linalg.norm(solid.body_load(GRAVITY_LOAD))
    assert np.all(signed_volumes(result.positions, mesh.tetrahedra) > 0.0)
    np.testing.assert_array_equal(result.positions[mesh.fixed_vertices], mesh.vertices[mesh.fixed_vertices])
    # The supports carry the whole weight: residuals on fixed dofs sum to minus the load.
    weight = GRAVITY_LOAD * signed_volumes(mesh.vertices, mesh.tetrahedra).sum()
    reactions = residual.reshape(-1, 3)[mesh.fixed_vertices].sum(axis=0)
    np.testing.assert_allclose(reactions, -weight, rtol=1e-9, atol=1e-9 * np.linalg.norm(weight))
    sag = mesh.vertices[:, 2] - result.positions[:, 2]
    assert sag.max() > 1e-5  # the block sags visibly under its weight


def test_equilibrium_matches_linear_fem_at_small_load():
    mesh = block()
    solid = NeoHookeanSolid(mesh, 3e3, 0.4)
    load = GRAVITY_LOAD * 1e-3  # displacements ~1e-8 of the size: the linear regime
    result = solid.equilibrium(mesh.vertices, body_force=load)
    model = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.4)
    free = np.setdiff1d(np.arange(mesh.vertex_count), mesh.fixed_vertices)
    free_dofs = (3 * free[:, None] + np.arange(3)).ravel()
    stiffness = model.stiffness(kind="linear")[free_dofs][:, free_dofs].toarray()
    linear = np.linalg.solve(stiffness, solid.body_load(load)[free_dofs])
    nonlinear = (result.positions - mesh.vertices).ravel()[free_dofs]
    assert np.linalg.norm(nonlinear - linear) < 1e-4 * np.linalg.norm(linear)


def test_prescribed_vertices_reach_their_targets():
    mesh = block()
    solid = heterogeneous_solid(mesh)
    top = np.flatnonzero(mesh.vertices[:, 2] == mesh.vertices[:, 2].max())
    targets = mesh.vertices[top] + np.array([1e-3, 0.0, -1.5e-3])
    result = solid.equilibrium(mesh.vertices, top, targets)
    np.testing.assert_array_equal(result.positions[top], targets)
    assert result.residual_norm <= result.tolerance
    with pytest.raises(HyperelasticInputError, match="not fixed"):
        solid.equilibrium(mesh.vertices, mesh.fixed_vertices[:1], mesh.vertices[mesh.fixed_vertices[:1]])
    with pytest.raises(HyperelasticInputError, match="prescribed_positions"):
        solid.equilibrium(mesh.vertices, top, targets[:-1])


def test_newton_directions_solve_definite_and_indefinite_tangents():
    """A positive definite free-dof tangent is solved by Cholesky, its factor refactored for the
    next tangent of the same pattern; an indefinite one (shifted down past its smallest
    eigenvalue) by LU, as a lifting step needs its direction whatever the energy's slope."""
    mesh = block()
    solid = heterogeneous_solid(mesh)
    free = np.flatnonzero(np.repeat(~np.isin(np.arange(mesh.vertex_count), mesh.fixed_vertices), 3))
    tangent = solid.tangent(deformed(mesh))[free][:, free].tocsr()
    rhs = np.random.default_rng(3).normal(size=free.size)
    direction = solid._symmetric_solve(tangent, rhs)
    assert np.linalg.norm(tangent @ direction - rhs) <= 1e-10 * np.linalg.norm(rhs)
    factor = solid._tangent_factor
    assert factor is not None
    stiffer = (2.0 * tangent).tocsr()
    assert np.linalg.norm(stiffer @ solid._symmetric_solve(stiffer, rhs) - rhs) <= 1e-10 * np.linalg.norm(rhs)
    assert solid._tangent_factor is factor

    dense = tangent.toarray()
    eigenvalues = np.linalg.eigvalsh(dense)
    shift = 0.5 * (eigenvalues[0] + eigenvalues[1])  # one negative eigenvalue, none zero
    indefinite = (tangent - shift * scipy.sparse.identity(free.size, format="csr")).tocsr()
    direction = solid._symmetric_solve(indefinite, rhs)
    np.testing.assert_allclose(direction, np.linalg.solve(dense - shift * np.eye(free.size), rhs), rtol=1e-8, atol=0.0)


def test_newton_that_runs_out_of_iterations_raises(monkeypatch):
    mesh = block()
    solid = heterogeneous_solid(mesh)
    monkeypatch.setattr(hyperelastic, "MAX_NEWTON_ITERATIONS", 1)
    with pytest.raises(EquilibriumError, match="did not converge in 1 iterations"):
        solid.equilibrium(mesh.vertices, body_force=GRAVITY_LOAD)


def test_sticky_tool_carries_the_vertices_it_touches_and_none_stays_inside():
    mesh = block(divisions=(4, 4, 2), size=(0.02, 0.02, 0.01))
    solid = NeoHookeanSolid(mesh, 3e3, 0.45)
    radius = 4e-3
    top_centre = np.array([0.01, 0.01, 0.01])
    centre_vertex = int(np.argmin(np.linalg.norm(mesh.vertices - top_centre, axis=1)))
    start = top_centre + np.array([0.0, 0.0, radius])  # touching the top's centre vertex
    contact = StickySphereContact(solid, radius, start, substeps=4)
    pressed = start - np.array([0.0, 0.0, 1e-3])
    positions = contact.advance(pressed)
    assert centre_vertex in contact.attached_vertices
    # Every attached vertex sits on the sphere; no other movable vertex is inside it.
    distances = np.linalg.norm(positions - pressed, axis=1)
    np.testing.assert_allclose(distances[contact.attached_vertices], radius, rtol=1e-12)
    movable = np.setdiff1d(np.arange(mesh.vertex_count), np.concatenate([mesh.fixed_vertices,
                                                                         contact.attached_vertices]))
    assert distances[movable].min() >= radius * (1.0 - 1e-9)
    assert contact.penetrating_vertices(pressed).size == 0
    # Dragging sideways: attached vertices follow the tool rigidly (they do not slide off).
    attached = contact.attached_vertices.copy()
    drag = np.array([1.5e-3, 0.0, 0.0])
    dragged = contact.advance(pressed + drag)
    np.testing.assert_allclose(dragged[attached] - positions[attached], np.broadcast_to(drag, (attached.size, 3)),
                               rtol=0, atol=1e-15)
    assert np.isin(attached, contact.attached_vertices).all()
    distances = np.linalg.norm(dragged - (pressed + drag), axis=1)
    movable = np.setdiff1d(movable, contact.attached_vertices)
    assert distances[movable].min() >= radius * (1.0 - 1e-9)
    # The tissue around the tool is pulled along: the top's far side moves in +x too.
    ring = np.flatnonzero((np.abs(mesh.vertices[:, 2] - 0.01) < 1e-12)
                          & (np.linalg.norm(mesh.vertices[:, :2] - 0.01, axis=1) > 6e-3))
    assert np.mean(dragged[ring, 0] - positions[ring, 0]) > 1e-5
    assert np.all(signed_volumes(dragged, mesh.tetrahedra) > 0.0)
    np.testing.assert_array_equal(dragged[mesh.fixed_vertices], mesh.vertices[mesh.fixed_vertices])


def test_contact_rejects_bad_arguments():
    solid = NeoHookeanSolid(block(), 3e3, 0.45)
    with pytest.raises(HyperelasticInputError, match="tool_radius"):
        StickySphereContact(solid, 0.0, np.zeros(3))
    with pytest.raises(HyperelasticInputError, match="substeps"):
        StickySphereContact(solid, 1e-3, np.zeros(3), substeps=0)
    with pytest.raises(HyperelasticInputError, match="tool_centre"):
        StickySphereContact(solid, 1e-3, np.zeros(2))
    with pytest.raises(HyperelasticInputError, match="body_force"):
        solid.body_load([0.0, np.nan, 0.0])
