"""Reference solvers of the same window problem (scipy, GTSAM) and the estimator benchmark.

`WhitenedProblem` turns a `FactorGraph` into the whitened residual vector e(x) (cost
0.5 |e|^2) and its sparse Jacobian over the free vertex coordinates, as general least-squares
solvers want it:
  physics prior   sqrt(scale) R_e (xhat_e - x_e) per element, R_e^T R_e = K_e (symmetric
                  square root of the element stiffness, so sum_e = scale K), and
                  sqrt(ridge) (xhat - x); needs PSD element matrices (linear, corotational or
                  projected); the information is the one the factor holds (fixed per update).
  measurements    sqrt(w_k) (q_k - m_k) on the frozen closest triangle (no robust kernel).
  temporal        (X_t - X_prev) / sigma.
`solve_scipy` runs scipy.optimize.least_squares on it and `solve_gtsam` builds the same
problem in GTSAM (a Point3 per free vertex and state, gtsam.CustomFactor for elements and
points, BetweenFactorPoint3 / PriorFactorPoint3 for time and ridge) and runs its
LevenbergMarquardtOptimizer. Both are cross-checks and latency baselines, not estimator paths.

`synthetic_sequence` makes a deforming box with a partial-view point cloud per step and an
imperfect prediction, and `benchmark_update` times the estimator node's step loop on it
(median / p95 latency, LM iterations, time of one linear solve) for `meshfg bench`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.sparse

from meshfg_ros.core.geometry.closest_point import REGION_FACE, project_onto_triangles, projection_jacobian
from meshfg_ros.core.estimation.factor_graph import FactorGraph
from meshfg_ros.core.estimation.factors import PhysicsPriorFactor, PointToSurfaceFactor, TemporalFactor, VolumeBarrierFactor
from meshfg_ros.core.solvers.levenberg_marquardt import LevenbergMarquardtConfig, levenberg_marquardt
from meshfg_ros.core.solvers.linear_solvers import make_linear_solver
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.synthetic.meshing import box_mesh
from meshfg_ros.evaluation.metrics import sample_surface

__all__ = [
    "BaselineError",
    "BaselineResult",
    "BenchmarkStep",
    "WhitenedProblem",
    "benchmark_update",
    "compare_single_update",
    "freeze_associations",
    "pending_window",
    "solve_gtsam",
    "solve_meshfg",
    "solve_scipy",
    "synthetic_sequence",
]


class BaselineError(ValueError):
    """A graph that the reference solvers cannot express (indefinite prior, robust kernel...)."""


def freeze_associations(graph: FactorGraph) -> None:
    """Pin every point of every measurement factor to its closest triangle at the current states."""
    for factor in graph.factors:
        if isinstance(factor, PointToSurfaceFactor):
            factor.freeze_association(graph.states)


def _element_roots(factor: PhysicsPriorFactor) -> np.ndarray:
    """R_e (M, 12, 12) with R_e^T R_e = K_e at the state the factor's information is fixed at."""
    if factor.information_state is None:
        factor.information(factor.predicted)
    matrices = factor.model.element_matrices(factor.information_state, kind=factor.kind,
                                             spd_projection=factor.spd_projection)
    eigenvalues, eigenvectors = np.linalg.eigh(matrices)
    if np.any(eigenvalues < -1e-9 * np.abs(eigenvalues).max()):
        raise BaselineError("element stiffness matrices are indefinite: no square-root information")
    return np.sqrt(np.clip(eigenvalues, 0.0, None))[:, :, None] * eigenvectors.transpose(0, 2, 1)


class WhitenedProblem:
    """Whitened residuals e(x) and sparse Jacobian de/dx of a FactorGraph's factors (see module doc)."""

    def __init__(self, graph: FactorGraph):
        self.graph = graph
        self.position = {key: t for t, key in enumerate(graph.keys)}
        self.size = len(graph.keys) * graph.block_size
        self.column = np.full((len(graph.keys), graph.dof_count), -1, dtype=np.int64)
        for t in range(len(graph.keys)):
            self.column[t, graph.free_dofs] = t * graph.block_size + np.arange(graph.block_size)
        self.roots = {}
        for factor in graph.factors:
            if isinstance(factor, PointToSurfaceFactor):
                if factor.robust is not None:
                    raise BaselineError("robust kernels have no plain least-squares form here")
                if factor.frozen_triangles is None:
                    raise BaselineError("freeze the association first (freeze_associations)")
            elif isinstance(factor, PhysicsPriorFactor):
                self.roots[id(factor)] = _element_roots(factor)
            elif not isinstance(factor, (TemporalFactor, VolumeBarrierFactor)):
                raise BaselineError(f"unsupported factor {type(factor).__name__}")

    def _blocks(self, x: np.ndarray, with_jacobian: bool):
        """Residual pieces and Jacobian triplets (rows local to the piece, full-dof columns, key)."""
        states = self.graph.states_from_x(x)
        for factor in self.graph.factors:
            if isinstance(factor, PhysicsPriorFactor):
                key = factor.keys[0]
                tets = factor.model.tetrahedra
                element_dofs = (3 * tets[:, :, None] + np.arange(3)).reshape(-1, 12)
                difference = (factor.predicted - states[key]).reshape(-1)
                roots = np.sqrt(factor.scale) * self.roots[id(factor)]
                values = [np.einsum("eij,ej->ei", roots, difference[element_dofs]).reshape(-1)]
                jac = []
                if with_jacobian:
                    rows = np.broadcast_to(np.arange(roots.shape[0] * 12).reshape(-1, 12, 1), roots.shape)
                    cols = np.broadcast_to(element_dofs[:, None, :], roots.shape)
                    jac.append((rows.reshape(-1), cols.reshape(-1), -roots.reshape(-1), key))
                if factor.ridge:
                    offset = roots.shape[0] * 12
                    values.append(np.sqrt(factor.ridge) * difference)
                    if with_jacobian:
                        dofs = np.arange(difference.size)
                        jac.append((offset + dofs, dofs, np.full(dofs.size, -np.sqrt(factor.ridge)), key))
                yield np.concatenate(values), jac
            elif isinstance(factor, PointToSurfaceFactor):
                yield self._point_residuals(factor, states, with_jacobian)
            elif isinstance(factor, VolumeBarrierFactor):
                key = factor.keys[0]
                values = factor.residual(states)
                jac = []
                if with_jacobian:
                    matrix = factor.jacobians(states)[key].tocoo()
                    jac.append((matrix.row, matrix.col, matrix.data, key))
                yield values, jac
            else:
                root = 1.0 / factor.sigma
                values = root * factor.residual(states)
                jac = []
                if with_jacobian:
                    dofs = np.arange(values.size)
                    jac.append((dofs, dofs, np.full(dofs.size, root), factor.key))
                    if factor.previous_key is not None:
                        jac.append((dofs, dofs, np.full(dofs.size, -root), factor.previous_key))
                yield values, jac

    @staticmethod
    def _point_residuals(factor: PointToSurfaceFactor, states: dict, with_jacobian: bool):
        """Whitened residuals of the points on their frozen triangles: a point projected inside
        its face gives the signed distance n.(q - m) (one row, Jacobian beta_i n: the
        estimator's Gauss-Newton terms, see factors._distance_hessians), one on an
        edge or a vertex the vector q - m (three rows). Same cost either way."""
        key = factor.keys[0]
        triangles = factor.triangles[factor.frozen_triangles]
        corners = states[key][triangles]
        projection = project_onto_triangles(factor.points, corners[:, 0], corners[:, 1], corners[:, 2])
        root = np.sqrt(factor.weights)
        face = projection.region == REGION_FACE
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        difference = projection.closest - factor.points
        face_values = root[face] * np.einsum("ij,ij->i", difference[face], normals[face])
        other_values = (root[~face, None] * difference[~face]).reshape(-1)
        values = np.concatenate([face_values, other_values])
        jac = []
        if with_jacobian:
            columns = (3 * triangles[:, :, None] + np.arange(3)).reshape(-1, 9)
            face_rows = (projection.barycentric[face][:, :, None] * normals[face][:, None, :]).reshape(-1, 9)
            face_rows *= root[face][:, None]
            rows = np.broadcast_to(np.arange(face_rows.shape[0])[:, None], face_rows.shape)
            jac.append((rows.reshape(-1), columns[face].reshape(-1), face_rows.reshape(-1), key))
            other = ~face
            jacobian = root[other][:, None, None] * projection_jacobian(
                factor.points[other], corners[other, 0], corners[other, 1], corners[other, 2], projection.region[other])
            rows = face_values.size + np.broadcast_to(np.arange(other_values.size).reshape(-1, 3, 1), jacobian.shape)
            cols = np.broadcast_to(columns[other].reshape(-1, 1, 9), jacobian.shape)
            jac.append((rows.reshape(-1), cols.reshape(-1), jacobian.reshape(-1), key))
        return values, jac

    def residual(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([values for values, _ in self._blocks(x, False)])

    def jacobian(self, x: np.ndarray) -> scipy.sparse.csr_matrix:
        rows, cols, data, offset = [], [], [], 0
        for values, pieces in self._blocks(x, True):
            for piece_rows, piece_cols, piece_data, key in pieces:
                column = self.column[self.position[key], piece_cols]
                keep = column >= 0  # fixed vertices are not unknowns
                rows.append(offset + piece_rows[keep])
                cols.append(column[keep])
                data.append(piece_data[keep])
            offset += values.size
        return scipy.sparse.csr_matrix(
            (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(offset, self.size)
        )

    def cost(self, x: np.ndarray) -> float:
        residual = self.residual(x)
        return 0.5 * float(residual @ residual)


@dataclass
class BaselineResult:
    """A solver's optimum: x (free dofs), final cost, iterations and wall time."""

    x: np.ndarray
    cost: float
    iterations: int
    time_ms: float


def solve_meshfg(graph: FactorGraph, x0=None, config: LevenbergMarquardtConfig | None = None,
                 solver: str = "pcg", **solver_options) -> BaselineResult:
    """This package's Levenberg-Marquardt on the graph. Its linear solver reserves the window's
    block factors before the clock starts, as the estimator's does at its construction: the
    numeric factorisations are timed, the pattern's analysis (once per mesh) is not."""
    x0 = graph.get_x() if x0 is None else x0
    linear_solver = make_linear_solver(solver, **solver_options)
    linear_solver.reserve(graph.block_pattern, len(graph.keys))
    start = time.perf_counter()
    result = levenberg_marquardt(graph, x0, config, linear_solver)
    return BaselineResult(result.x, result.final_cost, result.iterations, 1e3 * (time.perf_counter() - start))


def solve_scipy(graph: FactorGraph, x0=None, tolerance: float = 1e-12, tr_solver: str = "lsmr") -> BaselineResult:
    """scipy.optimize.least_squares (trust-region reflective) on the whitened residuals."""
    problem = WhitenedProblem(graph)
    x0 = graph.get_x() if x0 is None else x0
    start = time.perf_counter()
    result = scipy.optimize.least_squares(
        problem.residual, x0, jac=problem.jacobian, method="trf", tr_solver=tr_solver,
        ftol=tolerance, xtol=tolerance, gtol=tolerance, x_scale="jac",
    )
    return BaselineResult(result.x, 0.5 * float(result.fun @ result.fun), int(result.nfev),
                          1e3 * (time.perf_counter() - start))


def solve_gtsam(graph: FactorGraph, x0=None, tolerance: float = 1e-12, max_iterations: int = 100) -> BaselineResult:
    """The same problem in GTSAM 4.3 solved by its LevenbergMarquardtOptimizer."""
    import gtsam  # optional dependency, only for this baseline

    problem = WhitenedProblem(graph)
    x0 = graph.get_x() if x0 is None else x0
    start = time.perf_counter()
    states = graph.states_from_x(x0)
    free = graph.free_vertices
    slot = np.full(graph.vertex_count, -1, dtype=np.int64)
    slot[free] = np.arange(free.size)

    def symbol(t, vertex):
        return int(t * graph.vertex_count + vertex)

    values = gtsam.Values()
    for t, key in enumerate(graph.keys):
        for vertex in free:
            values.insert(symbol(t, vertex), gtsam.Point3(*states[key][vertex]))
    factors = gtsam.NonlinearFactorGraph()

    def linear_factor(t, vertices, constant_state, rows_root, target):
        """e = A (target - x_vertices) with A (m, 3k) over the free vertices among `vertices`."""
        free_local = [a for a, v in enumerate(vertices) if slot[v] >= 0]
        keys = [symbol(t, vertices[a]) for a in free_local]
        fixed_local = [a for a, v in enumerate(vertices) if slot[v] < 0]
        fixed_part = sum((rows_root[:, 3 * a:3 * a + 3] @ (target[a] - constant_state[vertices[a]]) for a in fixed_local),
                         np.zeros(rows_root.shape[0]))

        def error(this, current, jacobians):
            e = fixed_part.copy()
            for index, a in enumerate(free_local):
                block = rows_root[:, 3 * a:3 * a + 3]
                e += block @ (target[a] - current.atPoint3(this.keys()[index]))
                if jacobians is not None:
                    jacobians[index] = -block
            return e

        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows_root.shape[0]), keys, error)

    for factor in graph.factors:
        if isinstance(factor, PhysicsPriorFactor):
            t = problem.position[factor.keys[0]]
            roots = np.sqrt(factor.scale) * problem.roots[id(factor)]
            fixed_state = graph.states[factor.keys[0]]
            for element, vertices in enumerate(factor.model.tetrahedra):
                if np.all(slot[vertices] < 0):
                    continue
                factors.add(linear_factor(t, list(vertices), fixed_state, roots[element], factor.predicted[vertices]))
            if factor.ridge:
                noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0 / np.sqrt(factor.ridge))
                for vertex in free:
                    factors.add(gtsam.PriorFactorPoint3(symbol(t, vertex), gtsam.Point3(*factor.predicted[vertex]), noise))
        elif isinstance(factor, PointToSurfaceFactor):
            t = problem.position[factor.keys[0]]
            fixed_state = graph.states[factor.keys[0]]
            for point, triangle_index, weight in zip(factor.points, factor.frozen_triangles, factor.weights):
                factors.add(_point_factor(gtsam, factor.triangles[triangle_index], point, np.sqrt(weight),
                                          t, slot, fixed_state, symbol))
        elif isinstance(factor, VolumeBarrierFactor):
            # Zero wherever every element keeps half its volume in the prediction (any plausible
            # window): nothing to add; an active barrier has no CustomFactor form here.
            if factor.cost(graph.states) > 0.0:
                raise BaselineError("the volume barrier is active: GTSAM has no form of it here")
        else:
            t = problem.position[factor.key]
            noise = gtsam.noiseModel.Isotropic.Sigma(3, factor.sigma)
            for vertex in free:
                if factor.previous_key is None:
                    factors.add(gtsam.PriorFactorPoint3(symbol(t, vertex), gtsam.Point3(*factor.anchor[vertex]), noise))
                else:
                    s = problem.position[factor.previous_key]
                    factors.add(gtsam.BetweenFactorPoint3(symbol(s, vertex), symbol(t, vertex), gtsam.Point3(0, 0, 0), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(tolerance)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, values, params)
    optimum = optimizer.optimize()
    x = np.concatenate([
        np.concatenate([np.asarray(optimum.atPoint3(symbol(t, vertex))) for vertex in free])
        for t in range(len(graph.keys))
    ])
    return BaselineResult(x, float(factors.error(optimum)), int(optimizer.iterations()),
                          1e3 * (time.perf_counter() - start))


def _point_factor(gtsam, triangle, point, root, t, slot, fixed_state, symbol):
    """gtsam.CustomFactor of one point on a frozen triangle: e = root (q(x_a, x_b, x_c) - m)."""
    free_local = [a for a in range(3) if slot[triangle[a]] >= 0]
    keys = [symbol(t, triangle[a]) for a in free_local]

    def error(this, current, jacobians):
        corners = fixed_state[triangle].copy()
        for index, a in enumerate(free_local):
            corners[a] = current.atPoint3(this.keys()[index])
        projection = project_onto_triangles(point[None], corners[None, 0], corners[None, 1], corners[None, 2])
        if jacobians is not None:
            jacobian = root * projection_jacobian(point[None], corners[None, 0], corners[None, 1], corners[None, 2],
                                                  projection.region)[0]
            for index, a in enumerate(free_local):
                jacobians[index] = jacobian[:, 3 * a:3 * a + 3]
        return root * (projection.closest[0] - point)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(3), keys, error)


# ----------------------------------------------------------------------------- benchmark
@dataclass
class BenchmarkStep:
    """One synthetic step: stamp, measured points (K, 3), prediction (N, 3), truth (N, 3)."""

    stamp_ns: int
    points: np.ndarray
    predicted: np.ndarray
    truth: np.ndarray


def _viewed_box(target_vertices: int, size: float):
    """A box with its bottom face fixed, each vertex's relative height (N,), and the surface
    triangles seen from +x+y+z (the benchmark sequences' partial view)."""
    mesh = box_mesh(target_vertices, (size, size, size))
    rest = mesh.vertices
    mesh = mesh.with_fixed(np.flatnonzero(np.isclose(rest[:, 2], rest[:, 2].min())))
    height = (rest[:, 2] - rest[:, 2].min()) / size
    seen = mesh.surface_triangles[mesh.triangle_normals() @ np.array([1.0, 1.0, 1.0]) / np.sqrt(3) > 0.3]
    return mesh, height, seen


def synthetic_sequence(target_vertices: int = 500, points_per_step: int = 2000, steps: int = 20,
                       size: float = 0.1, noise_sigma: float = 1e-3, prediction_error: float = 1e-3,
                       seed: int = 0) -> tuple[TetMesh, list[BenchmarkStep]]:
    """A box (bottom face fixed) bending smoothly over `steps` steps; points on the faces seen
    from +x+y+z (a partial view) with Gaussian noise; predictions off the truth by a smooth
    bend (`prediction_error` [m] at the top, in a random direction each step), the kind of
    error a simulator with a wrong load or stiffness makes."""
    rng = np.random.default_rng(seed)
    mesh, height, seen = _viewed_box(target_vertices, size)
    rest = mesh.vertices
    sequence = []
    for step in range(1, steps + 1):
        phase = step / steps
        truth = rest.copy()
        truth[:, 0] += 0.08 * size * phase * height**2
        truth[:, 1] += 0.03 * size * np.sin(np.pi * phase) * height
        truth[:, 2] -= 0.02 * size * phase * height * (rest[:, 0] - rest[:, 0].min()) / size
        direction = rng.normal(size=3)
        predicted = truth + prediction_error * height[:, None] ** 2 * direction / np.linalg.norm(direction)
        clean = sample_surface(truth, seen, points_per_step, seed=int(rng.integers(2**31)))
        points = clean + rng.normal(scale=noise_sigma, size=clean.shape)
        sequence.append(BenchmarkStep(1_000_000_000 * step, points, predicted, truth))
    return mesh, sequence


def mismatch_sequence(target_vertices: int = 500, points_per_step: int = 2000, steps: int = 20,
                      size: float = 0.1, noise_sigma: float = 1e-3, leak_fraction: float = 0.15,
                      seed: int = 0) -> tuple[TetMesh, list[BenchmarkStep]]:
    """A box (bottom fixed) that a tool indents while it bends and sways, with a nominal model
    that differs from it as the accuracy suite's scenes do: the model misses the sway (an
    unmodelled lateral load), bends 20 % less (a stiffer truth) and indents 30 % less deep (a
    tool calibration error); the errors are systematic and grow with the motion, up to about
    2.5 mm at the top. Clouds: the faces seen from +x+y+z with Gaussian noise, plus
    `leak_fraction` of segmentation leaks on the tool and on a table around the box. The
    predictions come from the nominal model, not from the estimates (a benchmark of the
    estimator alone, without a simulator)."""
    rng = np.random.default_rng(seed)
    mesh, height, seen = _viewed_box(target_vertices, size)
    rest = mesh.vertices
    top_centre = np.array([rest[:, 0].mean(), rest[:, 1].mean(), rest[:, 2].max()])
    tool_radius = 0.15 * size
    lateral = np.linalg.norm((rest - top_centre)[:, :2], axis=1) / size

    def deformed(phase, bend, sway, depth):
        state = rest.copy()
        state[:, 0] += bend * 0.08 * size * phase * height**2
        state[:, 1] += sway * 0.03 * size * np.sin(np.pi * phase) * height
        state[:, 2] -= depth * 0.08 * size * phase * height**4 * np.exp(-(lateral / 0.2) ** 2)
        return state

    sequence = []
    for step in range(1, steps + 1):
        phase = step / steps
        truth = deformed(phase, 1.0, 1.0, 1.0)
        predicted = deformed(phase, 0.8, 0.0, 0.7)
        clean = sample_surface(truth, seen, points_per_step, seed=int(rng.integers(2**31)))
        points = clean + rng.normal(scale=noise_sigma, size=clean.shape)
        leaks = int(round(leak_fraction * points_per_step))
        tool = top_centre + np.array([0.0, 0.0, tool_radius - 0.08 * size * phase])
        on_tool = rng.normal(size=(leaks // 2, 3))
        on_tool = tool + tool_radius * on_tool / np.linalg.norm(on_tool, axis=1)[:, None]
        table = np.column_stack([rng.uniform(-0.5, 1.5, (leaks - leaks // 2, 2)) * size,
                                 np.full(leaks - leaks // 2, rest[:, 2].min())])
        points = np.concatenate([points, on_tool, table])
        sequence.append(BenchmarkStep(1_000_000_000 * step, points, predicted, truth))
    return mesh, sequence


def benchmark_update(mesh: TetMesh, sequence, config, warmup: int | None = None) -> dict:
    """Run the estimator node's step loop (core.scheduler.EstimationScheduler: each cloud paired
    with its prediction, given as the simulation node would) over `sequence`; latency statistics
    of the updates after `warmup` of them (default: the window filling, window_size - 1 updates).

    Returns latencies_ms, median_ms, p95_ms, mean_iterations, linear_solve_ms (median time of
    one linear solve over all updates, from StepResult.linear_solve_ms), final_costs, rmse_m
    (vertex RMSE of each update against the truth), converged_share (of the timed updates) and
    the last measurement sigma estimate.
    """
    from meshfg_ros.core.scheduler import EstimationScheduler, Prediction  # the scheduler imports the estimator

    scheduler = EstimationScheduler(mesh, config)
    warmup = config.window_size - 1 if warmup is None else warmup
    latencies, iterations, solves, costs, rmse, converged = [], [], [], [], [], []
    for index, step in enumerate(sequence):
        scheduler.add_cloud(step.stamp_ns, step.points)
        scheduler.add_prediction(Prediction(step.stamp_ns, step.predicted))
        start = time.perf_counter()
        outcome = scheduler.run(scheduler.next_step())
        elapsed = 1e3 * (time.perf_counter() - start)
        if outcome.result is None:
            raise RuntimeError(f"benchmark update {index} failed: {outcome.error}")
        result = outcome.result
        solves.extend(result.linear_solve_ms)
        if index >= warmup:
            latencies.append(elapsed)
            iterations.append(result.iterations)
            costs.append(result.final_cost)
            converged.append(result.converged)
        rmse.append(float(np.sqrt(np.mean(np.sum((result.positions - step.truth) ** 2, axis=1)))))
    latencies = np.asarray(latencies)
    return dict(
        latencies_ms=latencies.tolist(),
        median_ms=float(np.median(latencies)),
        p95_ms=float(np.percentile(latencies, 95)),
        mean_iterations=float(np.mean(iterations)),
        linear_solve_ms=float(np.median(solves)) if solves else 0.0,
        final_costs=costs,
        rmse_m=rmse,
        converged_share=float(np.mean(converged)),
        measurement_sigma_m=float(result.measurement_sigma),
    )


def pending_window(mesh: TetMesh, sequence, config):
    """The window problem of the last step of `sequence` as the estimator poses it: the
    estimator runs over all steps but the last, then adds the last one without optimising.
    Returns (estimator, graph) with the association frozen at the initial guess, ready for
    `compare_single_update`."""
    from meshfg_ros.core.estimation.estimator import SlidingWindowEstimator  # avoids an import cycle

    estimator = SlidingWindowEstimator(mesh, config)
    for step in sequence[:-1]:
        estimator.update(step.stamp_ns, step.points, step.predicted)
    last = sequence[-1]
    estimator.prepare(last.stamp_ns, last.points, last.predicted)
    graph = estimator.graph
    graph.relinearize_threshold = 0.0  # every solver sees the exact problem
    for factor in graph.factors:
        if isinstance(factor, PhysicsPriorFactor):
            factor.information(graph.states[factor.keys[0]])
    freeze_associations(graph)
    return estimator, graph


def compare_single_update(graph: FactorGraph, solvers=("meshfg", "scipy", "gtsam"), tolerance: float = 1e-10,
                          linear_tolerance: float = 1e-12) -> dict:
    """Solve one window problem (association frozen, information fixed) with each solver from
    the same start, to relative cost decrease `tolerance`; returns name -> BaselineResult.
    The graph's states are left unchanged."""
    freeze_associations(graph)
    x0 = graph.get_x()
    out = {}
    for name in solvers:
        if name == "meshfg":
            config = LevenbergMarquardtConfig(max_iterations=200, cost_tolerance=tolerance, step_tolerance=1e-14,
                                              gradient_tolerance=1e-14)
            out[name] = solve_meshfg(graph, x0, config, tolerance=linear_tolerance)
        elif name == "scipy":
            out[name] = solve_scipy(graph, x0, tolerance)
        elif name == "gtsam":
            out[name] = solve_gtsam(graph, x0, tolerance)
        else:
            raise ValueError(f"unknown solver {name!r}")
    return out
