"""Factors: Jacobians against finite differences / autograd, normal-equation terms, noise models,
robust kernels, and the factor graph's assembly against an independent dense J^T W J."""

import numpy as np
import pytest
import scipy.sparse
import torch
from torch.func import jacrev, vmap

from meshfg_ros.benchmarks.baselines import WhitenedProblem, freeze_associations
from meshfg_ros.core.estimation.factor_graph import FactorGraph
from meshfg_ros.core.estimation.factors import (
    CURVATURE_FLOOR,
    Factor,
    FactorError,
    PhysicsPriorFactor,
    PointToSurfaceFactor,
    TemporalFactor,
    prior_scale,
)
from meshfg_ros.core.geometry.closest_point import REGION_FACE, ClosestPointIndex
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.synthetic.meshing import cube_mesh
from meshfg_ros.evaluation.metrics import sample_surface
from meshfg_ros.core.estimation.noise import (
    CauchyKernel,
    HuberKernel,
    IdentityNoise,
    IsotropicNoise,
    NoiseModelError,
    PerPointNoise,
    RobustKernelError,
    make_robust_kernel,
)

from test_closest_point import torch_closest_point


@pytest.fixture(scope="module")
def cube():
    mesh = cube_mesh(side=0.1, divisions=3)
    return mesh.with_fixed(np.flatnonzero(mesh.vertices[:, 2] < 1e-9))


@pytest.fixture(scope="module")
def model(cube):
    return ElasticModel(cube.vertices, cube.tetrahedra, 3e3, 0.45)


def deformed(cube, amount=1.0, seed=0):
    rng = np.random.default_rng(seed)
    height = cube.vertices[:, 2:] / 0.1
    return cube.vertices + amount * (np.array([[0.004, 0.001, -0.001]]) * height + rng.normal(scale=4e-4, size=cube.vertices.shape))


def noisy_points(state, triangles, count=300, seed=0):
    points = sample_surface(state, triangles, count, seed=seed)
    return points + np.random.default_rng(seed).normal(scale=1.5e-3, size=points.shape)


def central_differences(function, state, step=1e-7):
    """d function(state) / d state.ravel() by central differences, (m, 3N)."""
    flat = state.reshape(-1)
    columns = []
    for index in range(flat.size):
        plus, minus = flat.copy(), flat.copy()
        plus[index] += step
        minus[index] -= step
        columns.append((function(plus.reshape(-1, 3)) - function(minus.reshape(-1, 3))) / (2 * step))
    return np.stack(columns, axis=1)


def test_point_to_surface_keeps_the_last_two_associations(cube, monkeypatch):
    """LM asks for the cost at a trial, at its extrapolation, and then (the extrapolation not
    taken) linearises at the trial: the second visit to a state reuses its exact association;
    a third state's pushes the oldest out."""
    from meshfg_ros.core.geometry import closest_point

    first, second, third = (deformed(cube, seed=seed) for seed in (1, 2, 3))
    points = noisy_points(first, cube.surface_triangles)
    selection = ClosestPointIndex(first, cube.surface_triangles).associate(points)
    factor = PointToSurfaceFactor(0, points, cube.surface_triangles, cube.vertex_count, IsotropicNoise(1e-3),
                                  association_at=(first, selection))
    queries = []
    original = closest_point.ClosestPointIndex.associate
    monkeypatch.setattr(closest_point.ClosestPointIndex, "associate",
                        lambda index, points, *args: queries.append(1) or original(index, points, *args))
    costs = [factor.cost({0: state}) for state in (second, third, second, third)]
    assert len(queries) == 2 and costs[:2] == costs[2:]
    factor.cost({0: first})  # the selection's association was pushed out by the other two
    assert len(queries) == 3


def test_point_to_surface_jacobian_matches_finite_differences(cube):
    state = deformed(cube)
    factor = PointToSurfaceFactor(0, noisy_points(state, cube.surface_triangles), cube.surface_triangles,
                                  cube.vertex_count, IsotropicNoise(1e-3))
    factor.freeze_association({0: state})  # no triangle switch inside the difference stencil
    analytic = factor.jacobians({0: state})[0].toarray()
    numeric = central_differences(lambda s: factor.residual({0: s}), state)
    np.testing.assert_allclose(analytic, numeric, rtol=0, atol=1e-7)
    assert np.abs(analytic).max() > 0.5


def test_point_to_surface_jacobian_matches_torch_autograd(cube):
    state = deformed(cube, seed=1)
    points = noisy_points(state, cube.surface_triangles, 200, seed=1)
    factor = PointToSurfaceFactor(0, points, cube.surface_triangles, cube.vertex_count)
    triangles = cube.surface_triangles[factor.associate({0: state}).triangle]
    analytic = factor.jacobians({0: state})[0].toarray()

    torch_points = torch.as_tensor(points)

    def residuals(flat_state):
        corners = flat_state.reshape(-1, 3)[torch.as_tensor(triangles)]
        closest = vmap(torch_closest_point)(torch_points, corners[:, 0], corners[:, 1], corners[:, 2])
        return (closest - torch_points).reshape(-1)

    reference = jacrev(residuals)(torch.tensor(state.reshape(-1))).numpy()
    np.testing.assert_allclose(analytic, reference, rtol=1e-9, atol=1e-12)


def test_physics_and_temporal_jacobians_match_finite_differences(cube, model):
    state, previous = deformed(cube), deformed(cube, 0.5, seed=3)
    prior = PhysicsPriorFactor(1, deformed(cube, 1.2, seed=2), model, "corotational", scale=1.0)
    temporal = TemporalFactor(1, 5e-3, previous_key=0)
    states = {0: previous, 1: state}
    np.testing.assert_allclose(prior.jacobians(states)[1].toarray(),
                               central_differences(lambda s: prior.residual({1: s}), state), atol=1e-8)
    for key in (0, 1):
        def residual(s, key=key):
            return temporal.residual({**states, key: s})
        np.testing.assert_allclose(temporal.jacobians(states)[key].toarray(),
                                   central_differences(residual, states[key]), atol=1e-8)


def test_linearize_equals_weighted_normal_equations(cube, model):
    state = deformed(cube)
    points = noisy_points(state, cube.surface_triangles)
    sigmas = np.random.default_rng(4).uniform(5e-4, 2e-3, len(points))
    for robust in (None, HuberKernel(1e-3), CauchyKernel(1e-3)):
        factor = PointToSurfaceFactor(0, points, cube.surface_triangles, cube.vertex_count, PerPointNoise(sigmas),
                                      robust)
        terms = factor.linearize({0: state})
        jacobian = factor.jacobians({0: state})[0]
        residual = factor.residual({0: state}).reshape(-1, 3)
        squared = (residual**2).sum(axis=1)
        weights = 1.0 / sigmas**2 * (1.0 if robust is None else robust.weight(squared))
        # Along the distance, a face point's term has its cost's curvature, at least
        # CURVATURE_FLOOR of the IRLS weight; edge and vertex points keep the IRLS weight.
        curvatures = weights if robust is None else np.maximum(robust.curvature(squared) / sigmas**2,
                                                               CURVATURE_FLOOR * weights)
        weight_rows = scipy.sparse.diags(np.repeat(weights, 3))
        blocks = terms.point_blocks[0]
        tri_dofs = (3 * cube.surface_triangles[blocks.triangle][:, :, None] + np.arange(3)).reshape(-1, 9)
        gradient = np.bincount(tri_dofs.reshape(-1), blocks.gradient.reshape(-1), minlength=jacobian.shape[1])
        np.testing.assert_allclose(gradient, jacobian.T @ (weight_rows @ residual.reshape(-1)), rtol=1e-10, atol=1e-6)
        hessian = np.zeros((jacobian.shape[1],) * 2)
        hessian_dofs = (3 * cube.surface_triangles[blocks.hessian_triangle][:, :, None] + np.arange(3)).reshape(-1, 9)
        np.add.at(hessian, (np.repeat(hessian_dofs, 9, axis=1), np.tile(hessian_dofs, (1, 9))), blocks.hessian)
        # Gauss-Newton on the distances: a point inside its face contributes the normal row
        # n^T J (the derivative of its signed distance), one on an edge or vertex all of J.
        association = factor.associate({0: state})
        corners = state[cube.surface_triangles[association.triangle]]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        dense = jacobian.toarray().reshape(len(points), 3, -1)
        face = association.region == REGION_FACE
        normal_rows = np.einsum("ki,kic->kc", normals[face], dense[face])
        expected = (normal_rows.T * curvatures[face]) @ normal_rows
        other_rows = dense[~face].reshape(-1, dense.shape[2])
        expected += (other_rows.T * np.repeat(weights[~face], 3)) @ other_rows
        np.testing.assert_allclose(hessian, expected, rtol=1e-10, atol=1e-3)
        expected_cost = 0.5 * np.sum(squared / sigmas**2) if robust is None else 0.5 * np.sum(robust.rho(squared) / sigmas**2)
        assert terms.cost == pytest.approx(expected_cost, rel=1e-12)


@pytest.mark.parametrize("frozen", [False, True])
def test_point_factors_evaluated_together_equal_each_alone(cube, frozen):
    """A graph linearises the point factors of several states in one pass (linearize_batch,
    cost_batch): each factor's cost, gradient blocks and Hessian rows are those it gives alone,
    for clouds of different sizes (one empty, one far off the surface, so that edge and vertex
    points fall on every state) with a robust kernel."""
    states = {key: deformed(cube, 0.3 * (key + 1), seed=30 + key) for key in range(4)}

    def factors():
        made = []
        for key, count in zip(states, (150, 0, 90, 40)):
            points = noisy_points(states[key], cube.surface_triangles, max(count, 1), seed=key)[:count]
            if key == 3:
                points = cube.vertices.mean(axis=0) + 1.3 * (points - cube.vertices.mean(axis=0))
            factor = PointToSurfaceFactor(key, points, cube.surface_triangles, cube.vertex_count, IsotropicNoise(1e-3),
                                          CauchyKernel(2e-3))
            if frozen:
                factor.freeze_association(states)
            made.append(factor)
        return made

    together = factors()
    regions = np.concatenate([factor.associate(states).region for factor in together])
    assert np.count_nonzero(regions != REGION_FACE) >= 10
    linearized = PointToSurfaceFactor.linearize_batch(together, states)
    gradient_only = PointToSurfaceFactor.linearize_batch(together, states, hessian=False)
    costs = PointToSurfaceFactor.cost_batch(together, states)
    for factor, terms, without, cost in zip(factors(), linearized, gradient_only, costs):
        alone = factor.linearize(states)
        assert terms.cost == pytest.approx(alone.cost, rel=1e-13) and cost == pytest.approx(alone.cost, rel=1e-13)
        assert without.cost == pytest.approx(alone.cost, rel=1e-13)
        if not factor.num_points:
            assert not terms.point_blocks and alone.cost == 0.0
            continue
        blocks, expected = terms.point_blocks[factor.keys[0]], alone.point_blocks[factor.keys[0]]
        np.testing.assert_array_equal(blocks.triangle, expected.triangle)
        np.testing.assert_allclose(blocks.gradient, expected.gradient, rtol=1e-13, atol=0.0)
        np.testing.assert_array_equal(blocks.hessian_triangle, expected.hessian_triangle)
        np.testing.assert_allclose(blocks.hessian, expected.hessian, rtol=1e-13, atol=1e-9 * np.abs(expected.hessian).max())
        assert without.point_blocks[factor.keys[0]].hessian is None


@pytest.mark.parametrize("distance_in_scales", [0.3, 0.5, 2.0])
def test_face_point_term_is_the_cost_curvature_along_the_normal(cube, distance_in_scales):
    """Moving a point's triangle along its normal by t changes the point's distance by t: the
    second derivative of its cost in t (central differences) is the term's weight, where it is
    above the floor; beyond it (a far point, negative curvature) the term is the floor."""
    state = cube.vertices.astype(np.float64)
    kernel = CauchyKernel(2e-3)
    sigma = 1e-3
    point = np.array([[0.0331, 0.0173, 0.1 + distance_in_scales * kernel.scale]])  # above the top face
    factor = PointToSurfaceFactor(0, point, cube.surface_triangles, cube.vertex_count, IsotropicNoise(sigma), kernel)
    assert factor.associate({0: state}).region[0] == REGION_FACE
    blocks = factor.linearize({0: state}).point_blocks[0]
    assert blocks.hessian_triangle.tolist() == blocks.triangle.tolist()  # one point: one row
    triangle = cube.surface_triangles[blocks.triangle[0]]
    normal_move = np.tile([0.0, 0.0, 1.0], 3)  # the three corners up along the top face's normal
    term = normal_move @ blocks.hessian[0].reshape(9, 9) @ normal_move

    def cost(t):
        moved = state.copy()
        moved[triangle] += [0.0, 0.0, t]
        return factor.cost({0: moved})

    step = 1e-6
    curvature = (cost(step) - 2.0 * cost(0.0) + cost(-step)) / step**2
    irls = float(kernel.weight(np.array([(distance_in_scales * kernel.scale) ** 2]))[0]) / sigma**2
    if curvature >= CURVATURE_FLOOR * irls:
        assert term == pytest.approx(curvature, rel=1e-5)
        assert term < irls  # IRLS overstates it
    else:
        assert term == pytest.approx(CURVATURE_FLOOR * irls, rel=1e-12)


def test_prior_scale_sets_mean_information(model, cube):
    stiffness = model.stiffness()
    scale = prior_scale(stiffness, 2e-3)
    assert np.mean(scale * stiffness.diagonal()) == pytest.approx(1.0 / 2e-3**2, rel=1e-12)
    prior = PhysicsPriorFactor(0, cube.vertices, model, "linear", scale=scale, ridge=7.0)
    information = prior.information(cube.vertices)
    np.testing.assert_allclose(information.diagonal(), scale * stiffness.diagonal() + 7.0)
    r = np.random.default_rng(5).normal(size=cube.vertices.shape)
    states = {0: cube.vertices - r}
    assert prior.cost(states) == pytest.approx(0.5 * r.reshape(-1) @ (information @ r.reshape(-1)), rel=1e-12)


def test_physics_information_keeps_the_stiffness_pattern(cube, model):
    """The ridge goes onto K's own diagonal: the information has K's pattern at every state (the
    graph maps it onto its block pattern once) and the values of scale K + ridge I exactly."""
    state = deformed(cube, 8.0)
    stiffness = model.stiffness(state, kind="corotational")
    information = PhysicsPriorFactor(0, state, model, "corotational", scale=3.0, ridge=7.0).information(state)
    assert np.array_equal(information.indptr, stiffness.indptr)
    assert np.array_equal(information.indices, stiffness.indices)
    expected = (3.0 * stiffness + 7.0 * scipy.sparse.identity(stiffness.shape[0])).toarray()
    assert np.array_equal(information.toarray(), expected)
    rest = PhysicsPriorFactor(0, cube.vertices, model, "corotational", ridge=1.0).information(cube.vertices)
    assert np.array_equal(rest.indices, information.indices)


def test_physics_information_is_held_until_invalidated(cube, model):
    state = deformed(cube, 8.0)
    prior = PhysicsPriorFactor(0, state, model, "corotational")
    first = prior.information(cube.vertices)
    assert abs(prior.information(state) - first).max() == 0.0
    prior.invalidate_information()
    assert abs(prior.information(state) - first).max() > 1e-3 * abs(first).max()


def test_association_follows_the_surface_exactly(cube):
    start = cube.vertices
    points = noisy_points(deformed(cube, 2.0), cube.surface_triangles, 400, seed=6)
    factor = PointToSurfaceFactor(0, points, cube.surface_triangles, cube.vertex_count)
    moved = deformed(cube, 3.0, seed=7)
    from meshfg_ros.core.geometry.closest_point import brute_force_closest

    reference = brute_force_closest(points, moved, cube.surface_triangles)
    np.testing.assert_allclose(factor.associate({0: moved}).distance, reference.distance, atol=1e-15)


def test_noise_models_and_robust_kernels():
    assert np.allclose(IsotropicNoise(0.5).point_weights(3), 4.0)
    assert np.allclose(IdentityNoise().point_weights(2), 1.0)
    per_point = PerPointNoise([1.0, 4.0])
    assert np.allclose(per_point.point_weights(2), [1.0, 1.0 / 16.0])
    with pytest.raises(NoiseModelError):
        IsotropicNoise(0.0)
    with pytest.raises(NoiseModelError):
        PerPointNoise([1.0]).point_weights(2)
    huber, cauchy = HuberKernel(2.0), CauchyKernel(2.0)
    squared = np.array([1.0, 4.0, 16.0])
    np.testing.assert_allclose(huber.rho(squared), [1.0, 4.0, 2 * 2 * 4 - 4])
    np.testing.assert_allclose(huber.weight(squared), [1.0, 1.0, 0.5])
    np.testing.assert_allclose(cauchy.rho(squared), 4 * np.log1p(squared / 4))
    np.testing.assert_allclose(cauchy.weight(squared), 1 / (1 + squared / 4))
    # curvature: d^2/dd^2 of 0.5 rho(d^2), by central differences in d.
    for kernel in (huber, cauchy):
        for distance in (0.5, 1.5, 3.0, 5.0):
            step = 1e-4
            half_cost = [0.5 * float(kernel.rho(np.array([(distance + k * step) ** 2]))[0]) for k in (-1, 0, 1)]
            expected = (half_cost[0] - 2.0 * half_cost[1] + half_cost[2]) / step**2
            assert float(kernel.curvature(np.array([distance**2]))[0]) == pytest.approx(expected, abs=1e-6)
    assert cauchy.curvature(np.array([16.0]))[0] < 0.0 < cauchy.weight(np.array([16.0]))[0]
    assert make_robust_kernel("none", 1.0) is None and make_robust_kernel(None, 1.0) is None
    with pytest.raises(RobustKernelError):
        make_robust_kernel("tukey", 1.0)


def build_window(cube, model, threshold=0.0, keys=3):
    graph = FactorGraph(cube.vertex_count, cube.tetrahedra, cube.surface_triangles, cube.fixed_vertices,
                        cube.vertices, threshold)
    scale = prior_scale(model.stiffness(), 1e-3, graph.free_dofs)
    for key in range(keys):
        truth = deformed(cube, 0.5 * (key + 1), seed=10 + key)
        predicted = deformed(cube, 0.5 * (key + 1), seed=20 + key)
        graph.add_state(key, predicted)
        graph.add_factor(PhysicsPriorFactor(key, predicted, model, "corotational", scale=scale, ridge=1.0))
        graph.add_factor(PointToSurfaceFactor(key, noisy_points(truth, cube.surface_triangles, 200, key),
                                              cube.surface_triangles, cube.vertex_count, IsotropicNoise(1e-3)))
        graph.add_factor(TemporalFactor(key, 5e-3, previous_key=key - 1) if key
                         else TemporalFactor(key, 5e-3, anchor=cube.vertices))
    return graph


def test_graph_assembly_equals_dense_whitened_normal_equations(cube, model):
    graph = build_window(cube, model)
    freeze_associations(graph)
    x = graph.get_x() + np.random.default_rng(8).normal(scale=1e-4, size=graph.get_x().size)
    system, gradient, cost = graph.linearize(x)
    whitened = WhitenedProblem(graph)
    jacobian, residual = whitened.jacobian(x), whitened.residual(x)
    np.testing.assert_allclose(system.to_csr().toarray(), (jacobian.T @ jacobian).toarray(), rtol=1e-9, atol=1e-3)
    np.testing.assert_allclose(gradient, jacobian.T @ residual, rtol=1e-9, atol=1e-6)
    assert cost == pytest.approx(0.5 * residual @ residual, rel=1e-12)
    assert graph.cost(x) == pytest.approx(cost, rel=1e-12)
    probe = np.random.default_rng(9).normal(size=x.size)
    np.testing.assert_allclose(system.matvec(probe), system.to_csr() @ probe, rtol=1e-12, atol=1e-6)


def test_relinearization_threshold_reuses_the_quadratic_model(cube, model):
    graph = build_window(cube, model, threshold=1e-3)
    x = graph.get_x()
    graph.linearize(x)
    assert graph.relinearizations == 3
    small = x + 1e-5
    system, gradient, cost = graph.linearize(small)
    assert graph.relinearizations == 3  # nobody moved 1 mm: the cached models stand
    # The stand-in is the Gauss-Newton quadratic at x: c + g.d + d.H d / 2 and gradient g + H d.
    exact = build_window(cube, model, threshold=0.0)
    lin_system, lin_gradient, lin_cost = exact.linearize(x)
    d = small - x
    assert cost == pytest.approx(lin_cost + lin_gradient @ d + 0.5 * d @ lin_system.matvec(d), rel=1e-12)
    np.testing.assert_allclose(gradient, lin_gradient + lin_system.matvec(d), rtol=1e-10, atol=1e-8)
    _, _, exact_cost = exact.linearize(small)
    assert cost == pytest.approx(exact_cost, rel=1e-4)  # and close to the re-linearised cost
    graph.linearize(x + 2e-3)
    assert graph.relinearizations == 6


def test_gradient_without_hessians_rebases_the_model(cube, model):
    """FactorGraph.gradient gives linearize's gradient and cost without new Hessians: a moved
    state's quadratic is re-based at x (exact cost and gradient, Hessian and revision kept)."""
    exact = build_window(cube, model, threshold=0.0)
    x = exact.get_x()
    step = np.random.default_rng(11).normal(scale=2e-4, size=x.size)
    reference = build_window(cube, model, threshold=0.0)
    reference.linearize(x)
    _, reference_gradient, reference_cost = reference.linearize(x + step)
    system, _, _ = exact.linearize(x)
    revisions = list(system.revisions)
    gradient, cost = exact.gradient(x + step)
    np.testing.assert_allclose(gradient, reference_gradient, rtol=1e-10, atol=1e-8)
    assert cost == pytest.approx(reference_cost, rel=1e-12)
    assert exact.relinearizations == 3  # no state re-linearised (no new Hessians)
    assert exact.cost(x + step) == pytest.approx(reference_cost, rel=1e-12)
    # Threshold 0: the next linearize re-linearises the re-based states all the same.
    system_after, gradient_after, _ = exact.linearize(x + step)
    assert exact.relinearizations == 6 and system_after.revisions != revisions
    np.testing.assert_allclose(gradient_after, reference_gradient, rtol=1e-10, atol=1e-8)
    # Threshold 1 mm, states moved by more: gradient re-bases them; the next linearize keeps
    # their Hessians (the threshold counts from the re-based point) and their model is exact
    # to first order there. Only the exact key (threshold 0) is re-linearised.
    relaxed = build_window(cube, model, threshold=1e-3)
    relaxed.exact_keys = {2}
    far = 10.0 * step
    reference = build_window(cube, model, threshold=0.0)
    reference.linearize(x)  # K is held from the first linearisation
    _, reference_gradient, reference_cost = reference.linearize(x + far)
    system, _, _ = relaxed.linearize(x)
    relaxed.gradient(x + far)
    system_next, gradient_next, cost_next = relaxed.linearize(x + far)
    assert relaxed.relinearizations == 4
    assert system_next.revisions[:2] == system.revisions[:2]
    np.testing.assert_allclose(gradient_next, reference_gradient, rtol=1e-10, atol=1e-8)
    assert cost_next == pytest.approx(reference_cost, rel=1e-12)


def test_graph_rejects_bad_factors(cube, model):
    graph = FactorGraph(cube.vertex_count, cube.tetrahedra, cube.surface_triangles)
    with pytest.raises(FactorError, match="unknown state"):
        graph.add_factor(TemporalFactor(1, 1e-3, anchor=cube.vertices))
    with pytest.raises(FactorError):
        TemporalFactor(1, 1e-3)
    with pytest.raises(FactorError, match="shape"):
        PointToSurfaceFactor(0, np.zeros((3, 2)), cube.surface_triangles, cube.vertex_count)
    with pytest.raises(FactorError):
        prior_scale(model.stiffness(), 0.0)
    graph.add_state(0, cube.vertices)
    graph.add_state(1, cube.vertices)

    class TwoStates(Factor):  # spans two states without declaring identity blocks
        keys = (0, 1)

    with pytest.raises(FactorError, match="identity_blocks"):
        graph.add_factor(TwoStates())


def test_volume_barrier_gradient_hessian_and_bounds(cube):
    """Zero on states that keep half their reference volume; its gradient is the derivative of
    its cost (finite differences) and its Gauss-Newton term the outer product of the residual's
    Jacobian; infinite once an element inverts."""
    from meshfg_ros.core.estimation.factors import BARRIER_VOLUME_RATIO, VolumeBarrierFactor
    from meshfg_ros.core.geometry.mesh import signed_volumes

    reference = signed_volumes(cube.vertices, cube.tetrahedra)
    barrier = VolumeBarrierFactor(0, cube.tetrahedra, reference, 2.0)
    assert barrier.cost({0: cube.vertices}) == 0.0
    assert not barrier.linearize({0: cube.vertices}).element_blocks
    corner = int(np.argmax(cube.vertices.sum(axis=1)))
    inward = cube.vertices.mean(axis=0) - cube.vertices[corner]
    for fraction in np.linspace(0.05, 1.0, 96):  # the first move that squashes an element below J_c
        squashed = cube.vertices.copy()
        squashed[corner] += fraction * inward
        ratios = signed_volumes(squashed, cube.tetrahedra) / reference
        if ratios.min() < 0.8 * BARRIER_VOLUME_RATIO:
            break
    assert ratios.min() > 0.0 and ratios.min() < BARRIER_VOLUME_RATIO
    terms = barrier.linearize({0: squashed})
    blocks = terms.element_blocks[0]
    gradient = np.zeros(squashed.size)
    np.add.at(gradient, (3 * cube.tetrahedra[blocks.tetrahedron][:, :, None] + np.arange(3)).reshape(-1),
              blocks.gradient.reshape(-1))
    step = 1e-7
    direction = np.random.default_rng(9).normal(size=squashed.shape)
    plus = barrier.cost({0: squashed + step * direction})
    minus = barrier.cost({0: squashed - step * direction})
    assert (plus - minus) / (2 * step) == pytest.approx(gradient @ direction.reshape(-1), rel=1e-5)
    jacobian = barrier.jacobians({0: squashed})[0].toarray()
    hessian = np.zeros((squashed.size,) * 2)
    dofs = (3 * cube.tetrahedra[blocks.tetrahedron][:, :, None] + np.arange(3)).reshape(-1, 12)
    np.add.at(hessian, (np.repeat(dofs, 12, axis=1), np.tile(dofs, (1, 12))), blocks.hessian)
    residual = barrier.residual({0: squashed})
    np.testing.assert_allclose(jacobian.T @ residual, gradient, rtol=1e-9, atol=1e-12 * np.abs(gradient).max())
    assert np.all(np.linalg.eigvalsh(hessian) > -1e-9 * np.abs(hessian).max())
    inverted = cube.vertices.copy()
    inverted[corner] = cube.vertices.mean(axis=0) - (cube.vertices[corner] - cube.vertices.mean(axis=0))
    assert barrier.cost({0: inverted}) == np.inf


def test_volume_barrier_keeps_the_last_states_volumes(cube, monkeypatch):
    """LM evaluates a trial's cost and then linearises there: the barrier computes that state's
    volumes once. Another state, or the same array changed in place, is computed afresh."""
    from meshfg_ros.core.estimation import factors
    from meshfg_ros.core.geometry import mesh
    from meshfg_ros.core.geometry.mesh import signed_volumes

    barrier = factors.VolumeBarrierFactor(0, cube.tetrahedra, signed_volumes(cube.vertices, cube.tetrahedra), 2.0)
    computed = []
    monkeypatch.setattr(mesh, "signed_volumes", lambda *args, **kw: computed.append(1) or signed_volumes(*args, **kw))
    state = deformed(cube, 1.0, seed=4)
    cost = barrier.cost({0: state})
    assert barrier.linearize({0: state}).cost == cost and len(computed) == 1
    barrier.cost({0: deformed(cube, 1.0, seed=5)})
    assert len(computed) == 2
    state[0] += 1e-3
    barrier.cost({0: state})
    assert len(computed) == 3


def test_barriers_and_the_inversion_guard_share_the_window_volumes(cube, monkeypatch):
    """The barriers of a window's states evaluate their volumes in one call, and the graph's
    inversion guard at the same x reuses them; the values are those of signed_volumes."""
    from meshfg_ros.core.estimation import factors
    from meshfg_ros.core.geometry import mesh
    from meshfg_ros.core.geometry.mesh import signed_volumes

    graph = FactorGraph(cube.vertex_count, cube.tetrahedra, cube.surface_triangles, cube.fixed_vertices,
                        cube.vertices)
    reference = signed_volumes(cube.vertices, cube.tetrahedra)
    for key, seed in ((0, 7), (1, 8)):
        graph.add_state(key, deformed(cube, 0.5, seed=seed))
        graph.add_factor(factors.VolumeBarrierFactor(key, cube.tetrahedra, reference, 2.0,
                                                     element_volumes=graph.element_volumes))
    calls = []
    monkeypatch.setattr(mesh, "signed_volumes", lambda vertices, *args, **kw: calls.append(np.shape(vertices))
                        or signed_volumes(vertices, *args, **kw))
    x = graph.get_x()
    cost = graph.cost(x)
    assert calls == [(2, cube.vertex_count, 3)]
    graph.step_fraction(x, 1e-6 * np.ones_like(x))
    assert len(calls) == 1
    states = graph.states_from_x(x)
    expected = sum(factors.VolumeBarrierFactor(key, cube.tetrahedra, reference, 2.0).cost(states) for key in (0, 1))
    assert cost == pytest.approx(expected, rel=1e-12)
    with pytest.raises(FactorError, match="other tetrahedra"):
        factors.VolumeBarrierFactor(0, cube.tetrahedra[::-1], reference, 2.0, element_volumes=graph.element_volumes)
