"""Factors of the mesh factor graph and the graph that assembles their normal equations.

A factor touches the states (N, 3) of one or two keys and gives its residual r, its
Jacobians dr/dX_key (sparse, w.r.t. the flattened vertex positions x0 y0 z0 x1 ...), its cost
and its contribution to the Gauss-Newton normal equations. Noise models (noise.py) and robust
kernels (robust.py) are separate objects passed to the factor.

  PhysicsPriorFactor     r = Xhat_t - X_t,  information Lambda = scale * K(X_t) + ridge I
  PointToSurfaceFactor   r_k = (a x_a + b x_b + c x_c) - m_k on the closest surface triangle
  TemporalFactor         r = X_t - X_{t-1} (or - an anchor state), information I / sigma^2

`FactorGraph` holds the states of a window (in time order), their factors and the fixed
(boundary) vertices, and is the problem Levenberg-Marquardt solves: unknowns are the free
vertex coordinates of every state; fixed vertices are eliminated (held at their known
positions), which is exact and keeps the system well conditioned, unlike a stiff prior.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse

from meshfg_ros.core.closest_point import REGION_FACE, Association, ClosestPointIndex, project_onto_triangles, projection_jacobian
from meshfg_ros.core.linear_solvers import WindowSystem, diagonal_positions
from meshfg_ros.core.mesh import signed_volumes
from meshfg_ros.core.noise import IdentityNoise, InformationMatrixNoise, PointNoise
from meshfg_ros.core.robust import RobustKernel

__all__ = [
    "MIN_VOLUME_RATIO_PER_STEP",
    "Factor",
    "FactorError",
    "FactorGraph",
    "FactorLinearization",
    "PhysicsPriorFactor",
    "ElementBlocks",
    "PointBlocks",
    "PointToSurfaceFactor",
    "TemporalFactor",
    "VolumeBarrierFactor",
    "prior_scale",
]


# LM's inversion guard: one step may shrink a tetrahedron to no less than this fraction of its
# volume (FactorGraph.step_fraction). A quarter leaves room for the real compression of tissue
# (volume ratios near 1: nearly incompressible) while no step can flatten or invert an element.
MIN_VOLUME_RATIO_PER_STEP = 0.25
# step_fraction brackets a volume's first crossing of the margin on this many equal fractions
# of the step, then bisects; the result is verified on exact volumes, halving if needed.
_STEP_FRACTION_GRID = 16
_STEP_FRACTION_BISECTIONS = 20
_STEP_FRACTION_HALVINGS = 30
# The physics prior's volume barrier (VolumeBarrierFactor) acts on tetrahedra below this
# fraction of their volume in the prior's mean (the prediction): far below any correction a
# nearly incompressible tissue needs, so it never moves a plausible estimate, while it keeps
# the optimum itself from flattening or inverting elements.
BARRIER_VOLUME_RATIO = 0.5


class FactorError(ValueError):
    """Bad factor input: wrong shapes, unknown keys, non-finite values."""


def _as_state(array, vertex_count: int, what: str) -> np.ndarray:
    state = np.asarray(array, dtype=np.float64)
    if state.shape != (vertex_count, 3):
        raise FactorError(f"{what} must have shape ({vertex_count}, 3), got {state.shape}")
    if not np.all(np.isfinite(state)):
        raise FactorError(f"{what} contains NaN or infinite values")
    return state


@dataclass
class PointBlocks:
    """Per-point normal-equation terms of point-to-triangle residuals: triangle (P,) surface
    triangle index, hessian (P, 81) = w J^T J (9x9 over the triangle's 9 coordinates, row
    major), gradient (P, 9) = w J^T r. hessian is None when only the gradient was asked for."""

    triangle: np.ndarray
    hessian: np.ndarray | None
    gradient: np.ndarray


@dataclass
class FactorLinearization:
    """A factor's cost and normal-equation terms at a linearisation point.

    gradients[key] (3N,) = J_key^T W r; hessians[(key, key)] csr (3N, 3N) = J^T W J;
    identity_terms[(key_i, key_j)] = c for a c * I block (i == j on the diagonal block,
    i != j the off-diagonal block); point_blocks[key] per-point terms (measurements);
    element_blocks[key] per-tetrahedron terms (the volume barrier).
    """

    cost: float
    gradients: dict = field(default_factory=dict)
    hessians: dict = field(default_factory=dict)
    identity_terms: dict = field(default_factory=dict)
    point_blocks: dict = field(default_factory=dict)
    element_blocks: dict = field(default_factory=dict)


@dataclass
class ElementBlocks:
    """Per-tetrahedron normal-equation terms: tetrahedron (P,) indices, hessian (P, 144) over
    the element's 12 coordinates (row major) or None, gradient (P, 12)."""

    tetrahedron: np.ndarray
    hessian: np.ndarray | None
    gradient: np.ndarray


class Factor:
    """Base: keys (the state keys it touches), residual, Jacobians, cost and linearisation."""

    keys: tuple = ()

    def residual(self, states: dict) -> np.ndarray:
        raise NotImplementedError

    def jacobians(self, states: dict) -> dict:
        """dr/dX_key for each key: csr (m, 3N)."""
        raise NotImplementedError

    def cost(self, states: dict) -> float:
        raise NotImplementedError

    def linearize(self, states: dict, hessian: bool = True) -> FactorLinearization:
        """Cost, gradient and (hessian=True) Gauss-Newton terms at `states`; hessian=False may
        leave the Hessian terms out, for a gradient-only evaluation."""
        raise NotImplementedError


def prior_scale(stiffness, simulation_sigma: float, free_dofs=None) -> float:
    """Scale s with mean(diag(s K)) = 1 / simulation_sigma^2 over `free_dofs` (None: all).

    K is in N/m and measurement information in 1/m^2, so K needs a scale ("temperature").
    Choosing it so the prior's mean per-coordinate information equals that of an independent
    simulator error of std `simulation_sigma` [m] per vertex coordinate makes the prior weigh
    like the simulator's expected accuracy while keeping K's stiffness ratios.
    """
    if not (np.isfinite(simulation_sigma) and simulation_sigma > 0.0):
        raise FactorError(f"simulation_sigma must be finite and > 0, got {simulation_sigma}")
    diagonal = scipy.sparse.csr_matrix(stiffness).diagonal()
    if free_dofs is not None:
        diagonal = diagonal[free_dofs]
    mean = float(np.mean(diagonal))
    if not mean > 0.0:
        raise FactorError("stiffness has a non-positive mean diagonal")
    return 1.0 / (simulation_sigma**2 * mean)


class PhysicsPriorFactor(Factor):
    """r = Xhat - X with information Lambda(X) = scale * K(X) + ridge * I.

    model: an ElasticModel (core.fem); kind / spd_projection select K. K depends on X and is
    treated as the information matrix, not differentiated. With relinearize=True it is
    re-evaluated at the linearisation point on every `linearize` (once per LM iteration);
    with relinearize=False it is evaluated at the first linearisation and kept until
    `invalidate_information()` (the estimator does that once per update, see estimator.py).
    `cost` uses the Lambda of the last evaluation, so a trial step is judged on the same
    quadratic as its model. The tiny ridge fixes the 6 rigid-body modes a free body's K leaves without
    information. Raw neo-Hookean K may be indefinite: then Lambda is too, and the solver's
    damping must make the step system positive definite.
    """

    def __init__(self, key, predicted, model, kind: str = "corotational", spd_projection: bool = False,
                 scale: float = 1.0, ridge: float = 0.0, relinearize: bool = True):
        self.keys = (key,)
        self.model = model
        self.predicted = _as_state(predicted, model.vertex_count, "predicted state")
        self.kind = kind
        self.spd_projection = bool(spd_projection)
        self.scale = float(scale)
        self.ridge = float(ridge)
        self.relinearize = bool(relinearize)
        self._information: scipy.sparse.csr_matrix | None = None
        self.information_state: np.ndarray | None = None  # where Lambda was last evaluated

    def information(self, state: np.ndarray) -> scipy.sparse.csr_matrix:
        """Lambda at `state` (N, 3); cached when K cannot change (linear kind or relinearize off)."""
        constant = self.kind == "linear" or not self.relinearize
        if self._information is None or not constant:
            stiffness = self.model.stiffness(state, kind=self.kind, spd_projection=self.spd_projection)
            information = (self.scale * stiffness).tocsr()
            if self.ridge:
                information = (information + scipy.sparse.identity(information.shape[0]) * self.ridge).tocsr()
            self._information = information
            self.information_state = np.array(state, dtype=np.float64)
        return self._information

    def invalidate_information(self) -> None:
        """Make the next linearisation re-evaluate K at its linearisation point."""
        if self.kind != "linear":
            self._information = None

    def noise_model(self, state: np.ndarray) -> InformationMatrixNoise:
        return InformationMatrixNoise(self.information(state))

    def residual(self, states):
        return (self.predicted - states[self.keys[0]]).reshape(-1)

    def jacobians(self, states):
        size = 3 * self.model.vertex_count
        return {self.keys[0]: -scipy.sparse.identity(size, format="csr")}

    def cost(self, states):
        if self._information is None:
            self.information(states[self.keys[0]])
        r = self.residual(states)
        return 0.5 * float(r @ (self._information @ r))

    def linearize(self, states, hessian=True):
        key = self.keys[0]
        information = self.information(states[key])
        r = self.residual(states)
        weighted = information @ r
        return FactorLinearization(
            cost=0.5 * float(r @ weighted),
            gradients={key: -weighted},
            hessians={(key, key): information} if hessian else {},
        )


def _six_volume_gradients(corners: np.ndarray) -> np.ndarray:
    """Gradient (P, 12) of 6 V w.r.t. the corners (P, 4, 3) of tetrahedra: u x v etc."""
    u, v, w = (corners[:, k] - corners[:, 0] for k in (1, 2, 3))
    by_corner = np.stack([np.cross(v, w), np.cross(w, u), np.cross(u, v)], axis=1)  # d(6V)/dx_1..3
    return np.concatenate([-by_corner.sum(axis=1, keepdims=True), by_corner], axis=1).reshape(-1, 12)


class VolumeBarrierFactor(Factor):
    """A barrier that keeps every tetrahedron of state `key` away from flat or inverted.

    With J_e = V_e(X) / V_e(reference) (the estimator's reference: the prior's mean Xhat, so
    the barrier is zero where the prior is centred) its cost is sum_e b_e psi(J_e),
        psi(J) = (J_c / J - 1)^2 for 0 < J < J_c,   0 for J >= J_c,   +inf for J <= 0,
    J_c = BARRIER_VOLUME_RATIO: C1 at J_c, so it is zero (and exerts no force) on every
    plausible state and grows like 1/J^2 towards a flat element. The physics prior is a
    Gaussian in X - Xhat and by itself prices an inverted element like any other displacement;
    the barrier belongs to it (the estimator gives b_e = the prior's scale times the element's
    rest bulk energy scale kappa V_e), so the optimum of a window never flattens an element
    further than the simulator did.
    As a least-squares residual r_e = sqrt(2 b_e psi(J_e)); its Gauss-Newton terms are
    b_e psi''(J_e) dJ dJ^T (positive: psi is convex) and the gradient b_e psi'(J_e) dJ.
    """

    def __init__(self, key, tetrahedra, reference_volumes, stiffness, threshold: float = BARRIER_VOLUME_RATIO):
        self.keys = (key,)
        self.tetrahedra = np.asarray(tetrahedra, dtype=np.int64)
        self.reference_volumes = np.asarray(reference_volumes, dtype=np.float64)
        self.stiffness = np.broadcast_to(np.asarray(stiffness, dtype=np.float64), self.reference_volumes.shape).copy()
        if not (0.0 < threshold < 1.0):
            raise FactorError(f"barrier threshold must lie in (0, 1), got {threshold}")
        if not (np.all(self.reference_volumes > 0.0) and np.all(np.isfinite(self.stiffness)) and np.all(self.stiffness >= 0.0)):
            raise FactorError("barrier needs positive reference volumes and finite, non-negative stiffness")
        self.threshold = float(threshold)

    def _ratios(self, state: np.ndarray) -> np.ndarray:
        return signed_volumes(state, self.tetrahedra) / self.reference_volumes

    def _psi(self, ratio: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """psi, psi', psi'' at ratios in (0, J_c)."""
        q = self.threshold / ratio
        return (q - 1.0) ** 2, -2.0 * (q - 1.0) * q / ratio, (2.0 * q * q + 4.0 * (q - 1.0) * q) / ratio**2

    def cost(self, states):
        ratio = self._ratios(states[self.keys[0]])
        if np.any(~(ratio > 0.0)):
            return np.inf
        active = ratio < self.threshold
        if not active.any():
            return 0.0
        return float(self.stiffness[active] @ self._psi(ratio[active])[0])

    def residual(self, states):
        ratio = self._ratios(states[self.keys[0]])
        values = np.zeros_like(ratio)
        active = (ratio > 0.0) & (ratio < self.threshold)
        values[active] = np.sqrt(2.0 * self.stiffness[active] * self._psi(ratio[active])[0])
        values[ratio <= 0.0] = np.inf
        return values

    def _terms(self, state):
        """(active tetrahedra, cost, psi', psi'', dJ (P, 12)) at `state`."""
        ratio = self._ratios(state)
        active = np.flatnonzero((ratio > 0.0) & (ratio < self.threshold))
        psi, slope, curvature = self._psi(ratio[active])
        six_volume_gradient = _six_volume_gradients(np.asarray(state, dtype=np.float64)[self.tetrahedra[active]])
        ratio_gradient = six_volume_gradient / (6.0 * self.reference_volumes[active])[:, None]
        return active, float(self.stiffness[active] @ psi), slope, curvature, ratio_gradient

    def jacobians(self, states):
        key = self.keys[0]
        state = states[key]
        active, _, slope, _, ratio_gradient = self._terms(state)
        values = self.residual(states)[active]
        scale = np.where(values > 0.0, self.stiffness[active] * slope / np.maximum(values, 1e-300), 0.0)
        columns = (3 * self.tetrahedra[active][:, :, None] + np.arange(3)).reshape(-1, 12)
        rows = np.broadcast_to(active[:, None], columns.shape)
        matrix = scipy.sparse.csr_matrix(((scale[:, None] * ratio_gradient).reshape(-1), (rows.reshape(-1), columns.reshape(-1))),
                                         shape=(len(self.tetrahedra), state.size))
        return {key: matrix}

    def linearize(self, states, hessian=True):
        key = self.keys[0]
        active, cost, slope, curvature, ratio_gradient = self._terms(states[key])
        if not active.size:
            return FactorLinearization(cost=cost)
        weight = self.stiffness[active]
        gradient = (weight * slope)[:, None] * ratio_gradient
        blocks = None
        if hessian:
            blocks = ((weight * curvature)[:, None, None] * ratio_gradient[:, :, None] * ratio_gradient[:, None, :])
            blocks = blocks.reshape(-1, 144)
        return FactorLinearization(cost=cost, element_blocks={key: ElementBlocks(active, blocks, gradient)})


class TemporalFactor(Factor):
    """r = X_t - X_previous with information I / sigma^2; the previous state is a key of the
    graph, or (anchor) a constant state: one that left the window or the initial mesh."""

    def __init__(self, key, sigma: float, previous_key=None, anchor=None):
        if not (np.isfinite(sigma) and sigma > 0.0):
            raise FactorError(f"temporal sigma must be finite and > 0, got {sigma}")
        if (previous_key is None) == (anchor is None):
            raise FactorError("a temporal factor needs exactly one of previous_key and anchor")
        self.sigma = float(sigma)
        self.weight = 1.0 / self.sigma**2
        self.key = key
        self.previous_key = previous_key
        self.anchor = None if anchor is None else np.array(anchor, dtype=np.float64)
        self.keys = (key,) if anchor is not None else (previous_key, key)

    def _previous(self, states):
        return self.anchor if self.anchor is not None else states[self.previous_key]

    def residual(self, states):
        return (states[self.key] - self._previous(states)).reshape(-1)

    def jacobians(self, states):
        size = states[self.key].size
        identity = scipy.sparse.identity(size, format="csr")
        out = {self.key: identity}
        if self.anchor is None:
            out[self.previous_key] = -identity
        return out

    def cost(self, states):
        r = self.residual(states)
        return 0.5 * self.weight * float(r @ r)

    def linearize(self, states, hessian=True):
        r = self.residual(states)
        out = FactorLinearization(cost=0.5 * self.weight * float(r @ r))
        out.gradients[self.key] = self.weight * r
        out.identity_terms[(self.key, self.key)] = self.weight
        if self.anchor is None:
            out.gradients[self.previous_key] = -self.weight * r
            out.identity_terms[(self.previous_key, self.previous_key)] = self.weight
            out.identity_terms[(self.previous_key, self.key)] = -self.weight
        return out


class PointToSurfaceFactor(Factor):
    """Measured points against the closest triangle of the surface of state `key`.

    r_k = q_k - m_k with q_k the closed-form closest point (closest_point.py) on the closest
    surface triangle; its Jacobian is the exact derivative of that projection (barycentrics
    included). Association: the closest triangle is re-found exactly (closest_point.py's AABB
    tree) whenever the residual is evaluated at a new state (every cost evaluation and
    linearisation), so the cost is the true point-to-surface distance, continuous in X, and
    LM's gain ratio compares like with like. `freeze_association` pins each point to its
    current triangle (for cross-checks with other solvers).

    Points farther than `gating_distance` from the surface at `initial_vertices` are rejected
    once, at construction (num_points_rejected), so the objective does not change while LM
    iterates; `gating_distance` may be a function of those distances (K,) that returns the gate
    (a gate from the data's own spread). Cost: 0.5 sum_k w_k rho(|r_k|^2), w_k = 1/sigma_k^2, rho the robust kernel
    (identity without one), applied as IRLS weights w_k rho'(|r_k|^2).
    """

    def __init__(self, key, points, surface_triangles, initial_vertices, noise: PointNoise | None = None,
                 robust: RobustKernel | None = None, gating_distance=np.inf):
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise FactorError(f"points must have shape (K, 3), got {points.shape}")
        if not np.all(np.isfinite(points)):
            raise FactorError("points contain NaN or infinite values")
        self.keys = (key,)
        self.triangles = np.asarray(surface_triangles, dtype=np.int64)
        initial_vertices = np.asarray(initial_vertices, dtype=np.float64)
        self.vertex_count = len(initial_vertices)
        noise = IdentityNoise() if noise is None else noise
        noise.point_weights(len(points))  # validates per-point sizes
        accepted = np.ones(len(points), dtype=bool)
        initial_association = None
        if (callable(gating_distance) or np.isfinite(gating_distance)) and len(points):
            initial_association = ClosestPointIndex(initial_vertices, self.triangles).associate(points)
            gate = gating_distance(initial_association.distance) if callable(gating_distance) else gating_distance
            accepted = initial_association.distance <= gate
            if not accepted.all():
                initial_association = Association(*(getattr(initial_association, name)[accepted] for name in (
                    "triangle", "closest", "barycentric", "region", "distance")))
        self.num_points_rejected = int(np.count_nonzero(~accepted))
        self.points = points[accepted]
        self.noise = noise.subset(accepted)
        self.weights = self.noise.point_weights(len(self.points))
        self.robust = robust
        self._frozen_triangle: np.ndarray | None = None
        # Last (vertices, association): LM linearises where the gating or a trial's cost associated.
        self._last_association = None if initial_association is None else (initial_vertices.copy(), initial_association)

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def frozen_triangles(self) -> np.ndarray | None:
        """Triangle index per point pinned by `freeze_association`, or None (free association)."""
        return self._frozen_triangle

    def associate(self, states) -> Association:
        """Closest triangle per point on the surface of the current state (or the frozen ones)."""
        vertices = states[self.keys[0]]
        last = self._last_association
        if last is not None and np.array_equal(last[0], vertices):
            return last[1]
        if self._frozen_triangle is not None:
            corners = vertices[self.triangles[self._frozen_triangle]]
            projection = project_onto_triangles(self.points, corners[:, 0], corners[:, 1], corners[:, 2])
            association = Association(self._frozen_triangle, projection.closest, projection.barycentric,
                                      projection.region, np.sqrt(projection.squared_distance))
        else:
            association = ClosestPointIndex(vertices, self.triangles).associate(self.points)
        self._last_association = (np.array(vertices, dtype=np.float64), association)
        return association

    def freeze_association(self, states) -> np.ndarray:
        """Pin every point to its closest triangle at `states`; returns those triangle indices."""
        self._frozen_triangle = self.associate(states).triangle.copy()
        self._last_association = None
        return self._frozen_triangle

    def _terms(self, states):
        association = self.associate(states)
        residual = association.closest - self.points
        squared = np.einsum("ij,ij->i", residual, residual)
        if self.robust is None:
            cost_terms, irls = squared, self.weights
        else:
            cost_terms, irls = self.robust.rho(squared), self.weights * self.robust.weight(squared)
        return association, residual, 0.5 * float(self.weights @ cost_terms), irls

    def residual(self, states):
        if not self.num_points:
            return np.zeros(0)
        return (self.associate(states).closest - self.points).reshape(-1)

    def _distance_hessians(self, states, association, residual, irls) -> np.ndarray:
        """Gauss-Newton terms (K, 81) of the points' squared distances.

        A point projected inside its face has d = n.(m - q): its Gauss-Newton term is
        w (beta (x) n)(beta (x) n)^T, since d d / d x_i = -beta_i n (the envelope theorem, as for
        the gradient). Gauss-Newton on the vector r = q - m instead adds d^2 (dn/dX)^T (dn/dX),
        a stiffness against turning the face that the distance does not have; at a window's
        optimum the prior holds the surface off the data, the d keep a systematic part and that
        term made Levenberg-Marquardt's steps stop short (measured on the airway scene: the
        vector form's curvature along a step was 1.35x the true one, LM converged linearly at
        about half the remaining decrease per iteration). A point projected onto an edge or a
        vertex keeps the vector form, which is exact there (distance to a line or a point)."""
        face = association.region == REGION_FACE
        hessians = np.empty((len(residual), 81))
        if face.any():
            corners = states[self.keys[0]][self.triangles[association.triangle[face]]]
            normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            normals /= np.linalg.norm(normals, axis=1)[:, None]
            rows = (association.barycentric[face][:, :, None] * normals[:, None, :]).reshape(-1, 9)
            hessians[face] = ((irls[face][:, None] * rows)[:, :, None] * rows[:, None, :]).reshape(-1, 81)
        if not face.all():
            other = ~face
            subset = Association(*(getattr(association, name)[other] for name in (
                "triangle", "closest", "barycentric", "region", "distance")))
            corners = states[self.keys[0]][self.triangles[subset.triangle]]
            jacobian = projection_jacobian(self.points[other], corners[:, 0], corners[:, 1], corners[:, 2], subset.region)
            # Batched matmul: 5x faster than the equivalent einsum on (K, 3, 9) stacks.
            hessians[other] = ((jacobian * irls[other][:, None, None]).transpose(0, 2, 1) @ jacobian).reshape(-1, 81)
        return hessians

    def _point_jacobians(self, states, association):
        corners = states[self.keys[0]][self.triangles[association.triangle]]
        return projection_jacobian(self.points, corners[:, 0], corners[:, 1], corners[:, 2], association.region)

    def jacobians(self, states):
        size = 3 * self.vertex_count
        if not self.num_points:
            return {self.keys[0]: scipy.sparse.csr_matrix((0, size))}
        association = self.associate(states)
        jacobian = self._point_jacobians(states, association)  # (K, 3, 9)
        vertex_dofs = 3 * self.triangles[association.triangle][:, :, None] + np.arange(3)  # (K, 3, 3)
        rows = np.broadcast_to(np.arange(3 * self.num_points).reshape(-1, 3, 1), jacobian.shape)
        cols = np.broadcast_to(vertex_dofs.reshape(-1, 1, 9), jacobian.shape)
        matrix = scipy.sparse.csr_matrix(
            (jacobian.reshape(-1), (rows.reshape(-1), cols.reshape(-1))), shape=(3 * self.num_points, size)
        )
        return {self.keys[0]: matrix}

    def cost(self, states):
        if not self.num_points:
            return 0.0
        return self._terms(states)[2]

    def linearize(self, states, hessian=True):
        key = self.keys[0]
        if not self.num_points:
            return FactorLinearization(cost=0.0)
        association, residual, cost, irls = self._terms(states)
        # J^T W r without J: q is the closest point of the triangle, so (dq/dX)^T r equals the
        # derivative with the barycentrics held fixed, beta_i r for corner i (envelope theorem;
        # test_jacobian_times_residual_is_the_fixed_barycentric_gradient checks it per region).
        weighted_residual = irls[:, None] * residual
        gradient = (association.barycentric[:, :, None] * weighted_residual[:, None, :]).reshape(-1, 9)
        point_hessian = None
        if hessian:
            point_hessian = self._distance_hessians(states, association, residual, irls)
        blocks = PointBlocks(association.triangle, point_hessian, gradient)
        return FactorLinearization(cost=cost, point_blocks={key: blocks})


@dataclass
class _StateLinearization:
    """Cached normal-equation terms of the single-state factors of one state at x_lin."""

    x_lin: np.ndarray        # (N, 3) linearisation point
    data: np.ndarray         # (nnz + 1,) block values on the pattern (last: sink)
    gradient: np.ndarray     # (3N,)
    cost: float
    block: scipy.sparse.csr_matrix | None = None  # block over the free dofs (for the model)
    revision: int = 0        # FactorGraph.relinearizations when it was made: names its values
    rebased: bool = False    # FactorGraph.gradient moved x_lin, cost, gradient; data is older
    model_at: tuple | None = None  # (state, cost, gradient) of the last model evaluation


class FactorGraph:
    """States of a window (time order), their factors and fixed vertices; the LM problem.

    vertex_count N, tetrahedra (M, 4) (sparsity pattern and inversion checks), surface
    triangles (F, 3), fixed vertices (held at fixed_positions). Unknown vector x: the free
    vertex coordinates of every state, concatenated in window order.

    Relinearisation (as iSAM2's): the single-state factors of a state (physics prior,
    measurements) are re-linearised when it moved more than `relinearize_threshold` [m] (RMS
    vertex displacement) from where they were last linearised; otherwise their cached
    Gauss-Newton quadratic c + g.d + 0.5 d.H d (d = X - X_lin) stands in for them, in the
    gradient and in the cost, until the next linearisation. States that are re-linearised are
    "active": `cost` evaluates their factors exactly. Old window states, which get no new
    measurements, thus cost nothing until they really move. threshold 0 re-linearises every
    state at every iteration (exact Levenberg-Marquardt on the window). Temporal factors are
    exact quadratics and always evaluated directly. States in `exact_keys` (the estimator's
    newest state, the one its new measurements and prediction act on) ignore the threshold.
    """

    def __init__(self, vertex_count: int, tetrahedra, surface_triangles, fixed_vertices=(), fixed_positions=None,
                 relinearize_threshold: float = 0.0):
        self.vertex_count = int(vertex_count)
        self.tetrahedra = np.asarray(tetrahedra, dtype=np.int64)
        self.surface_triangles = np.asarray(surface_triangles, dtype=np.int64)
        fixed = np.unique(np.asarray(fixed_vertices, dtype=np.int64))
        self.fixed_vertices = fixed
        is_free = np.ones(self.vertex_count, dtype=bool)
        is_free[fixed] = False
        self.free_vertices = np.flatnonzero(is_free)
        self.fixed_positions = None if fixed_positions is None else _as_state(fixed_positions, self.vertex_count, "fixed positions")[fixed]
        self.free_dofs = (3 * self.free_vertices[:, None] + np.arange(3)).reshape(-1)
        self.dof_count = 3 * self.vertex_count
        self.block_size = self.free_dofs.size
        self._free_index = np.full(self.dof_count, -1, dtype=np.int64)
        self._free_index[self.free_dofs] = np.arange(self.block_size)
        self.relinearize_threshold = float(relinearize_threshold)
        self._build_pattern()
        self.keys: list = []
        self.states: dict = {}
        self.factors: list[Factor] = []
        self._state_volumes: dict = {}  # key -> (state, its signed volumes): see _window_volumes
        self._cache: dict = {}
        self._active: set = set()
        self.exact_keys: set = set()  # states re-linearised whenever they move at all
        self.relinearizations = 0

    # ------------------------------------------------------------------------ pattern
    def _build_pattern(self) -> None:
        """Block pattern over free dofs: every pair of dofs of vertices sharing a tetrahedron."""
        tets = self.tetrahedra
        vertex_rows = np.repeat(tets, 4, axis=1).reshape(-1)
        vertex_cols = np.tile(tets, (1, 4)).reshape(-1)
        rows = (3 * vertex_rows[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2).reshape(-1)
        cols = (3 * vertex_cols[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1).reshape(-1)
        free_rows, free_cols = self._free_index[rows], self._free_index[cols]
        keep = (free_rows >= 0) & (free_cols >= 0)
        n = self.block_size
        keys = np.unique(free_rows[keep] * n + free_cols[keep])
        keys = np.union1d(keys, np.arange(n) * (n + 1))
        self._pattern_keys = keys
        pattern_rows, pattern_cols = np.divmod(keys, n)
        indptr = np.searchsorted(pattern_rows, np.arange(n + 1)).astype(np.int32)
        self._pattern = scipy.sparse.csr_matrix(
            (np.zeros(keys.size), pattern_cols.astype(np.int32), indptr), shape=(n, n)
        )
        self._diagonal_index = diagonal_positions(self._pattern)
        # Positions of every triangle's 9x9 dof pairs (row major) in the pattern (or the sink).
        triangle_dofs = (3 * self.surface_triangles[:, :, None] + np.arange(3)).reshape(-1, 9)
        self._triangle_dofs = triangle_dofs
        self._tetrahedron_dofs = (3 * self.tetrahedra[:, :, None] + np.arange(3)).reshape(-1, 12)
        self._triangle_slots = self._slots(
            np.repeat(triangle_dofs, 9, axis=1), np.tile(triangle_dofs, (1, 9))
        ).reshape(-1, 81)
        free_vertex_dofs = 3 * np.arange(n // 3)[:, None, None] + np.arange(3)
        self._vertex_block_slots = np.searchsorted(
            keys, (free_vertex_dofs * n + free_vertex_dofs.transpose(0, 2, 1)).reshape(-1)
        ).reshape(-1, 3, 3)
        self._csr_slot_cache: tuple | None = None
        self._scattered_hessians: dict = {}  # factor -> (its Hessian matrix, values on the pattern)

    def _slots(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Pattern data positions of full-dof pairs (rows, cols); nnz (a sink slot) where a dof
        is fixed."""
        free_rows, free_cols = self._free_index[rows], self._free_index[cols]
        inside = (free_rows >= 0) & (free_cols >= 0)
        keys = free_rows * self.block_size + free_cols
        slots = np.searchsorted(self._pattern_keys, np.where(inside, keys, 0))
        slots = np.where(inside, slots, self._pattern_keys.size)
        hit = slots[inside]
        if np.any(hit >= self._pattern_keys.size) or np.any(self._pattern_keys[hit] != keys[inside]):
            raise FactorError("a factor couples dofs of vertices that share no tetrahedron")
        return slots

    def _csr_slots(self, matrix: scipy.sparse.csr_matrix) -> np.ndarray:
        cache = self._csr_slot_cache
        if cache is not None and np.array_equal(cache[0], matrix.indptr) and np.array_equal(cache[1], matrix.indices):
            return cache[2]
        rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
        slots = self._slots(rows, matrix.indices.astype(np.int64))
        self._csr_slot_cache = (matrix.indptr.copy(), matrix.indices.copy(), slots)
        return slots

    def newest_vertex_information(self) -> np.ndarray:
        """3x3 information blocks (free vertices, 3, 3) of the newest state: its single-state
        factors at their last linearisation plus its temporal terms."""
        key = self.keys[-1]
        cached = self._cache.get(key) or self._relinearize(key, self.states[key])
        blocks = cached.data[self._vertex_block_slots].copy()
        temporal = 0.0
        for factor in self._cross_factors():
            if key in factor.keys and isinstance(factor, TemporalFactor):
                temporal += factor.weight
        return blocks + temporal * np.eye(3)

    # ------------------------------------------------------------------------ states
    def add_state(self, key, initial) -> None:
        """Append state `key` (newest) with initial positions (N, 3); fixed vertices are reset."""
        if key in self.states:
            raise FactorError(f"state {key!r} is already in the graph")
        state = _as_state(initial, self.vertex_count, f"initial state {key!r}").copy()
        if self.fixed_positions is not None:
            state[self.fixed_vertices] = self.fixed_positions
        self.keys.append(key)
        self.states[key] = state

    def remove_state(self, key) -> np.ndarray:
        """Drop state `key` and every factor touching it; returns its positions."""
        state = self.states.pop(key)
        self.keys.remove(key)
        self._state_volumes.pop(key, None)
        self._cache.pop(key, None)
        self._active.discard(key)
        self.factors = [factor for factor in self.factors if key not in factor.keys]
        return state

    def add_factor(self, factor: Factor) -> None:
        unknown = [key for key in factor.keys if key not in self.states]
        if unknown:
            raise FactorError(f"factor touches unknown state {unknown[0]!r}")
        self.factors.append(factor)
        if len(factor.keys) == 1 and not isinstance(factor, TemporalFactor):
            self._cache.pop(factor.keys[0], None)

    def get_x(self) -> np.ndarray:
        return np.concatenate([self.states[key].reshape(-1)[self.free_dofs] for key in self.keys])

    def states_from_x(self, x: np.ndarray) -> dict:
        parts = np.asarray(x, dtype=np.float64).reshape(len(self.keys), self.block_size)
        states = {}
        for key, part in zip(self.keys, parts):
            flat = self.states[key].reshape(-1).copy()
            flat[self.free_dofs] = part
            states[key] = flat.reshape(-1, 3)
        return states

    def set_x(self, x: np.ndarray) -> None:
        self.states = self.states_from_x(x)

    # ------------------------------------------------------------------------ problem
    def state_factors(self, key) -> list:
        """Factors on state `key` alone, except temporal ones (exact quadratics, never cached)."""
        return [factor for factor in self.factors if factor.keys == (key,) and not isinstance(factor, TemporalFactor)]

    def replace_state_factors(self, key, factors) -> None:
        """Put `factors` in place of state `key`'s `state_factors` (the estimator re-weights its
        newest state); the state's cached linearisation goes with the old ones."""
        old = self.state_factors(key)
        self.factors = [factor for factor in self.factors if not any(factor is o for o in old)]
        for factor in old:
            self._scattered_hessians.pop(factor, None)
        self._cache.pop(key, None)
        for factor in factors:
            self.add_factor(factor)

    def _relinearize(self, key, state: np.ndarray) -> _StateLinearization:
        nnz = self._pattern_keys.size
        data = np.zeros(nnz + 1)
        gradient = np.zeros(self.dof_count)
        cost = 0.0
        states = {key: state}
        for factor in self.state_factors(key):
            terms = factor.linearize(states)
            cost += terms.cost
            self._accumulate(terms, factor, data, gradient)
        self.relinearizations += 1
        pattern = self._pattern
        block = scipy.sparse.csr_matrix((data[:nnz], pattern.indices, pattern.indptr), shape=pattern.shape)
        return _StateLinearization(state.copy(), data, gradient, cost, block, self.relinearizations)

    def _scattered_hessian(self, factor, matrix) -> np.ndarray:
        """A factor's sparse Hessian as values on the block pattern (nnz + 1,). Kept while the
        factor hands back the same matrix object: the physics prior's information is one matrix
        for a whole update (factors replace, never modify, a Hessian they returned)."""
        cached = self._scattered_hessians.get(factor)
        if cached is not None and cached[0] is matrix:
            return cached[1]
        csr = scipy.sparse.csr_matrix(matrix)
        scattered = np.bincount(self._csr_slots(csr), weights=csr.data, minlength=self._pattern_keys.size + 1)
        self._scattered_hessians[factor] = (matrix, scattered)
        return scattered

    def _accumulate(self, terms: FactorLinearization, factor, data: np.ndarray | None, gradient: np.ndarray) -> None:
        """Add a factor's terms to a state's gradient and block values `data` (None: gradient only)."""
        for values in terms.gradients.values():
            gradient += values
        for blocks in terms.point_blocks.values():
            gradient += np.bincount(self._triangle_dofs[blocks.triangle].reshape(-1),
                                    weights=blocks.gradient.reshape(-1), minlength=self.dof_count)
        for blocks in terms.element_blocks.values():
            gradient += np.bincount(self._tetrahedron_dofs[blocks.tetrahedron].reshape(-1),
                                    weights=blocks.gradient.reshape(-1), minlength=self.dof_count)
        if data is None:
            return
        for matrix in terms.hessians.values():
            data += self._scattered_hessian(factor, matrix)
        for value in terms.identity_terms.values():
            data[self._diagonal_index] += value
        for blocks in terms.point_blocks.values():
            if blocks.hessian is not None:
                slots = self._triangle_slots[blocks.triangle].reshape(-1)
                data += np.bincount(slots, weights=blocks.hessian.reshape(-1), minlength=self._pattern_keys.size + 1)
        for blocks in terms.element_blocks.values():
            if blocks.hessian is not None:
                dofs = self._tetrahedron_dofs[blocks.tetrahedron]
                slots = self._slots(np.repeat(dofs, 12, axis=1), np.tile(dofs, (1, 12))).reshape(-1)
                data += np.bincount(slots, weights=blocks.hessian.reshape(-1), minlength=self._pattern_keys.size + 1)

    def _model(self, cached: _StateLinearization, state: np.ndarray):
        """(cost, gradient (3N,)) of the cached quadratic at `state`; the last evaluation is
        kept (LM's trial cost and its convergence test ask at one x)."""
        if cached.model_at is not None and np.array_equal(cached.model_at[0], state):
            return cached.model_at[1], cached.model_at[2]
        delta = (state - cached.x_lin).reshape(-1)
        free_delta = delta[self.free_dofs]
        product = np.zeros(self.dof_count)
        product[self.free_dofs] = cached.block @ free_delta
        cost = cached.cost + float(cached.gradient @ delta) + 0.5 * float(free_delta @ product[self.free_dofs])
        gradient = cached.gradient + product
        cached.model_at = (state.copy(), cost, gradient)
        return cost, gradient

    def _moved(self, cached: _StateLinearization, state: np.ndarray) -> float:
        """RMS vertex displacement since the linearisation (a max would let the few vertices at
        sharp surface edges, where the closest triangle flips, re-linearise every state)."""
        return float(np.sqrt(np.mean(np.sum((state - cached.x_lin) ** 2, axis=1))))

    def _outdated(self, key, cached: _StateLinearization, state: np.ndarray) -> bool:
        """Whether `linearize` must re-linearise state `key` (its cached quadratic stands in otherwise)."""
        threshold = 0.0 if key in self.exact_keys else self.relinearize_threshold
        return (cached.rebased and threshold == 0.0) or self._moved(cached, state) > threshold

    def _window_geometry(self, states: dict) -> tuple[np.ndarray, np.ndarray]:
        """Signed volumes and longest edges at corner 0, each (W, M), of the window's states.
        Each state's last result is kept: LM asks at one x repeatedly (`step_fraction` at every
        proposal from x), and a new update finds its older states where the last one left them."""
        kept_values = [None] * len(self.keys)
        missing = []
        for t, key in enumerate(self.keys):
            kept = self._state_volumes.get(key)
            if kept is not None and np.array_equal(kept[0], states[key]):
                kept_values[t] = kept[1]
            else:
                missing.append(t)
        if missing:
            volumes, edges = self._volumes_and_edges(np.stack([states[self.keys[t]] for t in missing]))
            for t, values, longest in zip(missing, volumes, edges):
                key = self.keys[t]
                self._state_volumes[key] = (states[key].copy(), (values, longest))
                kept_values[t] = (values, longest)
        return np.stack([v[0] for v in kept_values]), np.stack([v[1] for v in kept_values])

    def _window_volumes(self, states: dict) -> np.ndarray:
        """Signed volumes (W, M) of the window's states (kept per state, see _window_geometry)."""
        return self._window_geometry(states)[0]

    def _cross_factors(self) -> list:
        return [factor for factor in self.factors if len(factor.keys) != 1 or isinstance(factor, TemporalFactor)]

    def cost(self, x: np.ndarray) -> float:
        """Total cost: exact for active states and temporal factors, cached model for the rest."""
        states = self.states_from_x(x)
        total = 0.0
        for key in self.keys:
            cached = self._cache.get(key)
            if key in self._active or cached is None:
                total += sum(factor.cost(states) for factor in self.state_factors(key))
            else:
                total += self._model(cached, states[key])[0]
        total += sum(factor.cost(states) for factor in self._cross_factors())
        return float(total)

    def gradient(self, x: np.ndarray):
        """(gradient over the free dofs, cost) at x, as `linearize` gives them, without new
        Hessians: a state `linearize` would re-linearise gets its exact cost and gradient and
        its cached quadratic re-based at x (cost and gradient exact there, Hessian kept, same
        revision). LM calls this after an accepted step to test for convergence before paying
        for Hessians it may not need. A re-based state whose threshold is 0 (the estimator's
        newest, or exact LM) is re-linearised by the next `linearize`; the others follow the
        threshold rule from x, their quadratic exact to first order there (so the estimator's
        next update does not re-linearise the state it just finished)."""
        states = self.states_from_x(x)
        gradient = np.zeros((len(self.keys), self.dof_count))
        cost = 0.0
        position = {key: t for t, key in enumerate(self.keys)}
        for t, key in enumerate(self.keys):
            cached = self._cache.get(key)
            if cached is None:
                cached = self._cache[key] = self._relinearize(key, states[key])
                self._active.add(key)
            elif self._outdated(key, cached, states[key]):
                cached.cost, cached.gradient = 0.0, np.zeros(self.dof_count)
                for factor in self.state_factors(key):  # cached.data (the Hessian) is kept
                    terms = factor.linearize({key: states[key]}, hessian=False)
                    cached.cost += terms.cost
                    self._accumulate(terms, factor, None, cached.gradient)
                cached.x_lin = states[key].copy()
                cached.rebased = True
                cached.model_at = None
                self._active.add(key)
            cost_t, gradient[t] = self._model(cached, states[key])
            cost += cost_t
        for factor in self._cross_factors():
            terms = factor.linearize(states, hessian=False)
            cost += terms.cost
            for key, values in terms.gradients.items():
                gradient[position[key]] += values
        return gradient[:, self.free_dofs].reshape(-1), float(cost)

    def linearize(self, x: np.ndarray):
        """(WindowSystem of J^T W J, gradient J^T W r over the free dofs, cost) at x.

        The system's blocks are the states' cached linearisations themselves (not copied: at
        organ scale, W copies of 1.4M values cost ~60 ms an update); the temporal factors' terms
        go into its diagonal shift."""
        states = self.states_from_x(x)
        window = len(self.keys)
        gradient = np.zeros((window, self.dof_count))
        couplings = np.zeros(max(window - 1, 0))
        coupling_diagonal = np.zeros(window)
        cost = 0.0
        self._active = set()
        blocks, revisions = [], []
        for t, key in enumerate(self.keys):
            cached = self._cache.get(key)
            if cached is None or self._outdated(key, cached, states[key]):
                cached = self._cache[key] = self._relinearize(key, states[key])
                self._active.add(key)
                cost += cached.cost
                gradient[t] = cached.gradient
            else:
                model_cost, model_gradient = self._model(cached, states[key])
                cost += model_cost
                gradient[t] = model_gradient
            blocks.append(cached.block)
            revisions.append(cached.revision)
        position = {key: t for t, key in enumerate(self.keys)}
        for factor in self._cross_factors():
            terms = factor.linearize(states)
            cost += terms.cost
            for key, values in terms.gradients.items():
                gradient[position[key]] += values
            for (key_i, key_j), value in terms.identity_terms.items():
                t, s = position[key_i], position[key_j]
                if t == s:
                    coupling_diagonal[t] += value
                elif abs(t - s) == 1:
                    couplings[min(t, s)] += value
                else:
                    raise FactorError("identity terms may only couple consecutive states")
            if terms.hessians or terms.point_blocks or terms.element_blocks:
                raise FactorError("factors across states must give scaled-identity terms only")
        shift = np.repeat(coupling_diagonal[:, None], self.block_size, axis=1) if coupling_diagonal.any() else None
        system = WindowSystem(blocks, couplings, list(self.keys), self._diagonal_index, coupling_diagonal,
                              self._vertex_block_slots, revisions, shift)
        # Scattered Hessians serve states that get re-linearised; keep only those of this round's
        # (memory stays bounded by the active states, also in growing mode).
        self._scattered_hessians = {factor: kept for factor, kept in self._scattered_hessians.items()
                                    if factor.keys[0] in self._active}
        return system, gradient[:, self.free_dofs].reshape(-1), cost

    def _volumes_and_edges(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed tetrahedron volumes and the longest of the three edges at corner 0, of a state
        (N, 3) -> (M,) each, or of states (W, N, 3) -> (W, M) each."""
        # Coordinate-major triple product: ~2x faster than np.cross + einsum on (W, M, 3, 3) corners.
        x, y, z = np.moveaxis(state, -1, 0)
        first = self.tetrahedra[:, 0]

        def edge(coordinate, corner):
            return coordinate[..., self.tetrahedra[:, corner]] - coordinate[..., first]

        ux, uy, uz = edge(x, 1), edge(y, 1), edge(z, 1)
        vx, vy, vz = edge(x, 2), edge(y, 2), edge(z, 2)
        wx, wy, wz = edge(x, 3), edge(y, 3), edge(z, 3)
        volumes = ((uy * vz - uz * vy) * wx + (uz * vx - ux * vz) * wy + (ux * vy - uy * vx) * wz) / 6.0
        longest = np.sqrt(np.maximum.reduce([ux * ux + uy * uy + uz * uz, vx * vx + vy * vy + vz * vz,
                                             wx * wx + wy * wy + wz * wz]))
        return volumes, longest

    def _signed_volumes(self, state: np.ndarray) -> np.ndarray:
        """Signed tetrahedron volumes of a state (N, 3) -> (M,), or of states (W, N, 3) -> (W, M)."""
        return self._volumes_and_edges(state)[0]

    def step_fraction(self, x: np.ndarray, step: np.ndarray) -> float:
        """The largest alpha in [0, 1] such that every tetrahedron with a positive volume at x
        keeps at least MIN_VOLUME_RATIO_PER_STEP of it at x + alpha * step (LM's inversion guard).

        Along the step a volume is the cubic 6 V(alpha) = (u + a du) x (v + a dv) . (w + a dw) in
        the edge vectors at corner 0. With L the longest of u, v, w and delta the largest move of
        the element's corners, |6 V(alpha) - 6 V(0)| <= (L + 2 delta)^3 - L^3, which clears most
        elements at once; for the rest the cubic's first crossing of the margin is bracketed on a
        grid of alpha and refined by bisection, and the result is checked on exact volumes."""
        states = self.states_from_x(x)
        volumes, longest = self._window_geometry(states)
        moves = np.zeros((len(self.keys), self.dof_count))
        moves[:, self.free_dofs] = np.asarray(step, dtype=np.float64).reshape(len(self.keys), self.block_size)
        moves = moves.reshape(len(self.keys), -1, 3)
        largest = np.sqrt(np.einsum("wni,wni->wn", moves, moves))[:, self.tetrahedra].max(axis=2)  # (W, M)
        margin = MIN_VOLUME_RATIO_PER_STEP * 6.0 * volumes
        candidates = (volumes > 0.0) & ((longest + 2.0 * largest) ** 3 - longest**3 >= 6.0 * volumes - margin)
        if not candidates.any():
            return 1.0
        state_index, element = np.nonzero(candidates)
        window = np.stack([states[key] for key in self.keys])
        corners = window[state_index[:, None], self.tetrahedra[element]]      # (P, 4, 3)
        corner_moves = moves[state_index[:, None], self.tetrahedra[element]]  # (P, 4, 3)
        u, v, w = (corners[:, k] - corners[:, 0] for k in (1, 2, 3))
        du, dv, dw = (corner_moves[:, k] - corner_moves[:, 0] for k in (1, 2, 3))

        def triple(a, b, c):
            return np.einsum("pi,pi->p", np.cross(a, b), c)

        coefficients = np.stack([
            triple(u, v, w),
            triple(du, v, w) + triple(u, dv, w) + triple(u, v, dw),
            triple(du, dv, w) + triple(du, v, dw) + triple(u, dv, dw),
            triple(du, dv, dw),
        ])  # (4, P): 6 V(alpha) = sum_k c_k alpha^k
        bound = margin[candidates]
        grid = np.linspace(0.0, 1.0, _STEP_FRACTION_GRID + 1)[1:]
        crossed = np.polynomial.polynomial.polyval(grid[:, None], coefficients, tensor=False) < bound  # (G, P)
        hit = crossed.any(axis=0)
        if not hit.any():
            return 1.0
        first = np.argmax(crossed[:, hit], axis=0)
        low, high = np.where(first > 0, grid[first - 1], 0.0), grid[first]
        chosen, chosen_bound = coefficients[:, hit], bound[hit]
        for _ in range(_STEP_FRACTION_BISECTIONS):
            middle = 0.5 * (low + high)
            bad = np.polynomial.polynomial.polyval(middle, chosen, tensor=False) < chosen_bound
            high, low = np.where(bad, middle, high), np.where(bad, low, middle)
        fraction = float(low.min())
        positive = volumes > 0.0
        for _ in range(_STEP_FRACTION_HALVINGS):
            trial = x + fraction * np.asarray(step, dtype=np.float64)
            trial_volumes = self._window_volumes(self.states_from_x(trial))
            if not np.any(positive & (6.0 * trial_volumes < margin)):
                return fraction
            fraction *= 0.5
        return 0.0
