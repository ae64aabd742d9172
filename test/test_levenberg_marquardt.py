"""Levenberg-Marquardt and the linear solvers: optimum against scipy and GTSAM, indefinite
systems, inversion rejection, solver agreement and fallback."""

import threading
from concurrent.futures import Future

import numpy as np
import pytest
import scipy.optimize
import scipy.sparse
import scipy.sparse.linalg

from meshfg_ros.benchmarks.baselines import compare_single_update
from meshfg_ros.core.estimation import covariance
from meshfg_ros.core.estimation.covariance import MarginalCovariance
from meshfg_ros.core.estimation.factor_graph import MIN_VOLUME_RATIO_PER_STEP, FactorGraph
from meshfg_ros.core.estimation.factors import PhysicsPriorFactor, prior_scale
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.solvers.levenberg_marquardt import LevenbergMarquardtConfig, levenberg_marquardt
from meshfg_ros.core.solvers.linear_solvers import (
    BESIDE_ITERATIONS,
    BORROWED_ITERATIONS,
    CholeskySolver,
    FallbackSolver,
    LinearSolveError,
    NotPositiveDefiniteError,
    PCGSolver,
    SuperLUSolver,
    make_linear_solver,
)
from meshfg_ros.core.solvers.linear_system import WindowSystem
from meshfg_ros.core.geometry.mesh import signed_volumes
from meshfg_ros.core.solvers import linear_solvers, sparse_cholesky
from meshfg_ros.synthetic.meshing import cube_mesh

from test_factors import build_window, cube, model  # noqa: F401  (fixtures)

TIGHT = LevenbergMarquardtConfig(max_iterations=200, cost_tolerance=1e-15, step_tolerance=1e-15,
                                 gradient_tolerance=1e-15)


class CurveFit:
    """r_i = a exp(b t_i) - y_i, a small nonlinear least-squares problem."""

    def __init__(self):
        self.t = np.linspace(0.0, 1.0, 30)
        self.y = 2.0 * np.exp(-1.3 * self.t) + 0.01 * np.sin(17 * self.t)

    def residual(self, x):
        return x[0] * np.exp(x[1] * self.t) - self.y

    def jac(self, x):
        e = np.exp(x[1] * self.t)
        return np.stack([e, x[0] * self.t * e], axis=1)

    def cost(self, x):
        r = self.residual(x)
        return 0.5 * r @ r

    def linearize(self, x):
        J, r = self.jac(x), self.residual(x)
        return WindowSystem.single(J.T @ J), J.T @ r, self.cost(x)


class Rosenbrock:
    """Newton-type problem with the exact (indefinite at the start) Hessian as H."""

    def cost(self, x):
        return 0.5 * ((1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2)

    def linearize(self, x):
        a, b = x
        gradient = np.array([-(1 - a) - 200 * a * (b - a * a), 100 * (b - a * a)])
        hessian = np.array([[1 - 200 * b + 600 * a * a, -200 * a], [-200 * a, 100.0]])
        return WindowSystem.single(hessian), gradient, self.cost(x)


def test_curve_fit_matches_scipy():
    problem = CurveFit()
    result = levenberg_marquardt(problem, np.array([1.0, 0.0]), TIGHT, CholeskySolver())
    reference = scipy.optimize.least_squares(problem.residual, [1.0, 0.0], jac=problem.jac, xtol=1e-15, ftol=1e-15,
                                             gtol=1e-15)
    assert result.converged
    np.testing.assert_allclose(result.x, reference.x, rtol=1e-9)
    assert result.final_cost == pytest.approx(0.5 * reference.fun @ reference.fun, rel=1e-12)
    assert np.all(np.diff(result.cost_history) <= 0.0)
    assert result.cost_history[0] == result.initial_cost and result.cost_history[-1] == result.final_cost


class OverestimatedCurvature:
    """F(x) = 0.5 (x - 3)^2 with a Hessian four times the true curvature, as Gauss-Newton's
    is where systematic residuals' second-order terms are dropped: undamped steps reach a
    quarter of the way to the minimum."""

    def cost(self, x):
        return 0.5 * float((x[0] - 3.0) ** 2)

    def linearize(self, x):
        return WindowSystem.single(np.array([[4.0]])), np.array([x[0] - 3.0]), self.cost(x)


def test_a_step_that_beats_its_model_is_extrapolated_and_reported():
    """From 0 the model's step is 0.75 and lowers F by 1.97 against the 1.13 predicted (gain
    1.75 > EXTRAPOLATION_GAIN): the parabola through F(0), the slope and F(0.75) puts the
    minimiser at 4 steps, the minimum itself (the damping leaves it a hair short of that, and
    the cap on the extrapolation at MAX_EXTRAPOLATION steps holds it there). Without the
    extrapolation each step closes a quarter of the gap: some 75 to reach 1e-9."""
    result = levenberg_marquardt(OverestimatedCurvature(), np.array([0.0]), TIGHT, CholeskySolver())
    assert result.extrapolated_steps >= 1
    assert result.x[0] == pytest.approx(3.0, abs=1e-9)
    assert result.iterations <= 5
    assert f"{result.extrapolated_steps} extrapolated" in result.summary()


@pytest.mark.parametrize("solver", [CholeskySolver(), PCGSolver(tolerance=1e-12)])
def test_indefinite_hessian_raises_damping_and_converges(solver):
    problem = Rosenbrock()
    start = np.array([0.0, 1.0])
    assert np.linalg.eigvalsh(problem.linearize(start)[0].to_csr().toarray()).min() < 0
    result = levenberg_marquardt(problem, start, LevenbergMarquardtConfig(max_iterations=500, cost_tolerance=1e-20),
                                 solver)
    np.testing.assert_allclose(result.x, [1.0, 1.0], atol=1e-6)
    assert result.not_positive_definite > 0
    assert any("not positive definite" in message for message in result.messages)


def test_steps_that_would_invert_tetrahedra_are_shortened_not_dropped():
    """A prior pulling a corner through the cube: every step is cut to the fraction that keeps
    each element at MIN_VOLUME_RATIO_PER_STEP of its volume, and LM still makes progress."""
    mesh = cube_mesh(side=0.1, divisions=1)
    elastic = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45)
    corner = int(np.argmax(mesh.vertices.sum(axis=1)))
    target = mesh.vertices.copy()
    target[corner] = [-0.05, -0.05, -0.05]  # through the cube: inverts its elements
    graph = FactorGraph(mesh.vertex_count, mesh.tetrahedra, mesh.surface_triangles)
    graph.add_state(0, mesh.vertices)
    fixed = np.arange(mesh.vertex_count) != corner
    graph.fixed_vertices = np.flatnonzero(fixed)
    scale = prior_scale(elastic.stiffness(), 1e-3)
    graph.add_factor(PhysicsPriorFactor(0, target, elastic, "linear", scale=scale, ridge=1.0))
    start_volumes = signed_volumes(mesh.vertices, graph.tetrahedra)
    result = levenberg_marquardt(graph, graph.get_x(), LevenbergMarquardtConfig(max_iterations=30), CholeskySolver())
    final = signed_volumes(graph.states_from_x(result.x)[0], graph.tetrahedra)
    assert result.shortened_steps > 0 and result.accepted_steps > 0
    assert np.all(final > 0.0)
    assert result.final_cost < 0.5 * result.initial_cost
    assert not result.converged or result.reason in ("gradient", "decrement", "cost", "step", "predicted decrease")
    assert np.all(final >= MIN_VOLUME_RATIO_PER_STEP ** result.accepted_steps * start_volumes * (1 - 1e-9))


def test_step_fraction_keeps_the_margin_exactly():
    """Each state's fraction is the largest that keeps every volume of that state at the margin:
    a little more breaks it."""
    mesh = cube_mesh(side=0.1, divisions=3)
    graph = FactorGraph(mesh.vertex_count, mesh.tetrahedra, mesh.surface_triangles)
    graph.add_state(0, mesh.vertices)
    graph.add_state(1, mesh.vertices * 1.01)
    x = graph.get_x()
    rng = np.random.default_rng(0)

    def volumes(x_):
        return np.stack([signed_volumes(state, graph.tetrahedra) for state in graph.states_from_x(x_).values()])

    before = volumes(x)
    for scale, full in ((1e-4, True), (1e-2, False), (3e-2, False)):
        step = rng.normal(scale=scale, size=x.shape)
        fractions = graph.step_fraction(x, step)
        per_state = fractions.reshape(len(graph.keys), -1)
        assert np.all(per_state == per_state[:, :1])  # one fraction per state
        assert bool(np.all(fractions == 1.0)) == full
        assert np.min(volumes(x + fractions * step) / before) >= MIN_VOLUME_RATIO_PER_STEP * (1 - 1e-9)
        for t in np.flatnonzero(per_state[:, 0] < 1.0):
            longer = per_state.copy()
            longer[t] *= 1.01
            assert np.min((volumes(x + longer.reshape(-1) * step) / before)[t]) < MIN_VOLUME_RATIO_PER_STEP


def test_a_state_that_cannot_move_does_not_hold_back_the_others():
    """State 0's prior pulls a corner through the cube, so every step of it is cut; state 1's
    prior asks for a 2 mm move that inverts nothing. Cut state by state, state 1 gets within 1 %
    of its optimum in 16 iterations; cut by the smallest fraction of the window, it has not made
    half of its move after as many."""
    mesh = cube_mesh(side=0.1, divisions=1)
    elastic = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45)
    corner = int(np.argmax(mesh.vertices.sum(axis=1)))
    through = mesh.vertices.copy()
    through[corner] = [-0.05, -0.05, -0.05]
    harmless = mesh.vertices.copy()
    harmless[corner] += 2e-3
    scale = prior_scale(elastic.stiffness(), 1e-3)

    class WholeWindowFraction:  # the same graph, every state cut by the window's smallest fraction
        def __init__(self, graph):
            self.graph, self.cost, self.linearize = graph, graph.cost, graph.linearize

        def step_fraction(self, x, step):
            return float(np.min(self.graph.step_fraction(x, step)))

    errors = {}
    for name in ("per state", "whole window"):
        graph = FactorGraph(mesh.vertex_count, mesh.tetrahedra, mesh.surface_triangles)
        graph.fixed_vertices = np.flatnonzero(np.arange(mesh.vertex_count) != corner)
        for key, target in ((0, through), (1, harmless)):
            graph.add_state(key, mesh.vertices)
            graph.add_factor(PhysicsPriorFactor(key, target, elastic, "linear", scale=scale, ridge=1.0))
        problem = graph if name == "per state" else WholeWindowFraction(graph)
        result = levenberg_marquardt(problem, graph.get_x(), LevenbergMarquardtConfig(max_iterations=16),
                                     CholeskySolver())
        states = graph.states_from_x(result.x)
        assert result.shortened_steps > 0 and np.all(signed_volumes(states[0], graph.tetrahedra) > 0.0)
        errors[name] = np.linalg.norm(states[1][corner] - harmless[corner])
    assert errors["per state"] < 0.01 * 2e-3 and errors["whole window"] > 0.5 * 2e-3


def test_converged_means_optimal_not_stuck():
    """A run whose every step is rejected ends unconverged ("damping limit" or "max_iterations"),
    never converged with final == initial cost."""

    class Hopeless(Rosenbrock):
        def cost(self, x):  # any move from the start looks worse
            return super().cost(x) + (0.0 if np.array_equal(x, [0.0, 1.0]) else 1e6)

    result = levenberg_marquardt(Hopeless(), np.array([0.0, 1.0]), LevenbergMarquardtConfig(max_iterations=40),
                                 CholeskySolver())
    assert result.accepted_steps == 0 and not result.converged
    assert result.reason in ("damping limit", "max_iterations")
    assert "0 of" in result.summary() and "not converged" in result.summary()


def test_a_run_that_starts_at_the_optimum_says_so():
    """Started at Rosenbrock's minimum, LM converges by its gradient test without a step, and
    its summary says the run converged where it started, not that it moved there."""
    result = levenberg_marquardt(Rosenbrock(), np.array([1.0, 1.0]), TIGHT, CholeskySolver())
    assert result.converged and result.iterations == 0 and result.accepted_steps == 0
    assert result.summary().startswith(f"converged ({result.reason}) at its starting point; 0 of 0 steps")
    moved = levenberg_marquardt(Rosenbrock(), np.array([0.5, 0.2]), TIGHT, CholeskySolver())
    assert moved.converged and "starting point" not in moved.summary()


def test_window_optimum_matches_scipy_and_gtsam(cube, model):  # noqa: F811
    graph = build_window(cube, model, keys=2)
    results = compare_single_update(graph, tolerance=1e-14)
    ours = results["meshfg"]
    for name in ("scipy", "gtsam"):
        other = results[name]
        assert other.cost == pytest.approx(ours.cost, rel=1e-6), name
        assert np.abs(other.x - ours.x).max() < 1e-6, name
    assert ours.cost < graph.cost(graph.get_x())


def window_system(cube, model, damping=1e-3):  # noqa: F811
    graph = build_window(cube, model)
    system, gradient, _ = graph.linearize(graph.get_x())
    return system.with_added_diagonal(damping * system.diagonal()), -gradient


def test_added_diagonal_is_a_shift_shared_by_every_view(cube, model):  # noqa: F811
    """with_added_diagonal keeps the blocks and adds the damping in matvec, diagonal, to_csr,
    block_data and the materialised blocks alike (to rounding: the temporal terms are a shift
    too, summed in another order); the undamped system is left alone."""
    graph = build_window(cube, model)
    system, _, _ = graph.linearize(graph.get_x())
    undamped_diagonal = system.diagonal().copy()
    shift = np.random.default_rng(3).uniform(1.0, 2.0, size=system.size)
    damped = system.with_added_diagonal(shift).with_added_diagonal(shift)
    expected = system.to_csr() + scipy.sparse.diags(2.0 * shift)
    scale = abs(expected).max()
    assert abs(damped.to_csr() - expected).max() <= 1e-15 * scale
    x = np.random.default_rng(4).normal(size=system.size)
    np.testing.assert_allclose(damped.matvec(x), expected @ x, rtol=1e-13, atol=0.0)
    np.testing.assert_allclose(damped.diagonal(), expected.diagonal(), rtol=0.0, atol=1e-15 * scale)
    n = system.block_size
    for t in range(len(system.keys)):
        np.testing.assert_allclose(damped.blocks[t].toarray(), expected[t * n:(t + 1) * n, t * n:(t + 1) * n].toarray(),
                                   rtol=0.0, atol=1e-15 * scale)
    np.testing.assert_array_equal(system.diagonal(), undamped_diagonal)


def test_linear_solvers_agree(cube, model):  # noqa: F811
    system, rhs = window_system(cube, model)
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    solvers = [CholeskySolver(), SuperLUSolver()] + [
        PCGSolver(tolerance=1e-12, preconditioner=mode) for mode in ("block", "vertex", "auto")
    ]
    for solver in solvers:
        x, stats = solver.solve(system, rhs)
        np.testing.assert_allclose(x, reference, rtol=1e-8, atol=1e-10 * np.abs(reference).max())
        assert stats.time_ms >= 0.0
    pcg = PCGSolver(tolerance=1e-12, preconditioner="block")
    _, first = pcg.solve(system, rhs)
    _, second = pcg.solve(system, rhs)
    assert first.factorizations == 3 and second.factorizations == 0  # block factors are reused


def test_block_factors_are_refreshed_by_revision_and_drift(cube, model):  # noqa: F811
    """A damping-sized diagonal change keeps every cached factor; a block re-linearised (new
    revision) that drifted beyond refresh_change is factored again, and only that block."""
    system, rhs = window_system(cube, model)
    pcg = PCGSolver(tolerance=1e-10, preconditioner="block")
    assert pcg.solve(system, rhs)[1].factorizations == len(system.blocks)
    damped = system.with_added_diagonal(1e-4 * system.diagonal())
    assert pcg.solve(damped, rhs)[1].factorizations == 0
    blocks = list(system.blocks)
    blocks[0] = blocks[0] + scipy.sparse.diags(blocks[0].diagonal())  # not a multiple of the block
    relinearized = WindowSystem(blocks, system.couplings, system.keys, system.diagonal_index,
                                system.coupling_diagonal, revisions=["new"] + system.revisions[1:])
    x, stats = pcg.solve(relinearized, rhs)
    assert stats.factorizations == 1
    np.testing.assert_allclose(relinearized.matvec(x), rhs, rtol=1e-8, atol=1e-8 * np.abs(rhs).max())


def test_a_scaled_block_keeps_its_factor_and_is_solved_through_it(cube, model):  # noqa: F811
    """A window that is a multiple c of the one its factors were made from (a new noise
    estimate weighs whole blocks) keeps the factors, which serve it divided by c: PCG takes
    the iterations it took on the unscaled window, and the decrement of one state's block,
    exact through its own factor, stays exact."""
    system, rhs = window_system(cube, model)
    newest = np.array([len(system.keys) - 1])
    single, part = system.restricted(newest), system.split(rhs)[-1]
    pcg, one_state = PCGSolver(tolerance=1e-10, preconditioner="block"), PCGSolver(preconditioner="block")
    _, first = pcg.solve(system, rhs)
    exact = 0.5 * float(part @ scipy.sparse.linalg.spsolve(single.to_csr().tocsc(), part))
    assert one_state.decrement(single, part) == pytest.approx(exact, rel=1e-9)
    for scale in (4.0, 0.01):
        scaled = WindowSystem([block * scale for block in system.blocks], system.couplings * scale, system.keys,
                              system.diagonal_index, system.coupling_diagonal * scale,
                              revisions=[f"scaled {scale}"] * len(system.keys))
        x, stats = pcg.solve(scaled, rhs)
        assert stats.factorizations == 0 and stats.iterations == first.iterations
        np.testing.assert_allclose(scaled.matvec(x), rhs, rtol=1e-8, atol=1e-8 * np.abs(rhs).max())
        assert one_state.decrement(scaled.restricted(newest), part) == pytest.approx(exact / scale, rel=1e-9)
    assert one_state.factorizations == 1
    # Each block its own multiple: the preconditioner is each scaled block's exact inverse.
    scales = np.array([4.0, 0.5, 2.0])[:len(system.keys)]
    mixed = WindowSystem([block * c for block, c in zip(system.blocks, scales)], system.couplings, system.keys,
                         system.diagonal_index, revisions=["mixed"] * len(system.keys))
    x, stats = pcg.solve(mixed, rhs)
    assert stats.factorizations == 0
    np.testing.assert_allclose(mixed.matvec(x), rhs, rtol=1e-8, atol=1e-8 * np.abs(rhs).max())
    residual = np.random.default_rng(7).normal(size=mixed.size)
    applied = mixed.split(pcg._precondition(mixed, "block", residual))
    for t, block in enumerate(mixed.blocks):
        expected = scipy.sparse.linalg.spsolve(block.tocsc(), mixed.split(residual)[t])
        np.testing.assert_allclose(applied[t], expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("reserved", [0, 3])
def test_reserved_factors_serve_the_first_solves_without_analysis(cube, model, monkeypatch, reserved):  # noqa: F811
    """`reserve(pattern, W)` makes W factors before any solve, so the blocks of a window need
    no symbolic analysis (nor fresh memory); without, each block's factor is analysed."""
    system, rhs = window_system(cube, model)
    pcg = PCGSolver(tolerance=1e-12, preconditioner="block")
    pcg.reserve(system.pattern, reserved)
    analyses = []
    original = sparse_cholesky.SparseCholesky._analyse
    monkeypatch.setattr(sparse_cholesky.SparseCholesky, "_analyse",
                        lambda factor, data: analyses.append(1) or original(factor, data))
    x, stats = pcg.solve(system, rhs)
    assert stats.factorizations == len(system.keys)
    assert len(analyses) == (0 if reserved else len(system.keys))
    np.testing.assert_allclose(system.matvec(x), rhs, rtol=1e-8, atol=1e-9 * np.abs(rhs).max())


def test_no_factor_is_reserved_for_blocks_the_vertex_preconditioner_serves(cube, model, monkeypatch):  # noqa: F811
    system, _ = window_system(cube, model)
    analyses = []
    monkeypatch.setattr(sparse_cholesky.SparseCholesky, "_analyse", lambda factor, data: analyses.append(1))
    PCGSolver(preconditioner="block").reserve(system.pattern, 2)
    assert len(analyses) == 2
    for pcg in (PCGSolver(preconditioner="vertex"), PCGSolver(cholesky_max_block=system.block_size - 1)):
        pcg.reserve(system.pattern, 3)
    assert len(analyses) == 2


def test_stale_factors_are_refreshed_and_pcg_resumes_from_its_iterate(cube, model):  # noqa: F811
    """Factors kept from a different system (within refresh_change, under a new revision) fail
    to converge in refresh_iterations; PCG refactors every block and resumes from where it
    stopped, reaching the exact solution."""
    system, rhs = window_system(cube, model)
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    pcg = PCGSolver(tolerance=1e-12, preconditioner="block", refresh_iterations=1, refresh_change=1.0)
    shifted = system.with_added_diagonal(0.5 * system.diagonal())  # factors of a 1.5x diagonal
    pcg.solve(shifted, rhs)
    x, stats = pcg.solve(system, rhs)
    assert stats.factorizations == len(system.blocks)
    assert stats.iterations > 1  # the one stale iteration, then the refreshed ones
    np.testing.assert_allclose(x, reference, rtol=1e-8, atol=1e-10 * np.abs(reference).max())


def test_a_state_that_joins_the_window_borrows_the_newest_factor(cube, model):  # noqa: F811
    """The newest state of a sliding window starts with the factor of the state before it (one
    factorisation less per update); with a block close to its predecessor's, as consecutive
    states of a sequence have (here 2 % more on the diagonal; couplings as weak as the
    estimator's), PCG meets the tolerance with it (6 iterations against 3 with a factor of its
    own, measured). The lender's factor is not handed out as a spare while the newcomer still
    uses it after the lender left."""
    system, rhs = window_system(cube, model)
    blocks = list(system.blocks)
    blocks[2] = blocks[1] + scipy.sparse.diags(0.02 * blocks[1].diagonal())
    system = WindowSystem(blocks, 3e-3 * system.couplings, system.keys, system.diagonal_index)
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    pcg = PCGSolver(tolerance=1e-8, preconditioner="block")
    earlier = system.restricted([0, 1])
    assert pcg.solve(earlier, system.split(rhs)[:2].reshape(-1))[1].factorizations == 2
    x, stats = pcg.solve(system, rhs)
    assert stats.factorizations == 0 and stats.iterations <= BORROWED_ITERATIONS
    np.testing.assert_allclose(x, reference, rtol=1e-6, atol=1e-7 * np.abs(reference).max())
    newest, lender = (pcg._block_factors[system.keys[t]] for t in (2, 1))
    assert newest.borrowed and newest.factor is lender.factor
    later = system.restricted([2])
    pcg.solve(later, system.split(rhs)[2])  # states 0 and 1 left the window
    assert all(spare is not newest.factor for spare in pcg._spare) and len(pcg._spare) == 1


def _drifted_borrower(cube, model, spares: bool = True):  # noqa: F811
    """A PCGSolver whose newest state borrows a factor its block has drifted from (2 % more on
    the diagonal), after the solve that found it: (solver, system, right-hand side, that solve's
    SolveStats); `spares`: the window's factors reserved, with one more."""
    system, rhs = window_system(cube, model)
    blocks = list(system.blocks)
    blocks[2] = blocks[1] + scipy.sparse.diags(0.02 * blocks[1].diagonal())
    system = WindowSystem(blocks, 3e-3 * system.couplings, system.keys, system.diagonal_index)
    pcg = PCGSolver(tolerance=1e-8, preconditioner="block")
    if spares:
        pcg.reserve(system.pattern, len(system.keys) + 1)
    pcg.solve(system.restricted([0, 1]), system.split(rhs)[:2].reshape(-1))
    _, borrowed = pcg.solve(system, rhs)
    return pcg, system, rhs, borrowed


def test_a_drifted_borrowed_factor_is_replaced_by_one_made_beside_the_caller(cube, model, monkeypatch):  # noqa: F811
    """A joining state borrows a factor its block has drifted from (BESIDE_ITERATIONS or more PCG
    iterations, within BORROWED_ITERATIONS). `refactor_newest_beside` then makes a factor of the
    newest block of the last solve beside the caller; the next solve puts it in place of the
    borrowed one without a factorisation of its own, needs fewer iterations with it, and lends
    it to the next state that joins. A solve that needed fewer iterations starts none, nor does
    one without a spare factor. One worker thread or two, the same solutions."""
    solutions = []
    for threads in ("1", "2"):
        monkeypatch.setenv("MESHFG_WORKER_THREADS", threads)
        pcg, system, rhs, borrowed = _drifted_borrower(cube, model)
        assert BESIDE_ITERATIONS <= borrowed.iterations <= BORROWED_ITERATIONS and borrowed.factorizations == 0
        lent = pcg.state_factor(system.keys[1])
        assert pcg.state_factor(system.keys[2]) is lent
        fresh = pcg.refactor_newest_beside()
        assert fresh is not None and fresh is not lent and pcg.factorizations == 3
        x, stats = pcg.solve(system, rhs)
        assert stats.factorizations == 0 and stats.iterations < borrowed.iterations
        assert pcg.state_factor(system.keys[2]) is fresh and pcg.state_factor(system.keys[1]) is lent
        reference = np.linalg.solve(system.to_csr().toarray(), rhs)
        np.testing.assert_allclose(x, reference, rtol=1e-6, atol=1e-7 * np.abs(reference).max())
        solutions.append(x)
        assert pcg.refactor_newest_beside() is None  # its solve needed fewer iterations
        blocks = system.blocks
        joined = WindowSystem([*blocks[1:], blocks[2]], system.couplings, [*system.keys[1:], system.keys[2] + 1],
                              system.diagonal_index)
        pcg.solve(joined, np.concatenate([system.split(rhs)[1:], system.split(rhs)[2:]]).reshape(-1))
        assert pcg.state_factor(joined.keys[-1]) is fresh
    np.testing.assert_array_equal(solutions[0], solutions[1])
    pcg, _, _, borrowed = _drifted_borrower(cube, model, spares=False)  # no spare factor: nothing started
    assert borrowed.iterations >= BESIDE_ITERATIONS and pcg.refactor_newest_beside() is None


def test_a_factor_that_fails_beside_the_caller_goes_back_to_the_spares(cube, model, monkeypatch):  # noqa: F811
    """A factorisation beside the caller that runs out of memory (or meets a non-positive pivot)
    leaves the newest state with the factor it borrowed and its spare reusable; the solve goes on."""
    pcg, system, rhs, _ = _drifted_borrower(cube, model)
    lent = pcg.state_factor(system.keys[2])
    spares = len(pcg._spare)

    def fails(factor, data):
        failed = Future()
        failed.set_exception(MemoryError("CHOLMOD's factorisation failed"))
        return failed

    monkeypatch.setattr(sparse_cholesky.SparseCholesky, "refactor_beside", fails)
    fresh = pcg.refactor_newest_beside()
    assert fresh is not None and len(pcg._spare) == spares - 1
    x, stats = pcg.solve(system, rhs)
    assert pcg.state_factor(system.keys[2]) is lent and len(pcg._spare) == spares and fresh in pcg._spare
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    np.testing.assert_allclose(x, reference, rtol=1e-6, atol=1e-7 * np.abs(reference).max())


def test_the_next_covariance_draws_queue_behind_the_factor_made_beside(cube, model, monkeypatch):  # noqa: F811
    """The draws prepared through the factor `refactor_newest_beside` returns (as the estimator
    prepares the next update's) are made once, on the background thread after its factorisation,
    and the marginals of the next state's block through that factor use them: the numbers of
    draws made on the caller's thread through the same factor."""
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "2")
    monkeypatch.setattr(covariance, "DENSE_MAX_DOFS", 0)  # draws for the cube's small blocks too
    pcg, system, rhs, _ = _drifted_borrower(cube, model)
    drawn = []
    original = MarginalCovariance._draw_through
    def draw_through(marginals, factor, seed):
        drawn.append(threading.get_ident())
        return original(marginals, factor, seed)

    monkeypatch.setattr(MarginalCovariance, "_draw_through", draw_through)
    marginals = MarginalCovariance(samples=4)
    fresh = pcg.refactor_newest_beside()
    marginals.prepare(fresh, seed=3)
    pcg.solve(system, rhs)
    block = system.blocks[2]
    prepared = marginals.blocks(block, seed=3, factor=pcg.state_factor(system.keys[2]))
    assert len(drawn) == 1 and drawn[0] != threading.get_ident()
    np.testing.assert_allclose(prepared, MarginalCovariance(samples=4).blocks(block, seed=3, factor=fresh),
                               rtol=1e-12, atol=1e-14 * np.abs(prepared).max())
    assert len(drawn) == 2 and drawn[1] == threading.get_ident()


def test_the_solves_of_states_with_factors_of_their_own_run_side_by_side(cube, model, monkeypatch):  # noqa: F811
    """Blocks with factors of their own are preconditioned by one CHOLMOD call per factor, the
    calls split over the worker threads (from PARALLEL_MIN_SIZE rows, here lowered to the cube's
    blocks): two threads take part, and PCG gives the solution the calls in turn give."""
    system, rhs = window_system(cube, model)
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    threads = []
    original = sparse_cholesky.SparseCholesky.solve
    def solve(factor, b, split=True):
        threads.append(threading.get_ident())
        return original(factor, b, split)

    monkeypatch.setattr(sparse_cholesky.SparseCholesky, "solve", solve)
    monkeypatch.setenv("MESHFG_WORKER_THREADS", "2")
    solutions = []
    for smallest in (system.block_size + 1, 0):
        monkeypatch.setattr(linear_solvers, "PARALLEL_MIN_SIZE", smallest)
        threads.clear()
        x, stats = PCGSolver(tolerance=1e-12, preconditioner="block").solve(system, rhs)
        assert stats.factorizations == len(system.keys) and stats.iterations > 1
        solutions.append(x)
        assert len(set(threads)) == (1 if smallest else 2)
    np.testing.assert_allclose(solutions[1], reference, rtol=1e-8, atol=1e-10 * np.abs(reference).max())
    np.testing.assert_array_equal(solutions[1], solutions[0])  # one call per factor either way


def test_a_borrowed_factor_that_does_not_fit_is_replaced_by_the_states_own(cube, model):  # noqa: F811
    """A joining state whose block is far from the lender's (here 50 times its damping) makes PCG
    miss the tolerance within BORROWED_ITERATIONS; that state alone gets its own factor and PCG
    goes on from its iterate to the exact solution."""
    system, rhs = window_system(cube, model)
    blocks = list(system.blocks)
    blocks[2] = blocks[2] + scipy.sparse.diags(50.0 * np.abs(blocks[2].diagonal()))
    system = WindowSystem(blocks, 3e-3 * system.couplings, system.keys, system.diagonal_index)
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    pcg = PCGSolver(tolerance=1e-12, preconditioner="block")
    earlier = system.restricted([0, 1])
    pcg.solve(earlier, system.split(rhs)[:2].reshape(-1))
    lent = pcg._block_factors[system.keys[1]].factor
    x, stats = pcg.solve(system, rhs)
    assert stats.factorizations == 1 and stats.iterations > BORROWED_ITERATIONS
    assert pcg._block_factors[system.keys[1]].factor is lent and not pcg._block_factors[system.keys[2]].borrowed
    np.testing.assert_allclose(x, reference, rtol=1e-8, atol=1e-10 * np.abs(reference).max())


def _solved_blocks(monkeypatch):
    """Counts of the block factors' solves (one per block per preconditioner application)."""
    solves = []
    original = sparse_cholesky.SparseCholesky.solve
    monkeypatch.setattr(sparse_cholesky.SparseCholesky, "solve",
                        lambda factor, rhs: solves.append(1) or original(factor, rhs))
    return solves


def test_blocks_with_a_negligible_part_of_the_right_hand_side_are_left_out_of_a_solve(cube, model, monkeypatch):  # noqa: F811
    """A right-hand side that lives in the newest state (the others' parts 1e-6 of it: states
    earlier updates converged) and couplings as weak as the estimator's (1e-4 of the blocks'
    diagonal): PCG solves the newest block alone, its step elsewhere is zero, and the whole
    residual still meets the tolerance; the decrement matches the one over every block."""
    damped, rhs = window_system(cube, model)
    system = WindowSystem(damped.blocks, 3e-3 * damped.couplings, damped.keys, damped.diagonal_index)
    rhs = rhs.copy()
    parts = system.split(rhs)
    parts[:-1] *= 1e-6 * np.linalg.norm(parts[-1]) / np.linalg.norm(parts[:-1])
    every_block = PCGSolver(tolerance=1e-12, preconditioner="block").decrement(system, -rhs)  # nothing left out
    solves = _solved_blocks(monkeypatch)
    pcg = PCGSolver(tolerance=1e-3, preconditioner="block")
    decrement = pcg.decrement(system, -rhs)
    assert len(solves) == 1
    assert decrement == pytest.approx(every_block, rel=1e-9)
    x, stats = pcg.solve(system, rhs)
    assert stats.factorizations == 0 and len(solves) == stats.iterations  # the first M^-1 b is the decrement's
    assert not system.split(x)[:-1].any()
    assert np.linalg.norm(rhs - system.matvec(x)) <= 1e-3 * np.linalg.norm(rhs)


def test_the_vertex_preconditioner_leaves_out_blocks_alike(cube, model):  # noqa: F811
    """The factorisation-free preconditioner (large states) solves the kept blocks' restricted
    system (its own time Laplacian) and meets the tolerance over the whole window."""
    damped, rhs = window_system(cube, model)
    system = WindowSystem(damped.blocks, 3e-3 * damped.couplings, damped.keys, damped.diagonal_index)
    rhs = rhs.copy()
    system.split(rhs)[:-1] *= 1e-6 * np.linalg.norm(system.split(rhs)[-1]) / np.linalg.norm(system.split(rhs)[:-1])
    x, _ = PCGSolver(tolerance=1e-3, preconditioner="vertex").solve(system, rhs)
    assert not system.split(x)[:-1].any()
    assert np.linalg.norm(rhs - system.matvec(x)) <= 1e-3 * np.linalg.norm(rhs)


def test_a_left_out_block_that_the_couplings_pull_is_solved_after_all(cube, model):  # noqa: F811
    """When the kept block's step, through couplings stronger than the estimator's (3.5 % of the
    diagonal), leaves the left-out rows a residual above the tolerance, PCG goes on over every
    block from there and meets it."""
    system, rhs = window_system(cube, model)
    rhs = rhs.copy()
    system.split(rhs)[:-1] = 0.0
    x, stats = PCGSolver(tolerance=1e-6, preconditioner="block").solve(system, rhs)
    assert stats.factorizations == len(system.keys)
    assert system.split(x)[:-1].any()
    assert np.linalg.norm(rhs - system.matvec(x)) <= 1e-6 * np.linalg.norm(rhs)


def test_newton_decrement_estimates(cube, model):  # noqa: F811
    """decrement = 0.5 g^T A^-1 g: exact for direct solvers, and for PCG on one block (its
    preconditioner is that block's Cholesky factor); on a window PCG's block-Jacobi estimate
    ignores only the weak temporal coupling."""
    system, rhs = window_system(cube, model)
    exact = 0.5 * float(rhs @ np.linalg.solve(system.to_csr().toarray(), rhs))
    assert CholeskySolver().decrement(system, rhs) == pytest.approx(exact, rel=1e-10)
    estimate = PCGSolver(preconditioner="block").decrement(system, rhs)
    assert estimate == pytest.approx(exact, rel=0.05)
    single = WindowSystem.single(system.blocks[0])
    block_rhs = rhs[:system.block_size]
    single_exact = 0.5 * float(block_rhs @ np.linalg.solve(system.blocks[0].toarray(), block_rhs))
    assert PCGSolver(preconditioner="block").decrement(single, block_rhs) == pytest.approx(single_exact, rel=1e-10)


def test_step_after_the_decrement_reuses_its_preconditioned_gradient(cube, model, monkeypatch):  # noqa: F811
    """The solve for -g on the system the decrement saw starts from the decrement's M^-1 g
    (one preconditioner application fewer) and gives the very same bits as a solver that
    never estimated the decrement; another system, right-hand side or preconditioner does not."""
    system, rhs = window_system(cube, model)
    gradient = -rhs
    reference, _ = PCGSolver(tolerance=1e-3, preconditioner="block").solve(system, -gradient)
    pcg = PCGSolver(tolerance=1e-3, preconditioner="block")
    applications = []
    original = PCGSolver._precondition
    monkeypatch.setattr(PCGSolver, "_precondition",
                        lambda solver, *args: applications.append(1) or original(solver, *args))
    pcg.decrement(system, gradient)
    before = len(applications)
    step, stats = pcg.solve(system, -gradient)
    np.testing.assert_allclose(step, reference, rtol=1e-12, atol=0.0)
    assert len(applications) - before == stats.iterations - 1
    pcg.decrement(system, gradient)
    before = len(applications)
    _, stats = pcg.solve(system, -2.0 * gradient)  # another right-hand side: no reuse
    assert len(applications) - before == stats.iterations
    pcg.decrement(system, gradient)
    before = len(applications)
    _, stats = pcg.solve(system.with_added_diagonal(system.diagonal()), -gradient)  # another system
    assert len(applications) - before == stats.iterations
    pcg.decrement(system, gradient)
    pcg._prepare(system, "block", force=True)  # new factors: another preconditioner
    before = len(applications)
    step, stats = pcg.solve(system, -gradient)
    assert len(applications) - before == stats.iterations
    np.testing.assert_allclose(step, reference, rtol=1e-12, atol=0.0)


class CountingProblem:
    """A FactorGraph seen through LM's problem interface, counting calls; `with_gradient`
    False hides FactorGraph.gradient (LM then re-linearises after every accepted step)."""

    def __init__(self, graph, with_gradient: bool):
        self.graph, self.calls = graph, {"linearize": 0, "gradient": 0}
        self.cost, self.step_fraction = graph.cost, graph.step_fraction
        if with_gradient:
            self.gradient = self._gradient

    def linearize(self, x):
        self.calls["linearize"] += 1
        return self.graph.linearize(x)

    def _gradient(self, x):
        self.calls["gradient"] += 1
        return self.graph.gradient(x)


def test_converged_runs_skip_the_last_hessians(cube, model):  # noqa: F811
    """After a step whose model error is below the cost tolerance, LM tests convergence with
    the new gradient and the kept Hessians: same optimum, fewer linearisations."""
    config = LevenbergMarquardtConfig(cost_tolerance=1e-2)  # converges after one step here
    runs = {}
    for with_gradient in (True, False):
        graph = build_window(cube, model, threshold=1e-3)
        graph.exact_keys = {2}
        problem = CountingProblem(graph, with_gradient)
        runs[with_gradient] = (levenberg_marquardt(problem, graph.get_x(), config, PCGSolver(tolerance=1e-3)),
                               problem.calls)
    (fast, fast_calls), (plain, plain_calls) = runs[True], runs[False]
    assert fast.converged and plain.converged and fast.reason == plain.reason == "decrement"
    assert fast_calls == {"linearize": 1, "gradient": 1} and plain_calls == {"linearize": 2, "gradient": 0}
    assert fast.final_cost == pytest.approx(plain.final_cost, rel=1e-12)
    np.testing.assert_array_equal(fast.x, plain.x)


def test_indefinite_systems_are_reported():
    matrix = scipy.sparse.csr_matrix(np.array([[2.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]))
    system = WindowSystem.single(matrix)
    rhs = np.array([1.0, 1.0, 1.0])
    with pytest.raises(NotPositiveDefiniteError):
        CholeskySolver().solve(system, rhs)
    with pytest.raises(NotPositiveDefiniteError):
        PCGSolver(preconditioner="vertex").solve(system, rhs)
    x, _ = SuperLUSolver().solve(system, rhs)
    np.testing.assert_allclose(x, [0.5, -1.0, 1.0])


def test_fallback_solver_says_what_failed(cube, model):  # noqa: F811
    system, rhs = window_system(cube, model)
    solver = FallbackSolver([PCGSolver(tolerance=1e-14, max_iterations=1, preconditioner="vertex"), CholeskySolver()])
    x, stats = solver.solve(system, rhs)
    assert "pcg failed" in stats.message and "solved with cholesky" in stats.message
    np.testing.assert_allclose(system.matvec(x), rhs, rtol=1e-8, atol=1e-8 * np.abs(rhs).max())
    with pytest.raises(LinearSolveError):
        FallbackSolver([PCGSolver(tolerance=1e-14, max_iterations=1, preconditioner="vertex")]).solve(system, rhs)
    with pytest.raises(ValueError):
        make_linear_solver("qr")


def test_estimator_window_problem_matches_scipy():
    from meshfg_ros.benchmarks.baselines import pending_window, synthetic_sequence
    from meshfg_ros.core.estimation.estimator import EstimatorConfig

    mesh, sequence = synthetic_sequence(target_vertices=64, points_per_step=200, steps=4, noise_sigma=5e-4,
                                        prediction_error=2e-3, seed=2)
    _, graph = pending_window(mesh, sequence, EstimatorConfig(window_size=3, measurement_sigma=5e-4, robust_kernel=None))
    assert len(graph.keys) == 3
    start_cost = graph.cost(graph.get_x())
    results = compare_single_update(graph, solvers=("meshfg", "scipy"), tolerance=1e-13)
    assert results["meshfg"].cost < 0.9 * start_cost
    assert results["scipy"].cost == pytest.approx(results["meshfg"].cost, rel=1e-6)
    assert np.abs(results["scipy"].x - results["meshfg"].x).max() < 1e-6


@pytest.mark.parametrize("kept", [[0], [4], [0, 4], [1, 3], [0, 2, 4], [1, 2]])
def test_the_whole_windows_residual_of_a_partial_solve_needs_no_product_with_the_blocks(cube, model, kept):  # noqa: F811
    """b - A x for an x that is zero outside the kept blocks: the kept blocks' rows are their own
    system's residual, a left-out block's rows b minus its couplings to its neighbours' x (kept
    blocks at the window's ends, apart, and side by side)."""
    from meshfg_ros.core.solvers.linear_solvers import _whole_residual

    graph = build_window(cube, model, keys=5)
    system, gradient, _ = graph.linearize(graph.get_x())
    rhs = -gradient
    kept = np.array(kept)
    x = np.zeros_like(rhs)
    system.split(x)[kept] = np.random.default_rng(0).standard_normal((len(kept), system.block_size))
    kept_residual = system.split(rhs)[kept].reshape(-1) - system.restricted(kept).matvec(system.split(x)[kept].reshape(-1))
    expected = rhs - system.matvec(x)
    assert np.allclose(_whole_residual(system, rhs, x, kept, kept_residual), expected,
                       rtol=0.0, atol=1e-12 * np.abs(expected).max())


def test_a_miss_with_borrowed_factors_gives_the_newest_borrower_alone_a_factor_of_its_own(cube, model):  # noqa: F811
    """Two joining states borrow one factor in turn; the newest block is far from it (50 times
    its damping), the other close (2 % more on the diagonal). PCG misses with the borrowed
    factors: one factorisation, the newest state's, and PCG goes on to the solution; the other
    state keeps borrowing."""
    system, rhs = window_system(cube, model)
    blocks = list(system.blocks)
    blocks[1] = blocks[0] + scipy.sparse.diags(0.02 * blocks[0].diagonal())
    blocks[2] = blocks[2] + scipy.sparse.diags(50.0 * np.abs(blocks[2].diagonal()))
    system = WindowSystem(blocks, 3e-3 * system.couplings, system.keys, system.diagonal_index)
    reference = np.linalg.solve(system.to_csr().toarray(), rhs)
    pcg = PCGSolver(tolerance=1e-12, preconditioner="block")
    pcg.solve(system.restricted([0]), system.split(rhs)[0])
    pcg.solve(system.restricted([0, 1]), system.split(rhs)[:2].reshape(-1))
    assert pcg._block_factors[system.keys[1]].borrowed
    x, stats = pcg.solve(system, rhs)
    assert stats.factorizations == 1 and stats.iterations > BORROWED_ITERATIONS
    assert pcg._block_factors[system.keys[1]].borrowed and not pcg._block_factors[system.keys[2]].borrowed
    np.testing.assert_allclose(x, reference, rtol=1e-8, atol=1e-10 * np.abs(reference).max())
