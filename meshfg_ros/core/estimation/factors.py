"""Factors of the mesh factor graph: residual, Jacobian, cost and Gauss-Newton terms.

A factor touches the states (N, 3) of one or two keys and gives its residual r, its
Jacobians dr/dX_key (sparse, w.r.t. the flattened vertex positions x0 y0 z0 x1 ...), its cost
and its contribution to the Gauss-Newton normal equations. The measurement factor's noise
model and robust kernel are separate objects passed to it (noise.py); the physics prior's
information depends on the state it is evaluated at, so the prior evaluates and holds it, and
the temporal factor's is a constant I / sigma^2.

  PhysicsPriorFactor     r = Xhat_t - X_t,  information Lambda = scale * K(X_t) + ridge I
  VolumeBarrierFactor    keeps every tetrahedron of a state away from flat or inverted
  PointToSurfaceFactor   r_k = (a x_a + b x_b + c x_c) - m_k on the closest surface triangle
  TemporalFactor         r = X_t - X_{t-1} (or - an anchor state), information I / sigma^2

The graph that holds the states and assembles these terms is `FactorGraph` (factor_graph.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
import scipy.sparse
from numba.types import boolean, float64, int64

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.geometry.closest_point import (
    REGION_FACE,
    Association,
    ClosestPointIndex,
    project_onto_mesh_triangles,
    projection_jacobian,
    triangle_corners,
)
from meshfg_ros.core.geometry.kernel_types import read_only
from meshfg_ros.core.geometry.mesh import ElementVolumes, cross, cross3, dot3
from meshfg_ros.core.estimation.noise import IdentityNoise, PointNoise, RobustKernel

__all__ = [
    "BARRIER_VOLUME_RATIO",
    "ElementBlocks",
    "Factor",
    "FactorError",
    "FactorLinearization",
    "PhysicsPriorFactor",
    "PointBlocks",
    "PointToSurfaceFactor",
    "TemporalFactor",
    "VolumeBarrierFactor",
    "checked_state",
    "prior_scale",
]

# The physics prior's volume barrier (VolumeBarrierFactor) acts on tetrahedra below this
# fraction of their volume in the prior's mean (the prediction): far below any correction a
# nearly incompressible tissue needs, so it never moves a plausible estimate, while it keeps
# the optimum itself from flattening or inverting elements.
BARRIER_VOLUME_RATIO = 0.5
# The trials' closest-triangle searches answer from the surface grid the points within this many
# times the farthest point's distance at the state of their given association (the prediction;
# LM's steps move the surface by a fraction of that, but the grid's reach is held to one edge);
# the grid's cells around them answer the few beyond (closest_point.py, `scan_beyond_reach`).
TRIAL_REACH = 1.25
# A point's Gauss-Newton term (_distance_hessians) is weighted by the second
# derivative of its robust cost along its distance, w (rho' + 2 s rho'') (RobustKernel.curvature),
# but by at least this share of its IRLS weight w rho'. The IRLS weight overstates the curvature
# (Cauchy at 2.4 sigma, a point one sigma off: 0.85 w against 0.60 w), so LM's steps stop short
# and its decrement test sees less of the remaining decrease than there is; beyond about 0.6
# kernel scales the true curvature falls below half the IRLS weight and turns negative, and
# there the floor keeps the model convex (without it, steps chase the far points of the first
# updates: 5.2 LM iterations per organ-scale update instead of 3.8, up to 10). Measurements in
# docs/design-notes.md ("Curvature of the robust cost").
CURVATURE_FLOOR = 0.5


class FactorError(ValueError):
    """Bad factor input: wrong shapes, unknown keys, non-finite values."""


def checked_state(array, vertex_count: int, what: str) -> np.ndarray:
    """`array` as a finite float64 state (vertex_count, 3), or FactorError naming `what`."""
    state = np.asarray(array, dtype=np.float64)
    if state.shape != (vertex_count, 3):
        raise FactorError(f"{what} must have shape ({vertex_count}, 3), got {state.shape}")
    if not np.all(np.isfinite(state)):
        raise FactorError(f"{what} contains NaN or infinite values")
    return state


@dataclass
class PointBlocks:
    """Normal-equation terms of point-to-triangle residuals on their triangles' 9 coordinates:
    gradient (P, 9) = w J^T r per point, on the surface triangles `triangle` (P,); hessian
    (H, 81) Gauss-Newton terms (9x9, row major) on the triangles `hessian_triangle` (H,), where
    a row may sum the terms of several points on one triangle. hessian and hessian_triangle are
    None when only the gradient was asked for."""

    triangle: np.ndarray
    gradient: np.ndarray
    hessian: np.ndarray | None = None
    hessian_triangle: np.ndarray | None = None


@dataclass
class FactorLinearization:
    """A factor's cost and normal-equation terms at a linearisation point.

    gradients[key] (3N,) = J_key^T W r; hessians[(key, key)] csr (3N, 3N) = J^T W J;
    point_blocks[key] per-point terms (measurements); element_blocks[key] per-tetrahedron terms
    (the volume barrier). An identity_blocks factor gives its c * I blocks by `identity_terms`.
    """

    cost: float
    gradients: dict = field(default_factory=dict)
    hessians: dict = field(default_factory=dict)
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
    """Base: keys (the state keys it touches), residual, Jacobians, cost and linearisation.

    `identity_blocks` declares the structure of the factor's Gauss-Newton terms, which decides
    how a FactorGraph assembles it:
      False (default)  a factor on one state (one key) whose terms (Hessians, point or element
                       blocks) go into that state's block; the graph linearises it with the
                       state's other such factors and caches the result per state.
      True             terms that are c * I blocks on and between the states of its keys
                       (`identity_terms`, constant in X: an exact quadratic); the graph
                       evaluates it directly in every cost and linearisation and puts the
                       blocks into the window system's diagonal and its couplings between
                       consecutive states.
    """

    keys: tuple = ()
    identity_blocks: bool = False

    def identity_terms(self) -> dict:
        """{(key_i, key_j): c}, the c * I blocks of an identity_blocks factor (i == j: on the
        diagonal block of state i; i != j: between states i and j)."""
        raise NotImplementedError

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

    @classmethod
    def cost_batch(cls, factors: list, states: dict) -> list[float]:
        """`cost` of each of `factors` (all of this class) at `states`. A FactorGraph evaluates
        the factors of one class on all the states it evaluates at once; this version takes
        them one by one, a class whose per-call overhead outweighs its per-state work on small
        meshes vectorises across them."""
        return [factor.cost(states) for factor in factors]

    @classmethod
    def linearize_batch(cls, factors: list, states: dict, hessian: bool = True) -> list[FactorLinearization]:
        """`linearize` of each of `factors` (all of this class) at `states`; see cost_batch."""
        return [factor.linearize(states, hessian) for factor in factors]


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

    model: an ElasticModel (core.physics.fem); kind / spd_projection select K. K depends on X and is
    treated as the information matrix, not differentiated. It is evaluated at the first
    linearisation and kept until `invalidate_information()` (the estimator calls it once per
    update, see estimator.py), so each update optimises one fixed objective. `cost` uses the
    same Lambda, so a trial step is judged on the same quadratic as its model. The tiny ridge fixes the 6 rigid-body modes a free body's K leaves without
    information. Raw neo-Hookean K may be indefinite: then Lambda is too, and the solver's
    damping must make the step system positive definite.
    """

    def __init__(self, key, predicted, model, kind: str = "corotational", spd_projection: bool = False,
                 scale: float = 1.0, ridge: float = 0.0):
        self.keys = (key,)
        self.model = model
        self.predicted = checked_state(predicted, model.vertex_count, "predicted state")
        self.kind = kind
        self.spd_projection = bool(spd_projection)
        self.scale = float(scale)
        self.ridge = float(ridge)
        self._information: scipy.sparse.csr_matrix | None = None
        self.information_state: np.ndarray | None = None  # where Lambda was last evaluated
        self._weighted_kept: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (state, r, Lambda r)

    def information(self, state: np.ndarray) -> scipy.sparse.csr_matrix:
        """Lambda, evaluated at `state` (N, 3) when there is none since `invalidate_information`."""
        if self._information is None:
            # On K's own pattern, the ridge added in place: one pattern for every update, whose
            # positions in the window's block pattern FactorGraph then maps once.
            information = self.scale * self.model.stiffness(state, kind=self.kind, spd_projection=self.spd_projection)
            if self.ridge:
                information.data[self.model.diagonal_positions] += self.ridge
            self._information = information
            self.information_state = np.array(state, dtype=np.float64)
        return self._information

    def invalidate_information(self) -> None:
        """Make the next linearisation re-evaluate K at its linearisation point."""
        if self.kind != "linear":
            self._information = None
            self._weighted_kept = None

    def _weighted(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(r, Lambda r) at `state`, kept for the last state: Levenberg-Marquardt evaluates the
        states a step left alone (PCGSolver's left-out blocks) again at every trial."""
        kept = self._weighted_kept
        if kept is not None and np.array_equal(kept[0], state):
            return kept[1], kept[2]
        information = self.information(state)
        r = (self.predicted - state).reshape(-1)
        weighted = information @ r
        self._weighted_kept = (np.array(state, dtype=np.float64), r, weighted)
        return r, weighted

    @classmethod
    def cost_batch(cls, factors, states):
        return [cost for group in worker_threads.run_parts(_prior_costs, [(group, states) for group in _prior_groups(factors)])
                for cost in group]

    @classmethod
    def linearize_batch(cls, factors, states, hessian=True):
        return [linearization for group in worker_threads.run_parts(
            _prior_linearizations, [(group, states, hessian) for group in _prior_groups(factors)]) for linearization in group]

    def residual(self, states):
        return (self.predicted - states[self.keys[0]]).reshape(-1)

    def jacobians(self, states):
        size = 3 * self.model.vertex_count
        return {self.keys[0]: -scipy.sparse.identity(size, format="csr")}

    def cost(self, states):
        r, weighted = self._weighted(states[self.keys[0]])
        return 0.5 * float(r @ weighted)

    def linearize(self, states, hessian=True):
        key = self.keys[0]
        information = self.information(states[key])
        r, weighted = self._weighted(states[key])
        return FactorLinearization(
            cost=0.5 * float(r @ weighted),
            gradients={key: -weighted},
            hessians={(key, key): information} if hessian else {},
        )


# The physics priors of a window are evaluated on the worker threads (core/worker_threads.py),
# a share of the states each, when each thread gets at least this many unknowns: a product with
# a 10,648-vertex state's Lambda (32k unknowns, 1.3 million entries) takes 0.8 ms, a hand-off to
# a thread about 0.1 ms.
PARALLEL_MIN_PRIOR_DOFS = 20_000


def _prior_groups(factors: list) -> list[list]:
    dofs = sum(3 * factor.model.vertex_count for factor in factors)
    return [list(group) for group in worker_threads.split(factors, dofs // PARALLEL_MIN_PRIOR_DOFS)]


def _prior_costs(factors: list, states: dict) -> list[float]:
    return [factor.cost(states) for factor in factors]


def _prior_linearizations(factors: list, states: dict, hessian: bool) -> list:
    return [factor.linearize(states, hessian) for factor in factors]


def _six_volume_gradients(corners: np.ndarray) -> np.ndarray:
    """Gradient (P, 12) of 6 V w.r.t. the corners (P, 4, 3) of tetrahedra: u x v etc."""
    u, v, w = (corners[:, k] - corners[:, 0] for k in (1, 2, 3))
    by_corner = np.stack([cross(v, w), cross(w, u), cross(u, v)], axis=1)  # d(6V)/dx_1..3
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

    def __init__(self, key, tetrahedra, reference_volumes, stiffness, threshold: float = BARRIER_VOLUME_RATIO,
                 element_volumes: ElementVolumes | None = None):
        self.keys = (key,)
        self.tetrahedra = np.asarray(tetrahedra, dtype=np.int64)
        if element_volumes is None:
            element_volumes = ElementVolumes(self.tetrahedra)
        elif not np.array_equal(element_volumes.tetrahedra, self.tetrahedra):
            raise FactorError("element_volumes belongs to other tetrahedra")
        self.element_volumes = element_volumes
        self.reference_volumes = np.asarray(reference_volumes, dtype=np.float64)
        self.stiffness = np.broadcast_to(np.asarray(stiffness, dtype=np.float64), self.reference_volumes.shape).copy()
        if not (0.0 < threshold < 1.0):
            raise FactorError(f"barrier threshold must lie in (0, 1), got {threshold}")
        if not (np.all(self.reference_volumes > 0.0) and np.all(np.isfinite(self.stiffness)) and np.all(self.stiffness >= 0.0)):
            raise FactorError("barrier needs positive reference volumes and finite, non-negative stiffness")
        self.threshold = float(threshold)

    def _ratios(self, state: np.ndarray) -> np.ndarray:
        """J_e at `state` (its volumes from, or kept in, element_volumes)."""
        return self._batch_ratios([self], {self.keys[0]: state})[0]

    @staticmethod
    def _batch_ratios(factors: list, states: dict) -> list[np.ndarray]:
        """Each factor's J_e at `states`; the volumes of the factors that share an
        element_volumes are looked up, or made, in one call."""
        groups: dict = {}
        for index, factor in enumerate(factors):
            groups.setdefault(id(factor.element_volumes), []).append(index)
        ratios: list = [None] * len(factors)
        for indices in groups.values():
            volumes, _ = factors[indices[0]].element_volumes.of(states, [factors[i].keys[0] for i in indices])
            for index, state_volumes in zip(indices, volumes):
                ratios[index] = state_volumes / factors[index].reference_volumes
        return ratios

    @classmethod
    def cost_batch(cls, factors, states):
        return [factor._cost(ratio) for factor, ratio in zip(factors, cls._batch_ratios(factors, states))]

    @classmethod
    def linearize_batch(cls, factors, states, hessian=True):
        return [factor._linearize(states[factor.keys[0]], ratio, hessian)
                for factor, ratio in zip(factors, cls._batch_ratios(factors, states))]

    def _psi(self, ratio: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """psi, psi', psi'' at ratios in (0, J_c)."""
        q = self.threshold / ratio
        return (q - 1.0) ** 2, -2.0 * (q - 1.0) * q / ratio, (2.0 * q * q + 4.0 * (q - 1.0) * q) / ratio**2

    def cost(self, states):
        return self.cost_batch([self], states)[0]

    def _cost(self, ratio: np.ndarray) -> float:
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

    def _terms(self, state, ratio):
        """(active tetrahedra, cost, psi', psi'', dJ (P, 12)) at `state`, whose J_e are `ratio`."""
        active = np.flatnonzero((ratio > 0.0) & (ratio < self.threshold))
        if not active.size:  # every plausible state
            return active, 0.0, np.zeros(0), np.zeros(0), np.zeros((0, 12))
        psi, slope, curvature = self._psi(ratio[active])
        six_volume_gradient = _six_volume_gradients(np.asarray(state, dtype=np.float64)[self.tetrahedra[active]])
        ratio_gradient = six_volume_gradient / (6.0 * self.reference_volumes[active])[:, None]
        return active, float(self.stiffness[active] @ psi), slope, curvature, ratio_gradient

    def jacobians(self, states):
        key = self.keys[0]
        state = states[key]
        active, _, slope, _, ratio_gradient = self._terms(state, self._ratios(state))
        values = self.residual(states)[active]
        scale = np.where(values > 0.0, self.stiffness[active] * slope / np.maximum(values, 1e-300), 0.0)
        columns = (3 * self.tetrahedra[active][:, :, None] + np.arange(3)).reshape(-1, 12)
        rows = np.broadcast_to(active[:, None], columns.shape)
        matrix = scipy.sparse.csr_matrix(((scale[:, None] * ratio_gradient).reshape(-1), (rows.reshape(-1), columns.reshape(-1))),
                                         shape=(len(self.tetrahedra), state.size))
        return {key: matrix}

    def linearize(self, states, hessian=True):
        return self.linearize_batch([self], states, hessian)[0]

    def _linearize(self, state, ratio, hessian):
        key = self.keys[0]
        active, cost, slope, curvature, ratio_gradient = self._terms(state, ratio)
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
    graph, or (anchor) a constant state: one that left the window or the initial mesh. Its
    Gauss-Newton terms are multiples of the identity (identity_blocks)."""

    identity_blocks = True

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

    def identity_terms(self):
        terms = {(self.key, self.key): self.weight}
        if self.anchor is None:
            terms[(self.previous_key, self.previous_key)] = self.weight
            terms[(self.previous_key, self.key)] = -self.weight
        return terms

    def linearize(self, states, hessian=True):
        r = self.residual(states)
        out = FactorLinearization(cost=0.5 * self.weight * float(r @ r))
        out.gradients[self.key] = self.weight * r
        if self.anchor is None:
            out.gradients[self.previous_key] = -self.weight * r
        return out


@numba.njit((read_only(float64, 2), read_only(int64, 2), read_only(int64, 1), read_only(float64, 2),
             read_only(float64, 1), read_only(boolean, 1)), cache=True, boundscheck=True, error_model="numpy")
def _face_terms(vertices, triangles, triangle, barycentric, weight, face):
    """The face points' Gauss-Newton terms summed per triangle: (triangles seen (H,), terms
    (H, 81)), row h (sum_k w_k beta_k beta_k^T) (x) n n^T of triangle seen[h] with unit normal n
    (NaN for a degenerate triangle, whose terms stay in its own row), entry (3 i + r, 3 l + m)
    the moment (i, l) times n_r n_m. The moments' upper triangle is summed and mirrored, so
    each term is exactly symmetric.

    Compiled (numba): as numpy passes (a bincount per moment, gathers for the Kronecker
    product) its time on a window's clouds is mostly fixed cost (docs/design-notes.md, "Compiled kernels"); the terms are
    bit-identical."""
    moments = np.zeros((triangles.shape[0], 6))
    seen = np.zeros(triangles.shape[0], dtype=np.bool_)
    for k in range(triangle.shape[0]):
        if face[k]:
            t = triangle[k]
            seen[t] = True
            entry = 0
            for i in range(3):
                weighted = weight[k] * barycentric[k, i]
                for l in range(i, 3):
                    moments[t, entry] += weighted * barycentric[k, l]
                    entry += 1
    index = np.flatnonzero(seen)
    terms = np.empty((index.size, 81))
    upper = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
    for h in range(index.size):
        t = index[h]
        a, b, c = vertices[triangles[t, 0]], vertices[triangles[t, 1]], vertices[triangles[t, 2]]
        normal = cross3(b - a, c - a)
        normal /= np.sqrt(dot3(normal, normal))
        for i in range(3):
            for l in range(3):
                moment = moments[t, upper[i, l]]
                for r in range(3):
                    for m in range(3):
                        terms[h, (3 * i + r) * 9 + 3 * l + m] = moment * (normal[r] * normal[m])
    return index, terms


def _distance_hessians(parts: list, states: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """Gauss-Newton terms of point factors' robust costs, (triangles (H,), terms (H, 81)) per
    part (factor, association, curvature, irls): `curvature` (K,) weights a point inside its
    face, `irls` (K,) one on an edge or a vertex.

    A point projected inside its face has d = n.(m - q): its Gauss-Newton term is
    c (beta (x) n)(beta (x) n)^T, since d d / d x_i = -beta_i n (the envelope theorem, as for
    the gradient). Gauss-Newton on the vector r = q - m instead adds d^2 (dn/dX)^T (dn/dX),
    a stiffness against turning the face that the distance does not have; at a window's
    optimum the prior holds the surface off the data, the d keep a systematic part and that
    term makes Levenberg-Marquardt's steps stop short (on the airway scene the vector form's
    curvature along a step is 1.35 times the true one, and LM converges linearly, at about
    half the remaining decrease per iteration). The face points of one triangle share its n,
    so their terms sum to (sum_k c_k beta_k beta_k^T) (x) n n^T: one row per triangle,
    made from 3x3 sums, instead of one 9x9 per point (a cloud puts several points on each
    triangle it sees). A point projected onto an edge or a vertex keeps the vector form,
    which is exact there (distance to a line or a point), with its IRLS weight (a few
    points, weighted the conservative way), in a row of its own.

    The parts' states are stacked into one mesh (vertex and triangle indices offset), so that
    the edge and vertex points of all states take one numpy pass (projection_jacobian), whose
    fixed cost is most of its time on a window's few such points."""
    factors = [factor for factor, *_ in parts]
    vertex_offsets = np.cumsum([0] + [factor.vertex_count for factor in factors])
    triangle_offsets = np.cumsum([0] + [len(factor.triangles) for factor in factors])
    vertices = np.concatenate([states[factor.keys[0]] for factor in factors])
    triangles = np.concatenate([factor.triangles + offset for factor, offset in zip(factors, vertex_offsets)])
    points = np.concatenate([factor.points for factor in factors])
    triangle = np.concatenate([association.triangle + offset
                               for (_, association, *_), offset in zip(parts, triangle_offsets)])
    barycentric = np.concatenate([association.barycentric for _, association, *_ in parts])
    region = np.concatenate([association.region for _, association, *_ in parts])
    curvature = np.concatenate([part[2] for part in parts])
    irls = np.concatenate([part[3] for part in parts])

    face = region == REGION_FACE
    index, terms = _face_terms(vertices, triangles, triangle.astype(np.int64, copy=False), barycentric,
                               curvature.astype(np.float64, copy=False), face)
    if not face.all():
        other = ~face
        jacobian = projection_jacobian(points[other], *triangle_corners(vertices, triangles, triangle[other]),
                                       region[other])
        # Batched matmul: 5x faster than the equivalent einsum on (K, 3, 9) stacks.
        other_terms = ((jacobian * irls[other][:, None, None]).transpose(0, 2, 1) @ jacobian).reshape(-1, 81)
        index, terms = np.concatenate([index, triangle[other]]), np.concatenate([terms, other_terms])
    if len(parts) == 1:
        return [(index, terms)]
    owner = np.searchsorted(triangle_offsets, index, side="right") - 1
    return [(index[owner == s] - triangle_offsets[s], terms[owner == s]) for s in range(len(parts))]


class PointToSurfaceFactor(Factor):
    """Measured points against the closest triangle of the surface of state `key`.

    r_k = q_k - m_k with q_k the closed-form closest point (closest_point.py) on the closest
    surface triangle; its Jacobian is the exact derivative of that projection (barycentrics
    included). Association: the closest triangle is re-found exactly (closest_point.py's AABB
    tree) whenever the residual is evaluated at a new state (every cost evaluation and
    linearisation), so the cost is the true point-to-surface distance, continuous in X, and
    LM's gain ratio compares like with like. `freeze_association` pins each point to its
    current triangle (for cross-checks with other solvers).

    The factor takes the points (K, 3) and their noise model as they are: which points of a
    cloud it gets, and their noise, is the measurement front end's choice
    (measurement_selection.py). `association_at`, (vertices (N, 3), the points' Association
    there) where the caller has it, answers the first query at those vertices, and sets how far
    from the surface the trials' searches expect the points: the surface grid answers those
    within TRIAL_REACH times the farthest one's distance, and the few beyond from the cells
    around them (closest_point.py).
    Cost: 0.5 sum_k w_k rho(|r_k|^2), w_k = 1/sigma_k^2, rho the robust kernel (identity
    without one); its gradient carries the IRLS weights w_k rho'(|r_k|^2), its Gauss-Newton
    terms the curvature along each point's distance (see CURVATURE_FLOOR).
    """

    def __init__(self, key, points, surface_triangles, vertex_count: int, noise: PointNoise | None = None,
                 robust: RobustKernel | None = None, association_at: tuple[np.ndarray, Association] | None = None):
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise FactorError(f"points must have shape (K, 3), got {points.shape}")
        if not np.all(np.isfinite(points)):
            raise FactorError("points contain NaN or infinite values")
        self.keys = (key,)
        self.points = points
        self.triangles = np.asarray(surface_triangles, dtype=np.int64)
        self.vertex_count = int(vertex_count)
        self.noise = IdentityNoise() if noise is None else noise
        self.weights = self.noise.point_weights(len(points))  # validates per-point sizes
        self.robust = robust
        self._frozen_triangle: np.ndarray | None = None
        # The last two (vertices, association) pairs: LM linearises where the selection or a trial's
        # cost associated, and after an extrapolated trial it did not take, at the trial before it.
        self._associations: list = []
        self._reach = None
        if association_at is not None:
            vertices, association = association_at
            vertices = checked_state(vertices, self.vertex_count, "association_at's vertices")
            if len(association.triangle) != len(points):
                raise FactorError(f"association_at has {len(association.triangle)} points, the factor {len(points)}")
            # The distance from the surface within which the points lie, with room for LM's steps:
            # the trials' searches answer those points from the surface grid (closest_point.py).
            self._reach = TRIAL_REACH * float(association.distance.max(initial=0.0))
            self._associations = [(vertices.copy(), association)]

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def frozen_triangles(self) -> np.ndarray | None:
        """Triangle index per point pinned by `freeze_association`, or None (free association)."""
        return self._frozen_triangle

    def associate(self, states) -> Association:
        """Closest triangle per point on the surface of the current state (or the frozen ones);
        what was found at the same state by an earlier call serves again."""
        vertices = states[self.keys[0]]
        for kept_vertices, kept in reversed(self._associations):
            if np.array_equal(kept_vertices, vertices):
                return kept
        if self._frozen_triangle is None:
            index = ClosestPointIndex(vertices, self.triangles, self._reach, scan_beyond_reach=True)
            return self._remember(vertices, index.associate(self.points))
        projection = project_onto_mesh_triangles(self.points, vertices, self.triangles, self._frozen_triangle)
        return self._remember(vertices, Association(self._frozen_triangle, projection.closest, projection.barycentric,
                                                    projection.region, np.sqrt(projection.squared_distance)))

    def _remember(self, vertices, association: Association) -> Association:
        """Keep `association` as this factor's at `vertices` (with the one before it)."""
        self._associations = [*self._associations[-1:], (np.array(vertices, dtype=np.float64), association)]
        return association

    def freeze_association(self, states) -> np.ndarray:
        """Pin every point to its closest triangle at `states`; returns those triangle indices."""
        self._frozen_triangle = self.associate(states).triangle.copy()
        self._associations = []
        return self._frozen_triangle

    def _terms(self, association: Association):
        """(residuals (K, 3), their squares (K,), cost, IRLS weights (K,)) of an association."""
        residual = association.closest - self.points
        squared = np.einsum("ij,ij->i", residual, residual)
        if self.robust is None:
            cost_terms, irls = squared, self.weights
        else:
            cost_terms, irls = self.robust.rho(squared), self.weights * self.robust.weight(squared)
        return residual, squared, 0.5 * float(self.weights @ cost_terms), irls

    def _curvature_weights(self, squared, irls) -> np.ndarray:
        """Per-point weights of the Gauss-Newton terms along the distance (see CURVATURE_FLOOR)."""
        if self.robust is None:
            return irls
        return np.maximum(self.weights * self.robust.curvature(squared), CURVATURE_FLOOR * irls)

    def residual(self, states):
        if not self.num_points:
            return np.zeros(0)
        return (self.associate(states).closest - self.points).reshape(-1)

    def _point_jacobians(self, states, association):
        return projection_jacobian(self.points, *triangle_corners(states[self.keys[0]], self.triangles,
                                                                  association.triangle), association.region)

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
        return self._terms(self.associate(states))[2] if self.num_points else 0.0

    def linearize(self, states, hessian=True):
        return self.linearize_batch([self], states, hessian)[0]

    @classmethod
    def linearize_batch(cls, factors, states, hessian=True):
        """`linearize` of each factor; the Hessian terms of all of them are made in one pass
        (_distance_hessians)."""
        measured = [factor for factor in factors if factor.num_points]
        linearizations, parts = [], []
        for factor in measured:
            association = factor.associate(states)
            residual, squared, cost, irls = factor._terms(association)
            # J^T W r without J: q is the closest point of the triangle, so (dq/dX)^T r equals
            # the derivative with the barycentrics held fixed, beta_i r for corner i (envelope
            # theorem; test_jacobian_times_residual_is_the_fixed_barycentric_gradient checks it
            # per region).
            weighted_residual = irls[:, None] * residual
            gradient = (association.barycentric[:, :, None] * weighted_residual[:, None, :]).reshape(-1, 9)
            blocks = PointBlocks(association.triangle, gradient)
            linearizations.append(FactorLinearization(cost=cost, point_blocks={factor.keys[0]: blocks}))
            parts.append((factor, association, factor._curvature_weights(squared, irls), irls))
        if hessian and parts:
            for linearization, (triangle, terms) in zip(linearizations, _distance_hessians(parts, states)):
                blocks = next(iter(linearization.point_blocks.values()))
                blocks.hessian_triangle, blocks.hessian = triangle, terms
        done = iter(linearizations)
        return [next(done) if factor.num_points else FactorLinearization(cost=0.0) for factor in factors]
