"""Elastic simulator for tetrahedral meshes: the predictor of the physics prior.

`ElasticSimulator.predict(previous_state, tool_pose, dt)` moves the tool from its previous pose
to `tool_pose` in `substeps` increments (linear position, slerp orientation) and returns the
tissue near quasi-static equilibrium. The simulator owns the set-up, the tool contact and the
API; how a sub-step moves the tissue is a strategy chosen by SimulatorConfig.solver:

"vbd" (default, `VertexBlockDescent`): quasi-static vertex block descent (Chen et al. 2024)
    on the stable Neo-Hookean energy of Macklin & Mueller 2021,
        Psi = mu/2 (I_C - 3) + lambda'/2 (J - gamma)^2,  lambda' = lambda + mu,  gamma = 1 + mu / lambda'.
    I_C is quadratic and J affine in one vertex, so a vertex's energy is an exact quadratic
    with SPD Hessian V (mu |g|^2 I + lambda' (cof F g)(cof F g)^T): each block solve is exact,
    never raises the energy, and the largest move keeping every incident volume positive is
    closed-form (J is affine along the move). Each iteration is one coloured vertex sweep, then
    a quasi-Newton step with the rest Hessian K0 (factorised once per Poisson ratio, the step
    one ratio behind: RestFactor; constrained at the tool) for
    the smooth, global error that Gauss-Seidel alone removes in O(n^2) sweeps. The fixed point
    is the true equilibrium whatever the iteration count.
"xpbd" (`ExtendedPositionBasedDynamics`, Macklin et al. 2016): damped dynamics; per
    sub-step, Gauss-Seidel over per-element Neo-Hookean constraints with compliance, solved
    as a coupled 2x2 system per element:
        C_D = sqrt(I_C J^(-2/3) - 3),  alpha_D = 1 / (mu V)      (isochoric)
        C_H = J - 1,                   alpha_H = 1 / (kappa V)   (volume, kappa = lambda + 2 mu / 3)
    Both vanish at rest. The split of Macklin & Mueller 2021 (C_D = sqrt(I_C), C_H = J - gamma)
    carries a rest pre-stress whose dropped geometric stiffness makes Gauss-Seidel diverge
    once elements are stiff relative to inertia, i.e. in the quasi-static regime of 1 s steps.
    XPBD restarts its multipliers each sub-step, so with finitely many iterations its fixed
    point is not the equilibrium (the bias shrinks with iterations and sub-steps), and
    settling depends on the physical time scale sqrt(density / E) * size.

lambda' and kappa make both energies linearise to linear elasticity with the Lame parameters
(mu, lambda) of (E, nu): core.physics.fem's linear K0 is their small-strain Hessian. Gauss-Seidel is
sequential, so vertices (vbd) or elements (xpbd) are coloured at set-up and each colour is one
batch (vbd: a compiled loop, xpbd: numpy passes). Runs are bit-reproducible (fixed order, no
threads, no randomness).
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, replace

import numba
import numpy as np
import scipy.sparse
from numba.types import boolean, float64, int64
from scipy.spatial.transform import Rotation, Slerp

import meshfg_ros.core.worker_threads as worker_threads
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.geometry.kernel_types import read_only, writable
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky
from meshfg_ros.core.geometry.mesh import TetMesh, name_elements, signed_volumes
from meshfg_ros.core.inputs.pose_history import InvalidPoseError, as_pose
from meshfg_ros.core.physics.tissue_and_tool import TissueAndTool
from meshfg_ros.core.settings import check_settings, setting

__all__ = [
    "FLAT_VOLUME_RATIO",
    "SOLVERS",
    "SOLVER_STRATEGIES",
    "TOOL_CONTACTS",
    "ElasticSimulator",
    "ElementInversionError",
    "ExtendedPositionBasedDynamics",
    "SimulatorConfig",
    "SimulatorConfigError",
    "SimulatorInputError",
    "SimulatorSolver",
    "VertexBlockDescent",
    "colour_tetrahedra",
    "colour_vertices",
]

TOOL_CONTACTS = ("stick", "slide")
SOLVERS = ("vbd", "xpbd")

# Shape-function gradients of the 4 corners from the rows of Dm^-1 (corner 0: minus their sum).
_CORNER_FROM_EDGES = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
_DIAGONAL = np.arange(3)
# vbd: one move may shrink an element's volume at most to this fraction of its current value.
_MIN_VOLUME_FRACTION_PER_MOVE = 0.1
# A colour's vertex sweep runs on the worker threads in shares of at least this many (vertex,
# element) incidences: the 10,648-vertex box's 8 colours hold 13,000-41,000, swept in about
# 0.9 ms each on one thread; a hand-off to a thread costs about 0.1 ms.
PARALLEL_MIN_INCIDENCES = 4000
# Floor of a distance that divides (a vertex at the tool's centre).
_TINY = np.finfo(float).tiny
_NO_ROWS = np.zeros(0, dtype=np.int64)  # no movable vertex held or sliding
# Each of RestFactor's two factors keeps forward-substituted unit columns of at most this many
# bytes, the oldest dropped first (a vertex's three take 0.7 MB at organ scale, 10,648 vertices).
_UNIT_HALVES_BYTES = 64 * 2**20
# vbd: vertices within this factor of the tool radius touch the tool.
_CONTACT_BAND = 1.0 + 1e-4
# stick contact: a prediction that leaves an element below this fraction of its rest volume
# (or inverted) is run again with the stuck vertices slipping wherever carrying them would take
# an element below it (ElasticSimulator.predict). Tissue never compresses to a hundredth of its
# volume, and such an element cannot be moved by the estimator: any step of its corners inverts
# it, and LM's volume guard then stops every step of the window. Measured on dome-tilted pushed
# twice as deep as designed (seed 0, 20 steps): a prediction with an element at 0.04 % of its
# rest volume left LM unconverged in the last three updates (final vertex RMSE 1.05x the
# simulation alone); with this floor every update converged (0.98x). The bundled airway
# (cao-push) is the only scene of the accuracy suite whose predictions go below it.
FLAT_VOLUME_RATIO = 0.01
# stick contact: a vertex stuck to the tool at the end of the last prediction is still stuck
# when the next prediction starts from a state that puts it within this fraction of the tool
# radius of the sphere's surface (an estimate's correction moves it by about the sensor noise).
_CONTACT_MEMORY_BAND = 0.25
# vbd: halvings of a global step before it is skipped; energy rise accepted as rounding.
_MAX_STEP_HALVINGS = 6
_ENERGY_ROUNDING = 1e-12
# xpbd: the isochoric invariant uses max(J, this), a guard for (nearly) inverted elements.
_MIN_VOLUME_RATIO = 0.05
# xpbd: isochoric strain below which C_D counts as zero: its gradient direction at the tip of
# the rest cone is rounding noise (sqrt of ~1e-16 is ~1e-8).
_MIN_DEVIATORIC = 1e-6


class SimulatorConfigError(ValueError):
    """A simulator setting outside its valid range."""


class SimulatorInputError(ValueError):
    """A state, tool pose, time step or vertex set of the wrong shape or value."""


class ElementInversionError(RuntimeError):
    """A predicted state with non-positive (or NaN) tetrahedron volumes; names the elements."""

    def __init__(self, element_indices: np.ndarray):
        self.element_indices = np.asarray(element_indices, dtype=np.int64)
        super().__init__(
            f"{self.element_indices.size} tetrahedra inverted (or not finite) after the simulation step: "
            f"{name_elements(self.element_indices)}"
        )


@dataclass(frozen=True)
class SimulatorConfig(TissueAndTool):
    """Material, tool and solver settings of `ElasticSimulator` (SI units): the tissue model and
    the tool it shares with the estimator (TissueAndTool), and its own. The fields made with
    `setting` are parameters of the simulation node and the replay (core/settings.py)."""

    density: float = setting(1.0e3, "Tissue density in kg/m^3.", range=(1.0, 1e5))  # gravity load, xpbd's inertia
    tool_contact: str = setting(
        "stick", "Sphere contact: 'stick' (the tissue does not slip while pushed) or 'slide' (frictionless).",
        choices=TOOL_CONTACTS)
    substeps: int = setting(2, "Tool increments per prediction.", range=(1, 1000), parameter="simulator_substeps")
    solver_iterations: int = setting(  # vbd: vertex sweep + global step; xpbd: constraint sweep
        3, "Solver iterations per sub-step.", range=(1, 1000), parameter="simulator_iterations")
    damping: float = 1.0  # xpbd: fraction of the velocity removed each sub-step (1: quasi-static)
    # m / s^2; xpbd moves (dt / substeps)^2 g per sub-step before solving: keep it << element size
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    deterministic: bool = True  # required: both solvers are bit-reproducible
    solver: str = setting("vbd", "Simulator solver: 'vbd' (vertex block descent) or 'xpbd'.", choices=SOLVERS,
                          parameter="simulator")  # see the module docstring
    estimate_body_load: bool = setting(
        True, "Estimate a uniform body load the tissue model does not know (a change of gravity, a pull) "
              "from each estimate's correction of its prediction, and apply it in the next predictions "
              "(core/physics/body_load.py).")
    estimate_poisson_ratio: bool = setting(
        True, "Learn the model's Poisson ratio online from the estimates' corrections of the surface, jointly "
              "with the body load (poisson_ratio is where it starts; core/physics/poisson_ratio.py, core/physics/model_fit.py).")

    def __post_init__(self):
        check_settings(self, SimulatorConfigError)
        checks = [
            (0.0 <= self.damping <= 1.0, "damping must lie in [0, 1]"),
            (
                np.shape(self.gravity) == (3,) and bool(np.all(np.isfinite(self.gravity))),
                "gravity must be 3 finite numbers",
            ),
            (self.deterministic, "deterministic=False is not offered: every run is bit-reproducible"),
        ]
        for passed, message in checks:
            if not passed:
                raise SimulatorConfigError(message)

    @property
    def shear_modulus(self) -> float:
        """Lame mu = E / (2 (1 + nu))."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda(self) -> float:
        """Lame lambda = E nu / ((1 + nu)(1 - 2 nu))."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


# ------------------------------------------------------------------------------ colouring


def _lowest_free_bit(taken: int) -> int:
    """The lowest zero bit of `taken`, as a one-bit mask."""
    return ~taken & (taken + 1)


def _group_by_colour(items: np.ndarray, colours: np.ndarray) -> list[np.ndarray]:
    """Split `items` into lists of equal colour, lowest colour first, each in input order."""
    order = np.argsort(colours, kind="stable")
    boundaries = np.flatnonzero(np.diff(colours[order])) + 1
    return np.split(np.asarray(items)[order], boundaries)


def colour_tetrahedra(tetrahedra: np.ndarray, vertex_count: int) -> list[np.ndarray]:
    """Greedy first-fit colouring: tetrahedron index lists, no two of a list share a vertex.

    Hand-written set-up loop (about a microsecond per element, bit masks per vertex): graph
    libraries would need the element conflict graph, which is far larger than the mesh.
    """
    vertex_colours = [0] * vertex_count  # bit c set: a tetrahedron of colour c uses the vertex
    colours = np.empty(len(tetrahedra), dtype=np.int64)
    for element, (a, b, c, d) in enumerate(np.asarray(tetrahedra).tolist()):
        bit = _lowest_free_bit(vertex_colours[a] | vertex_colours[b] | vertex_colours[c] | vertex_colours[d])
        colours[element] = bit.bit_length() - 1
        for vertex in (a, b, c, d):
            vertex_colours[vertex] |= bit
    return _group_by_colour(np.arange(len(tetrahedra)), colours)


def colour_vertices(vertices: np.ndarray, edges: np.ndarray, vertex_count: int) -> list[np.ndarray]:
    """Greedy first-fit colouring of `vertices`: index lists, no two of a list share an edge.

    Set-up loop over vertices and their neighbours, like `colour_tetrahedra`.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    directed = np.concatenate([edges, edges[:, ::-1]])
    directed = directed[np.argsort(directed[:, 0], kind="stable")]
    neighbours = np.split(directed[:, 1], np.searchsorted(directed[:, 0], np.arange(1, vertex_count)))
    neighbour_lists = [part.tolist() for part in neighbours]
    vertex_colours = [0] * vertex_count  # one-bit colour mask, 0 while uncoloured
    members = np.asarray(vertices, dtype=np.int64)
    colours = np.empty(members.size, dtype=np.int64)
    for position, vertex in enumerate(members.tolist()):
        taken = 0
        for neighbour in neighbour_lists[vertex]:
            taken |= vertex_colours[neighbour]
        vertex_colours[vertex] = _lowest_free_bit(taken)
        colours[position] = vertex_colours[vertex].bit_length() - 1
    return _group_by_colour(members, colours)


# ---------------------------------------------------------------------- per-colour data


@dataclass
class _VertexColour:
    """vbd: one colour of vertices and the (vertex, tetrahedron) incidences of its vertices,
    sorted by vertex, incidence-major and C-contiguous (the compiled sweep reads each
    incidence's data together)."""

    vertices: np.ndarray  # (n,) vertex indices, sorted
    segment_bounds: np.ndarray  # (n + 1,) the incidences of vertex i are segment_bounds[i]:segment_bounds[i + 1]
    corners: np.ndarray  # (P, 4) vertex indices of the incident tetrahedron
    rest_inverse: np.ndarray  # (P, 3, 3) Dm^-1 of the incident tetrahedron
    shape_gradient: np.ndarray  # (P, 3) g: gradient of the vertex's shape function
    volume_gradient: np.ndarray  # (P, 3) V g
    volumetric_stiffness: np.ndarray  # (P,) lambda' V
    shear_diagonal: np.ndarray  # (n,) sum of mu V |g|^2: the isotropic part of the Hessian
    gravity_force: np.ndarray  # (n, 3) lumped mass times gravity


@dataclass
class _ElementColour:
    """xpbd: constant data of one colour of tetrahedra (element-major), and their multipliers."""

    corners: np.ndarray  # (4, B) vertex indices
    rest_inverse: np.ndarray  # (3, 3, B) Dm^-1
    weighted_metric: np.ndarray  # (3, 3, B) sum_k w_k g_k g_k^T: inverse-mass metric of gradients in F
    corner_step: np.ndarray  # (4, 3, B) w_k g_k: corner moves from a gradient in F
    compliance: np.ndarray  # (2, B) [1 / (mu V), 1 / (kappa V)]
    multipliers: np.ndarray  # (2, B) XPBD multipliers of [C_D, C_H]


def _cofactor_em(matrices: np.ndarray) -> np.ndarray:
    """Cofactors cof(A) = det(A) A^-T of element-major A (3, 3, K): columns a1 x a2, a2 x a0, a0 x a1."""
    first, second = matrices[:, [1, 2, 0]], matrices[:, [2, 0, 1]]
    cofactor = np.empty_like(matrices)
    cofactor[0] = first[1] * second[2] - first[2] * second[1]
    cofactor[1] = first[2] * second[0] - first[0] * second[2]
    cofactor[2] = first[0] * second[1] - first[1] * second[0]
    return cofactor


@numba.njit(inline="always")
def _deformation(state, corners, rest_inverse, p):
    """F = Ds Dm^-1 (row-major 9-tuple) of the tetrahedron corners[p] (4,) at `state` (N, 3),
    Dm^-1 rest_inverse[p] (3, 3); Ds's columns are the edges from corner 0."""
    i0, i1, i2, i3 = corners[p, 0], corners[p, 1], corners[p, 2], corners[p, 3]
    ux, uy, uz = state[i1, 0] - state[i0, 0], state[i1, 1] - state[i0, 1], state[i1, 2] - state[i0, 2]
    vx, vy, vz = state[i2, 0] - state[i0, 0], state[i2, 1] - state[i0, 1], state[i2, 2] - state[i0, 2]
    wx, wy, wz = state[i3, 0] - state[i0, 0], state[i3, 1] - state[i0, 1], state[i3, 2] - state[i0, 2]
    r00, r01, r02 = rest_inverse[p, 0, 0], rest_inverse[p, 0, 1], rest_inverse[p, 0, 2]
    r10, r11, r12 = rest_inverse[p, 1, 0], rest_inverse[p, 1, 1], rest_inverse[p, 1, 2]
    r20, r21, r22 = rest_inverse[p, 2, 0], rest_inverse[p, 2, 1], rest_inverse[p, 2, 2]
    return (ux * r00 + vx * r10 + wx * r20, ux * r01 + vx * r11 + wx * r21, ux * r02 + vx * r12 + wx * r22,
            uy * r00 + vy * r10 + wy * r20, uy * r01 + vy * r11 + wy * r21, uy * r02 + vy * r12 + wy * r22,
            uz * r00 + vz * r10 + wz * r20, uz * r01 + vz * r11 + wz * r21, uz * r02 + vz * r12 + wz * r22)


@numba.njit(inline="always")
def _cofactor(f00, f01, f02, f10, f11, f12, f20, f21, f22):
    """cof(F) = det(F) F^-T (row-major 9-tuple): its columns are f1 x f2, f2 x f0, f0 x f1 for
    F's columns f0, f1, f2."""
    return (f11 * f22 - f21 * f12, f12 * f20 - f22 * f10, f10 * f21 - f20 * f11,
            f21 * f02 - f01 * f22, f22 * f00 - f02 * f20, f20 * f01 - f00 * f21,
            f01 * f12 - f11 * f02, f02 * f10 - f12 * f00, f00 * f11 - f10 * f01)


@numba.njit((writable(float64, 2), read_only(int64, 1), read_only(int64, 1), read_only(int64, 2),
             read_only(float64, 3), read_only(float64, 2), read_only(float64, 2), read_only(float64, 1),
             read_only(float64, 1), read_only(float64, 2), read_only(boolean, 1), float64, float64, float64,
             read_only(float64, 1), float64, boolean), cache=True, boundscheck=False, error_model="numpy", nogil=True)
def _sweep_colour(state, vertices, segment_bounds, corners, rest_inverse, shape_gradient, volume_gradient,
                  volumetric_stiffness, shear_diagonal, gravity_force, held, shear_modulus, volumetric_modulus,
                  rest_volume_ratio, tool_centre, tool_radius, push):
    """vbd's sweep over one colour's vertices, in place (VertexBlockDescent._vertex_sweep): per
    vertex, the exact minimiser of its quadratic energy over its incidences p (from
    segment_bounds[i] to segment_bounds[i + 1]) from F, cof F and J of each incident element; pushed out of
    the tool sphere (`push`); kept where it is when `held`; the move shortened so that no
    incident J drops below _MIN_VOLUME_FRACTION_PER_MOVE of its value. Vertices of a colour
    share no element, so moving them one after the other is moving them together.

    Compiled (numba): as numpy passes over the colour's incidences (einsum contractions, the
    cofactors, reduceat sums) the sweeps take half of a prediction's time at organ scale. Not
    bounds-checked, unlike the package's other kernels (checks double its time): its indices
    are the rest mesh's elements, which TetMesh keeps within its vertices, and `state` and
    `held` have a row per vertex (ElasticSimulator.predict checks the state's shape)."""
    slopes = np.empty((corners.shape[0], 3))  # dJ/dx = cof(F) g of each incidence
    ratios = np.empty(corners.shape[0])  # J
    for i in range(vertices.size):
        vertex = vertices[i]
        if held[vertex]:
            continue
        h00 = h01 = h02 = h11 = h12 = h22 = 0.0  # sum of lambda' V (cof F g)(cof F g)^T
        g0 = g1 = g2 = 0.0  # sum of V P g
        for p in range(segment_bounds[i], segment_bounds[i + 1]):
            f00, f01, f02, f10, f11, f12, f20, f21, f22 = _deformation(state, corners, rest_inverse, p)
            c00, c01, c02, c10, c11, c12, c20, c21, c22 = _cofactor(f00, f01, f02, f10, f11, f12, f20, f21, f22)
            ratio = f00 * c00 + f10 * c10 + f20 * c20
            pressure = volumetric_modulus * (ratio - rest_volume_ratio)
            b0, b1, b2 = volume_gradient[p, 0], volume_gradient[p, 1], volume_gradient[p, 2]
            g0 += (shear_modulus * f00 + pressure * c00) * b0 + (shear_modulus * f01 + pressure * c01) * b1 + (
                shear_modulus * f02 + pressure * c02) * b2
            g1 += (shear_modulus * f10 + pressure * c10) * b0 + (shear_modulus * f11 + pressure * c11) * b1 + (
                shear_modulus * f12 + pressure * c12) * b2
            g2 += (shear_modulus * f20 + pressure * c20) * b0 + (shear_modulus * f21 + pressure * c21) * b1 + (
                shear_modulus * f22 + pressure * c22) * b2
            a0, a1, a2 = shape_gradient[p, 0], shape_gradient[p, 1], shape_gradient[p, 2]
            s0 = c00 * a0 + c01 * a1 + c02 * a2
            s1 = c10 * a0 + c11 * a1 + c12 * a2
            s2 = c20 * a0 + c21 * a1 + c22 * a2
            k = volumetric_stiffness[p]
            h00 += k * s0 * s0
            h01 += k * s0 * s1
            h02 += k * s0 * s2
            h11 += k * s1 * s1
            h12 += k * s1 * s2
            h22 += k * s2 * s2
            slopes[p, 0], slopes[p, 1], slopes[p, 2] = s0, s1, s2
            ratios[p] = ratio
        h00 += shear_diagonal[i]
        h11 += shear_diagonal[i]
        h22 += shear_diagonal[i]
        force0 = gravity_force[i, 0] - g0
        force1 = gravity_force[i, 1] - g1
        force2 = gravity_force[i, 2] - g2
        # The Hessian is symmetric positive definite: its inverse is its adjugate (cofactor) over det.
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = _cofactor(h00, h01, h02, h01, h11, h12, h02, h12, h22)
        determinant = h00 * a00 + h01 * a10 + h02 * a20
        x0, x1, x2 = state[vertex, 0], state[vertex, 1], state[vertex, 2]
        t0 = x0 + (a00 * force0 + a01 * force1 + a02 * force2) / determinant
        t1 = x1 + (a10 * force0 + a11 * force1 + a12 * force2) / determinant
        t2 = x2 + (a20 * force0 + a21 * force1 + a22 * force2) / determinant
        if push:  # _outside_tool
            o0, o1, o2 = t0 - tool_centre[0], t1 - tool_centre[1], t2 - tool_centre[2]
            distance = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
            if distance < tool_radius:
                scale = tool_radius / max(distance, _TINY)
                t0, t1, t2 = tool_centre[0] + scale * o0, tool_centre[1] + scale * o1, tool_centre[2] + scale * o2
        m0, m1, m2 = t0 - x0, t1 - x1, t2 - x2
        # J is affine along a vertex move: keep every incident J above a fraction of its value.
        scale = 1.0
        for p in range(segment_bounds[i], segment_bounds[i + 1]):
            slope = slopes[p, 0] * m0 + slopes[p, 1] * m1 + slopes[p, 2] * m2
            if slope < 0.0 and ratios[p] > 0.0:
                scale = min(scale, (1.0 - _MIN_VOLUME_FRACTION_PER_MOVE) * ratios[p] / -slope)
        state[vertex, 0] = x0 + scale * m0
        state[vertex, 1] = x1 + scale * m1
        state[vertex, 2] = x2 + scale * m2


@numba.njit((read_only(float64, 2), read_only(int64, 2), read_only(float64, 3), read_only(float64, 3),
             read_only(float64, 1), float64, float64, float64, writable(float64, 1), writable(float64, 2)),
            cache=True, boundscheck=False, error_model="numpy")
def _elastic_energy(state, tetrahedra, rest_inverse, corner_volume_gradient, volumes, shear_modulus,
                    volumetric_modulus, rest_volume_ratio, volume_ratios, forces):
    """The elastic energy of `state` (N, 3), sum of V (mu/2 (I_C - 3) + lambda'/2 (J - gamma)^2);
    each element's J into volume_ratios (M,), and, unless `forces` has no rows, the elastic
    forces -dE/dx (N, 3) added into it (corner k of element e: -V P g_k, corner_volume_gradient
    (M, 4, 3) holding V g_k, P = mu F + lambda' (J - gamma) cof F).

    Compiled (numba): as numpy passes (F, cof F, their contractions, a bincount per axis) the
    energies and forces of the global steps take a sixth of a prediction at organ scale. Not
    bounds-checked, as `_sweep_colour` (the checks would cost several times its time)."""
    energy = 0.0
    with_forces = forces.shape[0] > 0
    for e in range(tetrahedra.shape[0]):
        f00, f01, f02, f10, f11, f12, f20, f21, f22 = _deformation(state, tetrahedra, rest_inverse, e)
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = _cofactor(f00, f01, f02, f10, f11, f12, f20, f21, f22)
        ratio = f00 * c00 + f10 * c10 + f20 * c20
        volume_ratios[e] = ratio
        frobenius_squared = (f00 * f00 + f01 * f01 + f02 * f02 + f10 * f10 + f11 * f11 + f12 * f12
                             + f20 * f20 + f21 * f21 + f22 * f22)
        change = ratio - rest_volume_ratio
        energy += volumes[e] * (0.5 * shear_modulus * (frobenius_squared - 3.0)
                                + 0.5 * volumetric_modulus * change * change)
        if with_forces:
            pressure = volumetric_modulus * change
            mu = shear_modulus
            p00, p01, p02 = mu * f00 + pressure * c00, mu * f01 + pressure * c01, mu * f02 + pressure * c02
            p10, p11, p12 = mu * f10 + pressure * c10, mu * f11 + pressure * c11, mu * f12 + pressure * c12
            p20, p21, p22 = mu * f20 + pressure * c20, mu * f21 + pressure * c21, mu * f22 + pressure * c22
            for k in range(4):
                b0, b1, b2 = (corner_volume_gradient[e, k, 0], corner_volume_gradient[e, k, 1],
                              corner_volume_gradient[e, k, 2])
                corner = tetrahedra[e, k]
                forces[corner, 0] -= p00 * b0 + p01 * b1 + p02 * b2
                forces[corner, 1] -= p10 * b0 + p11 * b1 + p12 * b2
                forces[corner, 2] -= p20 * b0 + p21 * b1 + p22 * b2
    return energy


def _as_pose(tool_pose) -> np.ndarray:
    """Validated [x y z qx qy qz qw] with a unit quaternion (pose_history.as_pose), or SimulatorInputError."""
    try:
        return as_pose(tool_pose)
    except InvalidPoseError as error:
        raise SimulatorInputError(f"tool_pose: {error}") from None


# ------------------------------------------------------------------------ shared set-up


@dataclass(frozen=True)
class _Body:
    """What every solver strategy starts from: the rest mesh, the settings, which vertices
    move, and the elements' rest data."""

    rest_mesh: TetMesh
    config: SimulatorConfig
    kinematic: np.ndarray  # (N,) bool: fixed or grasped (moved by the boundary or the tool only)
    movable_vertices: np.ndarray  # (n,) the others
    volumes: np.ndarray  # (M,) rest volumes
    rest_inverse: np.ndarray  # (M, 3, 3) Dm^-1
    corner_gradient: np.ndarray  # (M, 4, 3) shape-function gradients of the corners
    vertex_mass: np.ndarray  # (N,) lumped mass
    gravity: np.ndarray  # (3,) m / s^2
    # (A, B) with the rest stiffness K0 = mu A + lambda B (3 N, 3 N, on one pattern): K0 at any
    # Poisson ratio without a new ElasticModel (ElasticModel.linear_stiffness_parts)
    stiffness_parts: tuple


def _outside_tool(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """`points` (k, 3) with those inside the tool sphere (`radius` about `centre`) moved
    radially onto its surface."""
    offsets = points - centre
    distances = np.sqrt(np.einsum("ij,ij->i", offsets, offsets))
    inside = np.flatnonzero(distances < radius)
    if inside.size == 0:
        return points
    pushed = points.copy()
    directions = offsets[inside] / np.maximum(distances[inside], _TINY)[:, None]
    pushed[inside] = centre + radius * directions
    return pushed


class _KeptFactor:
    """One numeric factor of K0, the unit columns forward-substituted through it (movable row ->
    L^-1 P of its three unit columns, (3 n, 3)), and its last refactor (running beside the
    loop, or ended, with what it met)."""

    def __init__(self, cholesky: SparseCholesky):
        self.cholesky = cholesky
        self.unit_halves: dict[int, np.ndarray] = {}
        self._refactoring: Future | None = None  # start_background's

    def refactor(self, values: np.ndarray) -> None:
        """Refactor with `values` beside the caller (worker_threads.start_background: in line
        with one worker thread; SparseCholesky's refactor releases the GIL); `settle` waits for
        it and raises what it met."""
        self.unit_halves.clear()
        self._refactoring = worker_threads.start_background(self.cholesky.refactor, values)

    def settle(self) -> _KeptFactor:
        """This factor once its refactor has ended; its error, if it failed."""
        refactoring, self._refactoring = self._refactoring, None
        if refactoring is not None:
            refactoring.result()
        return self


class RestFactor:
    """The Cholesky factor of K0 (small-strain stiffness: the Hessian at rest) on the movable
    dofs, and its solves with some movable vertices held or sliding on the tool.

    K0 = mu A + lambda B (the body's stiffness_parts) has one pattern at any moduli: the
    entries of A and B on the movable dofs are picked once, and a new Poisson ratio is a
    numeric refactor of their sum (`refactor`).

    Two factors, so that a new ratio's refactor is off the loop's path. The learning's rest
    responses need K0 at the current moduli (`solve`); the prediction's global step only needs
    a Hessian close to the body's, since its line search keeps the energy's own moduli
    (`solve(..., stepping=True)`). After a ratio change the global step therefore uses the
    factor of the ratio before it, while the new ratio's is made on a thread of its own (with
    more than one worker thread, core/worker_threads.py), during the prediction and the update
    that follow, and waited for by the next learning. The steps use the previous ratio's factor
    however long the refactor takes, so a prediction does not depend on the timing: a replay
    gives what the live nodes give.

    A constrained solve is a Schur complement on the factor: with K0 = P^T L L^T P, the
    constraint columns E and W = L^-1 P E, the solution of K0 x = f held to E^T x = 0 is
    x = P^T L^-T (z - W (W^T W)^-1 W^T z), z = L^-1 P f (W^T W = E^T K0^-1 E): one forward and
    one back substitution, as an unconstrained solve. A held vertex's constraints are its three
    unit columns and a sliding vertex's is its normal there, so W is made of the forward
    substitutions of the three unit columns of each such vertex, which are kept until the next
    refactor: a vertex in contact costs three half-solves once, instead of a full solve per
    constraint column at every global step (a single-column solve reads the whole factor).
    """

    def __init__(self, body: _Body):
        shear, volumetric = body.stiffness_parts
        dofs = (3 * body.movable_vertices[:, None] + _DIAGONAL).reshape(-1)
        # Which entries of the parts' shared pattern K0's movable block holds, in its sorted csr order.
        picked = scipy.sparse.csr_matrix((np.arange(1.0, shear.nnz + 1.0), shear.indices, shear.indptr),
                                         shape=shear.shape)[dofs][:, dofs]
        picked.sort_indices()
        entries = picked.data.astype(np.int64) - 1
        self._shear, self._volumetric = shear.data[entries], volumetric.data[entries]
        stiffness = scipy.sparse.csr_matrix((self._values(body.config), picked.indices, picked.indptr),
                                            shape=picked.shape)
        self._current = _KeptFactor(SparseCholesky(stiffness, node_size=3))  # at the body's moduli
        self._stepping = self._current  # the global step's: at the moduli before the last change

    @property
    def size(self) -> int:
        """Movable dofs."""
        return self._current.cholesky.size

    def _values(self, config: SimulatorConfig) -> np.ndarray:
        return config.shear_modulus * self._shear + config.lame_lambda * self._volumetric

    def refactor(self, config: SimulatorConfig) -> None:
        """K0 at `config`'s moduli for the rest responses from now on; the global step keeps the
        factor of the moduli before (class doc)."""
        current = self._current.settle()
        spare = self._stepping if self._stepping is not current else _KeptFactor(current.cholesky.sibling(None))
        self._stepping, self._current = current, spare
        spare.refactor(self._values(config))

    def catch_up(self) -> None:
        """The global step from now on through the factor of the current moduli too (waiting for
        it): the next prediction steps as a newly made simulator's would."""
        self._stepping = self._current.settle()

    def solve(self, forces: np.ndarray, held_rows: np.ndarray = _NO_ROWS, sliding_rows: np.ndarray = _NO_ROWS,
              normals: np.ndarray | None = None, stepping: bool = False) -> np.ndarray:
        """K0^-1 forces for forces (3 n,) or (3 n, k), the movable vertices at `held_rows` (of
        the movable set) held and those at `sliding_rows` not moving along their `normals` (s, 3);
        `stepping`: through the global step's factor (class doc)."""
        kept = self._stepping if stepping else self._current.settle()
        half = kept.cholesky.forward_solve(forces)
        constraints = self._constraint_halves(kept, held_rows, sliding_rows, normals)
        if constraints.shape[1]:
            half = half - constraints @ np.linalg.solve(constraints.T @ constraints, constraints.T @ half)
        return kept.cholesky.back_solve(half)

    def _constraint_halves(self, kept: _KeptFactor, held_rows, sliding_rows, normals) -> np.ndarray:
        """W = L^-1 P E (3 n, 3 h + s) through `kept`'s factor: the held vertices' unit columns,
        then the sliding ones' normals."""
        rows = np.concatenate([held_rows, sliding_rows]).astype(np.int64)
        unit_halves = kept.unit_halves
        missing = [int(row) for row in np.unique(rows) if int(row) not in unit_halves]
        if missing:
            dofs = (3 * np.asarray(missing)[:, None] + _DIAGONAL).reshape(-1)
            units = np.zeros((self.size, dofs.size))
            units[dofs, np.arange(dofs.size)] = 1.0
            halves = kept.cholesky.forward_solve(units)
            for k, row in enumerate(missing):
                unit_halves[row] = np.ascontiguousarray(halves[:, 3 * k:3 * k + 3])
        columns = [unit_halves[int(row)] for row in held_rows]
        if sliding_rows.size:
            columns.append(np.stack([unit_halves[int(row)] @ normal
                                     for row, normal in zip(sliding_rows, normals)], axis=1))
        while len(unit_halves) * 3 * self.size * 8 > _UNIT_HALVES_BYTES:
            del unit_halves[next(iter(unit_halves))]  # the oldest
        return np.concatenate(columns, axis=1) if columns else np.zeros((self.size, 0))


# ---------------------------------------------------------------------- solver strategies


class SimulatorSolver:
    """How one sub-step moves the tissue (SimulatorConfig.solver picks the strategy).

    `begin` is called once per prediction with its starting state; `substep` moves `state` in
    place for a sub-step of `step` seconds with the tool at `tool_centre`, keeping the `held`
    vertices (stuck to the tool) where they are. Fixed and grasped vertices are the
    simulator's: a strategy moves only `movable_vertices`.
    """

    rest_stiffness: RestFactor | None = None  # K0's factor on the movable dofs, where the strategy factors it

    def begin(self, state: np.ndarray) -> None:
        """Start a prediction from `state` (N, 3)."""

    def set_gravity(self, gravity: np.ndarray) -> None:
        """Uniform body acceleration (3,) in m/s^2 from the next sub-step on."""
        raise NotImplementedError

    def set_material(self, config: SimulatorConfig) -> None:
        """Use `config`'s elastic moduli from the next sub-step on (the rest of it unchanged;
        the owner refactors `rest_stiffness`)."""
        raise NotImplementedError

    def substep(self, state: np.ndarray, step: float, tool_centre: np.ndarray, held: np.ndarray) -> None:
        raise NotImplementedError


class VertexBlockDescent(SimulatorSolver):
    """solver "vbd": quasi-static vertex block descent with a global rest-Hessian step.

    Each iteration is one coloured sweep of exact per-vertex energy minimisations, then a
    quasi-Newton step with the rest Hessian K0 (see the module docstring). The fixed point is
    the equilibrium whatever the iteration count; `step` (the sub-step's duration) is unused.
    """

    def __init__(self, body: _Body):
        config = body.config
        self.rest_mesh, self.config, self.movable_vertices = body.rest_mesh, config, body.movable_vertices
        tets, volumes = body.rest_mesh.tetrahedra, body.volumes
        self._volumetric_modulus = config.lame_lambda + config.shear_modulus  # lambda'
        self._rest_volume_ratio = 1.0 + config.shear_modulus / self._volumetric_modulus  # gamma
        self._volumes = volumes
        self._tetrahedra = np.ascontiguousarray(tets, dtype=np.int64)
        self._rest_inverse = np.ascontiguousarray(body.rest_inverse)
        self._corner_volume_gradient = np.ascontiguousarray(volumes[:, None, None] * body.corner_gradient)
        self._vertex_mass = body.vertex_mass
        self._gravity_force = body.vertex_mass[:, None] * body.gravity
        self._colours = self._vertex_colours(tets, volumes, body.rest_inverse, body.corner_gradient)
        self.rest_stiffness = RestFactor(body) if self.movable_vertices.size else None

    def set_gravity(self, gravity: np.ndarray) -> None:
        self._gravity_force = self._vertex_mass[:, None] * gravity
        for colour in self._colours:
            colour.gravity_force = self._gravity_force[colour.vertices]

    def set_material(self, config: SimulatorConfig) -> None:
        """The element moduli rescaled in place: the colouring (a Python loop over the
        vertices) is kept."""
        volumetric_modulus = config.lame_lambda + config.shear_modulus
        shear_scale = config.shear_modulus / self.config.shear_modulus
        volumetric_scale = volumetric_modulus / self._volumetric_modulus
        for colour in self._colours:
            colour.shear_diagonal = colour.shear_diagonal * shear_scale
            colour.volumetric_stiffness = colour.volumetric_stiffness * volumetric_scale
        self.config, self._volumetric_modulus = config, volumetric_modulus
        self._rest_volume_ratio = 1.0 + config.shear_modulus / volumetric_modulus

    def _vertex_colours(self, tets, volumes, rest_inverse, corner_gradient) -> list[_VertexColour]:
        """Colours of the movable vertices with their incident-element data."""
        element_count = tets.shape[0]
        incidence_vertex = tets.reshape(-1)
        by_vertex = np.argsort(incidence_vertex, kind="stable")
        incidence_vertex = incidence_vertex[by_vertex]
        incidence_element = np.repeat(np.arange(element_count), 4)[by_vertex]
        incidence_corner = np.tile(np.arange(4), element_count)[by_vertex]
        colours = []
        vertex_count = self.rest_mesh.vertex_count
        for members in colour_vertices(self.movable_vertices, self.rest_mesh.edges, vertex_count):
            members = np.sort(members)
            selected = np.flatnonzero(np.isin(incidence_vertex, members))
            element = incidence_element[selected]
            gradient = corner_gradient[element, incidence_corner[selected]]
            local_vertex = np.searchsorted(members, incidence_vertex[selected])
            segment_bounds = np.flatnonzero(np.r_[True, local_vertex[1:] != local_vertex[:-1], True])
            shear = self.config.shear_modulus * volumes[element] * np.einsum("pi,pi->p", gradient, gradient)
            colours.append(
                _VertexColour(
                    vertices=members,
                    segment_bounds=segment_bounds,
                    corners=np.ascontiguousarray(tets[element], dtype=np.int64),
                    rest_inverse=np.ascontiguousarray(rest_inverse[element]),
                    shape_gradient=np.ascontiguousarray(gradient),
                    volume_gradient=np.ascontiguousarray(volumes[element][:, None] * gradient),
                    volumetric_stiffness=self._volumetric_modulus * volumes[element],
                    shear_diagonal=np.add.reduceat(shear, segment_bounds[:-1]),
                    gravity_force=self._gravity_force[members],
                )
            )
        return colours

    def substep(self, state, step, tool_centre, held) -> None:
        """Quasi-static iterations of one sub-step in place: a vertex sweep, then a global K0 step.

        `held` vertices (stuck to the tool) keep their positions during the sub-step.
        """
        held_mask = np.zeros(self.rest_mesh.vertex_count, dtype=bool)
        held_mask[held] = True
        held_rows = np.flatnonzero(held_mask[self.movable_vertices])
        for _ in range(int(self.config.solver_iterations)):
            for colour in self._colours:
                self._vertex_sweep(state, colour, tool_centre, held_mask)
            self._global_step(state, tool_centre, held_mask, held_rows)

    def _energy_and_volume_ratios(self, state: np.ndarray, with_forces: bool = False):
        """Total energy (elastic + gravity) and volume ratios J (M,) at `state`; with
        `with_forces`, the forces -dE/dx (N, 3), elastic + gravity, too (else None)."""
        volume_ratio = np.empty(self._volumes.size)
        forces = np.zeros(state.shape if with_forces else (0, 3))
        elastic = _elastic_energy(state, self._tetrahedra, self._rest_inverse, self._corner_volume_gradient,
                                  self._volumes, self.config.shear_modulus, self._volumetric_modulus,
                                  self._rest_volume_ratio, volume_ratio, forces)
        energy = elastic - float(np.einsum("ij,ij->", self._gravity_force, state))
        return energy, volume_ratio, (forces + self._gravity_force if with_forces else None)

    def _global_step(self, state, tool_centre, held_mask, held_rows) -> None:
        """Quasi-Newton step with the rest Hessian K0, in place: the smooth, global part of the error.
        K0 is the factor of the Poisson ratio before the last change (RestFactor), a metric
        only: the line search below judges the step with the energy at the current moduli.

        Held vertices (`held_rows` of the movable ones) do not move and other vertices touching
        the tool may only slide along it: the step is constrained through a Schur complement on
        the K0 factor (RestFactor.solve). It is halved until the energy does not rise and no
        volume drops below a fraction of its value, and skipped if that fails.
        """
        energy, volume_ratio, forces = self._energy_and_volume_ratios(state, with_forces=True)
        movable = self.movable_vertices
        sliding_rows, normals = self._sliding_contacts(state[movable], tool_centre, held_mask[movable])
        step = self.rest_stiffness.solve(forces[movable].reshape(-1), held_rows, sliding_rows, normals, stepping=True)
        step = step.reshape(-1, 3)
        trial = state.copy()
        for _ in range(_MAX_STEP_HALVINGS):
            trial[movable] = state[movable] + step
            trial_energy, trial_ratio, _ = self._energy_and_volume_ratios(trial)
            if trial_energy <= energy + _ENERGY_ROUNDING * abs(energy) and np.all(
                trial_ratio > _MIN_VOLUME_FRACTION_PER_MOVE * volume_ratio
            ):
                state[movable] = trial[movable]
                return
            step *= 0.5

    def _sliding_contacts(self, positions: np.ndarray, tool_centre, held: np.ndarray):
        """The movable vertices touching the tool, not held (rows of `positions`, the movable
        ones'), and their outward normals on it (k, 3): they may not move along them."""
        if self.config.tool_mode != "sphere":
            return _NO_ROWS, np.zeros((0, 3))
        offsets = positions - tool_centre
        distances = np.sqrt(np.einsum("ij,ij->i", offsets, offsets))
        touching = np.flatnonzero((distances <= self.config.tool_radius * _CONTACT_BAND) & ~held)
        return touching, offsets[touching] / distances[touching, None]

    def _vertex_sweep(self, state: np.ndarray, colour: _VertexColour, tool_centre: np.ndarray,
                      held_mask: np.ndarray) -> None:
        """Exact energy minimisation over each vertex of a colour, tool contact, volume-safe move
        (the compiled `_sweep_colour`); vertices in `held_mask` (N,) stay where they are. The
        colour's vertices share no element, so shares of them move at once on the worker threads
        (core/worker_threads.py), each vertex as on one thread, when each share holds at least
        PARALLEL_MIN_INCIDENCES incidences."""
        centre = np.ascontiguousarray(tool_centre, dtype=np.float64)
        shares = worker_threads.ranges(colour.vertices.size, colour.corners.shape[0] // PARALLEL_MIN_INCIDENCES)
        worker_threads.run_parts(_sweep_colour, [
            (state, colour.vertices[share], colour.segment_bounds[share.start:share.stop + 1], colour.corners,
             colour.rest_inverse, colour.shape_gradient, colour.volume_gradient, colour.volumetric_stiffness,
             colour.shear_diagonal[share], colour.gravity_force[share], held_mask, self.config.shear_modulus,
             self._volumetric_modulus, self._rest_volume_ratio, centre, float(self.config.tool_radius),
             self.config.tool_mode == "sphere") for share in shares])


def _bulk_modulus(config: SimulatorConfig) -> float:
    return config.lame_lambda + 2.0 * config.shear_modulus / 3.0


class ExtendedPositionBasedDynamics(SimulatorSolver):
    """solver "xpbd": damped XPBD dynamics over per-element Neo-Hookean constraints.

    Per sub-step: damp the velocity, move by it and by gravity, then Gauss-Seidel over the
    coloured elements' coupled isochoric + volume constraints (see the module docstring). The
    velocity carries over between the sub-steps of one prediction and starts at zero.
    """

    def __init__(self, body: _Body):
        self.config, self.movable_vertices = body.config, body.movable_vertices
        self._gravity = body.gravity
        inverse_mass = np.where(body.kinematic, 0.0, 1.0 / body.vertex_mass)
        self._colours = self._element_colours(body.rest_mesh, body.volumes, body.rest_inverse,
                                              body.corner_gradient, inverse_mass)
        self._velocity: np.ndarray | None = None

    def begin(self, state):
        self._velocity = np.zeros_like(state)

    def set_gravity(self, gravity: np.ndarray) -> None:
        self._gravity = gravity

    def set_material(self, config: SimulatorConfig) -> None:
        """The elements' compliances rescaled in place (the colouring kept)."""
        shear_scale = self.config.shear_modulus / config.shear_modulus
        bulk_scale = _bulk_modulus(self.config) / _bulk_modulus(config)
        for colour in self._colours:
            colour.compliance = colour.compliance * np.array([[shear_scale], [bulk_scale]])
        self.config = config

    def substep(self, state, step, tool_centre, held) -> None:
        self._velocity = self._xpbd_substep(state, self._velocity, step, tool_centre, held)

    def _element_colours(self, rest_mesh: TetMesh, volumes, rest_inverse, corner_gradient, inverse_mass):
        """Tetrahedron colours with their constant metric and compliance data."""
        tets = rest_mesh.tetrahedra
        corner_step = inverse_mass[tets][:, :, None] * corner_gradient  # (M, 4, 3)
        weighted_metric = np.transpose(corner_gradient, (0, 2, 1)) @ corner_step
        compliance = np.stack([1.0 / (self.config.shear_modulus * volumes),
                               1.0 / (_bulk_modulus(self.config) * volumes)])
        return [
            _ElementColour(
                corners=np.ascontiguousarray(tets[members].T),
                rest_inverse=np.ascontiguousarray(rest_inverse[members].transpose(1, 2, 0)),
                weighted_metric=np.ascontiguousarray(weighted_metric[members].transpose(1, 2, 0)),
                corner_step=np.ascontiguousarray(corner_step[members].transpose(1, 2, 0)),
                compliance=np.ascontiguousarray(compliance[:, members]),
                multipliers=np.zeros((2, members.size)),
            )
            for members in colour_tetrahedra(tets, rest_mesh.vertex_count)
        ]

    def _xpbd_substep(self, state: np.ndarray, velocity, step: float, tool_centre, held) -> np.ndarray:
        """One damped XPBD sub-step in place, `held` vertices kept in place; returns the new velocity."""
        start = state.copy()
        held_positions = state[held]
        movable = self.movable_vertices
        velocity = velocity * (1.0 - self.config.damping)
        state[movable] += step * velocity[movable] + step * step * self._gravity
        state[held] = held_positions
        inverse_step_squared = 1.0 / (step * step)
        for colour in self._colours:
            colour.multipliers[:] = 0.0
        for _ in range(int(self.config.solver_iterations)):
            for colour in self._colours:
                self._project_constraints(state, colour, inverse_step_squared)
            if self.config.tool_mode == "sphere":
                state[movable] = _outside_tool(state[movable], tool_centre, self.config.tool_radius)
            state[held] = held_positions
        return (state - start) / step

    @staticmethod
    def _project_constraints(state: np.ndarray, colour: _ElementColour, inverse_step_squared: float) -> None:
        """One coupled XPBD update (2x2 solve) of the isochoric + volume constraints of a colour."""
        positions = state.T[:, colour.corners]  # (3, 4, B)
        deformation = np.einsum("akb,kjb->ajb", positions[:, 1:] - positions[:, :1], colour.rest_inverse)
        cofactor = _cofactor_em(deformation)  # dJ/dF
        volume_ratio = np.einsum("ab,ab->b", deformation[:, 0], cofactor[:, 0])
        frobenius_squared = np.einsum("ajb,ajb->b", deformation, deformation)
        clamped_ratio = np.maximum(volume_ratio, _MIN_VOLUME_RATIO)
        isochoric_scale = np.cbrt(clamped_ratio) ** -2
        deviatoric = np.sqrt(np.maximum(frobenius_squared * isochoric_scale - 3.0, 0.0))
        # dC_D/dF = J^(-2/3) (F - I_C / (3 J) cof F) / C_D; zero at the tip of the rest cone.
        gradient_scale = np.where(
            deviatoric > _MIN_DEVIATORIC, isochoric_scale / np.maximum(deviatoric, _MIN_DEVIATORIC), 0.0
        )
        cofactor_scale = gradient_scale * frobenius_squared / (3.0 * clamped_ratio)
        deviatoric_gradient = gradient_scale * deformation - cofactor_scale * cofactor
        metric_deviatoric = np.einsum("alb,jlb->ajb", deviatoric_gradient, colour.weighted_metric)
        metric_cofactor = np.einsum("alb,jlb->ajb", cofactor, colour.weighted_metric)
        compliance = colour.compliance * inverse_step_squared  # alpha tilde
        a = np.einsum("ajb,ajb->b", deviatoric_gradient, metric_deviatoric) + compliance[0]
        b = np.einsum("ajb,ajb->b", deviatoric_gradient, metric_cofactor)
        d = np.einsum("ajb,ajb->b", cofactor, metric_cofactor) + compliance[1]
        residual = -compliance * colour.multipliers
        residual[0] -= deviatoric
        residual[1] -= volume_ratio - 1.0
        inverse_determinant = 1.0 / (a * d - b * b)
        delta_deviatoric = (d * residual[0] - b * residual[1]) * inverse_determinant
        delta_volume = (a * residual[1] - b * residual[0]) * inverse_determinant
        colour.multipliers[0] += delta_deviatoric
        colour.multipliers[1] += delta_volume
        gradient = delta_deviatoric * deviatoric_gradient + delta_volume * cofactor
        state.T[:, colour.corners] = positions + np.einsum("ajb,kjb->akb", gradient, colour.corner_step)


# The strategy of each SimulatorConfig.solver name (SOLVERS).
SOLVER_STRATEGIES = {"vbd": VertexBlockDescent, "xpbd": ExtendedPositionBasedDynamics}


# ---------------------------------------------------------------------------- simulator


class ElasticSimulator:
    """Quasi-static prediction of an elastic tetrahedral mesh pushed or held by a tool.

    The set-up, the tool and its contact belong to the simulator; each sub-step's motion is
    `solver`, the strategy SimulatorConfig.solver names (VertexBlockDescent or
    ExtendedPositionBasedDynamics, SOLVER_STRATEGIES).

    Fixed vertices (`rest_mesh.fixed_vertices`) never move. In "sphere" mode movable vertices
    inside the tool sphere (radius `tool_radius` about the tool position) are pushed onto its
    surface. With tool_contact "stick", vertices touching the sphere when a sub-step starts
    move with it for that sub-step unless it moves away from them: frictionless contact of a
    single vertex on a sphere is an unstable equilibrium (the tissue slides off the pole,
    differently for every iteration count), which sticking removes. Sticking persists across
    predictions: a vertex stuck at the end of the last one is put back on the sphere and stays
    stuck when the next starting state (an estimate) has it within _CONTACT_MEMORY_BAND tool
    radii of the surface. Without that memory a 0.1 mm correction that lifts the vertex off the
    tool releases it, it slides off the pole, the tool passes between the vertices of a coarse
    mesh and the prediction jumps by centimetres (measured on the SOFA liver). A prediction
    that ends with an element flattened below FLAT_VOLUME_RATIO of its rest volume is run once
    more with stuck vertices slipping where carrying them would flatten an element (`predict`).
    `body_acceleration` adds a uniform load to the configured gravity (the unmodelled load of
    core/physics/body_load.py). In "grasp" mode `grasped_vertices` follow the tool rigidly: at pose T
    they sit at T T0^-1 applied to their rest positions, T0 being the first tool pose (set by
    `reset`, or by the first `predict`).
    """

    def __init__(self, rest_mesh: TetMesh, config: SimulatorConfig, grasped_vertices=None):
        self.rest_mesh = rest_mesh
        self.config = config
        self.grasped_vertices = self._checked_grasp(grasped_vertices, rest_mesh, config)
        vertex_count = rest_mesh.vertex_count
        kinematic = np.zeros(vertex_count, dtype=bool)
        kinematic[rest_mesh.fixed_vertices] = True
        kinematic[self.grasped_vertices] = True
        self.movable_vertices = np.flatnonzero(~kinematic)

        tets = rest_mesh.tetrahedra
        rest_edges = rest_mesh.vertices[tets[:, 1:]] - rest_mesh.vertices[tets[:, :1]]  # rows = edges
        volumes = np.linalg.det(rest_edges) / 6.0
        rest_inverse = np.linalg.inv(np.transpose(rest_edges, (0, 2, 1)))  # Dm^-1, Dm columns = edges
        corner_gradient = _CORNER_FROM_EDGES @ rest_inverse  # (M, 4, 3) shape-function gradients
        corner_volumes = np.repeat(volumes / 4.0, 4)
        vertex_mass = config.density * np.bincount(tets.reshape(-1), corner_volumes, vertex_count)
        model = ElasticModel(rest_mesh.vertices, tets, config.youngs_modulus, config.poisson_ratio)
        self._body = _Body(rest_mesh, config, kinematic, self.movable_vertices, volumes, rest_inverse,
                           corner_gradient, vertex_mass, np.asarray(config.gravity, dtype=np.float64),
                           model.linear_stiffness_parts())
        self.solver: SimulatorSolver = SOLVER_STRATEGIES[config.solver](self._body)
        self._body_acceleration = np.zeros(3)
        self._first_pose: np.ndarray | None = None
        self._previous_pose: np.ndarray | None = None
        self._stuck: np.ndarray = np.zeros(0, dtype=np.int64)  # stuck at the end of the last prediction

    @staticmethod
    def _checked_grasp(grasped_vertices, rest_mesh: TetMesh, config: SimulatorConfig) -> np.ndarray:
        if config.tool_mode == "sphere":
            if grasped_vertices is not None and np.size(grasped_vertices):
                raise SimulatorInputError('grasped_vertices are only used with tool_mode="grasp"')
            return np.zeros(0, dtype=np.int64)
        if grasped_vertices is None or np.size(grasped_vertices) == 0:
            raise SimulatorInputError('tool_mode="grasp" needs a non-empty grasped_vertices set')
        raw = np.asarray(grasped_vertices)
        if not np.issubdtype(raw.dtype, np.integer):
            raise SimulatorInputError(f"grasped_vertices must be integer indices, got dtype {raw.dtype}")
        grasped = np.unique(raw.astype(np.int64).reshape(-1))
        if grasped[0] < 0 or grasped[-1] >= rest_mesh.vertex_count:
            raise SimulatorInputError(f"grasped_vertices out of range [0, {rest_mesh.vertex_count})")
        if np.intersect1d(grasped, rest_mesh.fixed_vertices).size:
            raise SimulatorInputError("grasped_vertices must not include fixed vertices")
        return grasped

    def remove_elements(self, removed_elements) -> bool:
        """Follow a cut: from the next prediction on, simulate the rest mesh without the element
        slots `removed_elements` (TetMesh.without_elements: slots of the uncut mesh, cumulative;
        those removed already may be repeated). The vertices left without an element are held
        where the state has them (they are no longer part of the body) and leave the grasped
        and stuck sets; the load, the Poisson ratio and the tool's poses are kept. Returns
        whether the topology changed. Raises, and changes nothing, InvalidMeshError for a slot
        out of range and NotPositiveDefiniteError for a cut that leaves a piece with rigid modes
        (core/geometry/topology.py: cut_elements removes such pieces too)."""
        mesh = self.rest_mesh.without_elements(removed_elements)
        if mesh is self.rest_mesh:
            return False
        grasped = None
        if self.config.tool_mode == "grasp":
            grasped = np.setdiff1d(self.grasped_vertices, mesh.invalid_vertices)
        cut = ElasticSimulator(mesh, self.config, grasped)
        cut.body_acceleration = self._body_acceleration
        cut._first_pose, cut._previous_pose = self._first_pose, self._previous_pose
        cut._stuck = np.setdiff1d(self._stuck, mesh.invalid_vertices)
        vars(self).clear()
        vars(self).update(vars(cut))
        return True

    @property
    def vertex_mass(self) -> np.ndarray:
        """Lumped mass (N,) of every vertex in kg (density times a quarter of each incident volume)."""
        return self._body.vertex_mass

    @property
    def body_acceleration(self) -> np.ndarray:
        """Uniform body acceleration (3,) in m/s^2 applied on top of the configured gravity: a
        load the model does not know, estimated from the estimates (core/physics/body_load.py)."""
        return self._body_acceleration.copy()

    @body_acceleration.setter
    def body_acceleration(self, acceleration) -> None:
        acceleration = np.asarray(acceleration, dtype=np.float64)
        if acceleration.shape != (3,) or not np.all(np.isfinite(acceleration)):
            raise SimulatorInputError(f"body_acceleration must be 3 finite numbers, got {acceleration!r}")
        self._body_acceleration = acceleration.copy()
        self.solver.set_gravity(self._body.gravity + acceleration)

    @property
    def poisson_ratio(self) -> float:
        """The Poisson ratio the simulator uses (config.poisson_ratio, or what
        core/physics/poisson_ratio.py set)."""
        return float(self.config.poisson_ratio)

    @poisson_ratio.setter
    def poisson_ratio(self, poisson_ratio: float) -> None:
        """Use another Poisson ratio from the next prediction on (the solver's moduli and rest
        factor follow); the load, the tool's poses and the stuck vertices are kept."""
        self.config = replace(self.config, poisson_ratio=float(poisson_ratio))
        self._body = replace(self._body, config=self.config)
        self.solver.set_material(self.config)
        if self.solver.rest_stiffness is not None:  # numeric only: K0's pattern does not change
            self.solver.rest_stiffness.refactor(self.config)

    @property
    def linear_stiffness_parts(self) -> tuple:
        """(A, B), the rest stiffness K0 = mu A + lambda B (3 N, 3 N) at any Lame parameters."""
        return self._body.stiffness_parts

    @property
    def stuck_vertices(self) -> np.ndarray:
        """Vertices stuck to the tool at the end of the last prediction (stick contact)."""
        return self._stuck.copy()

    def restart_rest_factor(self) -> None:
        """Predict from now on as a newly made simulator at the current moduli would: the global
        step leaves the factor of the Poisson ratio before the last change (RestFactor) for the
        current one. A new timeline (LearningSimulator.reset) starts so."""
        if self.solver.rest_stiffness is not None:
            self.solver.rest_stiffness.catch_up()

    def rest_response(self, forces: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """Displacements K0^-1 f of the movable dofs under forces (3 n,) or (3 n, k) on them, the
        other vertices held, and the movable ones in `held` too (a Schur complement on the
        factor, as the global step holds stuck vertices): the model's small-strain response."""
        if self.solver.rest_stiffness is None:
            self.solver.rest_stiffness = RestFactor(self._body)
        rows = np.flatnonzero(np.isin(self.movable_vertices, held)) if held is not None else _NO_ROWS
        response = self.solver.rest_stiffness.solve(forces, held_rows=rows)
        response[(3 * rows[:, None] + _DIAGONAL).reshape(-1)] = 0.0  # zero but for rounding
        return response

    def reset(self, tool_pose=None) -> None:
        """Set the tool's previous and first (grasp reference) pose and forget the stuck
        vertices; None forgets both poses."""
        self._stuck = np.zeros(0, dtype=np.int64)
        if tool_pose is None:
            self._first_pose = self._previous_pose = None
            return
        pose = _as_pose(tool_pose)
        self._first_pose = pose
        self._previous_pose = pose.copy()

    def place_tool(self, tool_pose) -> None:
        """Put the tool at `tool_pose` without a step (a pose stamped at or before the previous one,
        as a restarted stream's): the next `predict` moves it from there. The grasp reference (the
        first pose) is kept, so grasped vertices stay where the tool holds them; the stuck
        vertices are forgotten, as the jump breaks their contact. SimulatorInputError for an
        invalid pose."""
        pose = _as_pose(tool_pose)
        self._stuck = np.zeros(0, dtype=np.int64)
        self._previous_pose = pose

    def predict(self, previous_state, tool_pose, dt: float) -> np.ndarray:
        """State (N, 3) after the tool moves from its previous pose to `tool_pose` over dt seconds.

        vbd is quasi-static (dt only validated); xpbd integrates damped dynamics over dt.
        With stick contact, a prediction that ends with an element below FLAT_VOLUME_RATIO of
        its rest volume (or inverted) is run again with the stuck vertices slipping wherever
        carrying them would take an element below it (see `_carry_stuck_vertices`). Raises
        ElementInversionError if the result still has a non-positive element volume.
        """
        start = np.array(previous_state, dtype=np.float64, copy=True)
        if start.shape != (self.rest_mesh.vertex_count, 3) or not np.all(np.isfinite(start)):
            raise SimulatorInputError(
                f"previous_state must be finite with shape ({self.rest_mesh.vertex_count}, 3), "
                f"got {start.shape}"
            )
        if not (np.isfinite(dt) and dt > 0.0):
            raise SimulatorInputError(f"dt must be > 0, got {dt}")
        pose = _as_pose(tool_pose)
        if self._previous_pose is None:
            self.reset(pose)
        state = self._moved(start, pose, dt, slip=False)
        ratios = self._volume_ratios(state)
        if self._stuck_contact and not np.all(ratios >= FLAT_VOLUME_RATIO):  # NaN too
            state = self._moved(start, pose, dt, slip=True)
            ratios = self._volume_ratios(state)
        inverted = np.flatnonzero(~(ratios > 0.0))  # rest volumes are positive
        self._previous_pose = pose
        if inverted.size:
            raise ElementInversionError(inverted)
        self._stuck = self._touching(state, pose[:3], _CONTACT_BAND)
        return state

    def _volume_ratios(self, state: np.ndarray, elements=slice(None)) -> np.ndarray:
        """Volumes of `elements` at `state` over their rest volumes."""
        return signed_volumes(state, self.rest_mesh.tetrahedra[elements]) / self._body.volumes[elements]

    @property
    def _stuck_contact(self) -> bool:
        return self.config.tool_mode == "sphere" and self.config.tool_contact == "stick"

    def _moved(self, start: np.ndarray, pose: np.ndarray, dt: float, slip: bool) -> np.ndarray:
        """The tissue from `start` after the tool's sub-steps from its previous pose to `pose`;
        `slip`: stuck vertices whose carrying would invert an element slip instead."""
        state = start.copy()
        substeps = int(self.config.substeps)
        fractions = np.arange(1, substeps + 1) / substeps
        centres, rotations = self._interpolated_poses(self._previous_pose, pose, fractions)
        self.solver.begin(state)
        previous_centre = self._previous_pose[:3]
        self._restore_stuck_vertices(state, previous_centre, slip)
        for substep in range(substeps):
            if self.config.tool_mode == "grasp":
                state[self.grasped_vertices] = self._grasp_targets(centres[substep], rotations[substep])
            held = self._carry_stuck_vertices(state, previous_centre, centres[substep], slip)
            previous_centre = centres[substep]
            if self.movable_vertices.size == 0:
                continue
            self.solver.substep(state, dt / substeps, centres[substep], held)
        return state

    # ------------------------------------------------------------------------------ tool

    @staticmethod
    def _interpolated_poses(start_pose, end_pose, fractions):
        """Tool centres (S, 3) (linear) and rotation matrices (S, 3, 3) (slerp) at the sub-steps."""
        centres = start_pose[:3] + fractions[:, None] * (end_pose[:3] - start_pose[:3])
        key_rotations = Rotation.from_quat(np.stack([start_pose[3:], end_pose[3:]]))
        return centres, Slerp([0.0, 1.0], key_rotations)(fractions).as_matrix()

    def _grasp_targets(self, centre: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """Grasped vertex positions for a tool at (centre, rotation), rigid w.r.t. the first pose."""
        first_rotation = Rotation.from_quat(self._first_pose[3:]).as_matrix()
        anchors = self.rest_mesh.vertices[self.grasped_vertices] - self._first_pose[:3]
        return anchors @ (rotation @ first_rotation.T).T + centre

    def _touching(self, state: np.ndarray, centre, band: float) -> np.ndarray:
        """Movable vertices within band * tool_radius of the tool centre (stick contact only)."""
        if not self._stuck_contact:
            return np.zeros(0, dtype=np.int64)
        offsets = state[self.movable_vertices] - centre
        inside = np.einsum("ij,ij->i", offsets, offsets) <= (self.config.tool_radius * band) ** 2
        return self.movable_vertices[inside]

    def _restore_stuck_vertices(self, state: np.ndarray, centre, slip: bool) -> None:
        """Put the vertices stuck at the end of the last prediction back on the sphere, in
        place, where `state` has them within _CONTACT_MEMORY_BAND radii of its surface (with
        `slip`, not those whose move would invert an element)."""
        if self._stuck.size == 0:
            return
        offsets = state[self._stuck] - centre
        distances = np.sqrt(np.einsum("ij,ij->i", offsets, offsets))
        radius = self.config.tool_radius
        near = (np.abs(distances - radius) <= _CONTACT_MEMORY_BAND * radius) & (distances > 0.0)
        vertices = self._stuck[near]
        targets = centre + radius * offsets[near] / distances[near, None]
        kept = self._kept_moves(state, vertices, targets, slip)
        state[vertices[kept]] = targets[kept]

    def _carry_stuck_vertices(self, state: np.ndarray, previous_centre, centre, slip: bool) -> np.ndarray:
        """Stick contact: move the vertices touching the tool with it, in place; returns them (sorted).

        A vertex is released when the tool moves away from it (negative normal motion), and with
        `slip` also when moving it would take an element below FLAT_VOLUME_RATIO of its rest
        volume (`_kept_moves`): the tissue then slips on the tool instead of folding over it.
        `predict` slips only when a prediction without it ends with such an element: a sphere
        pushing into a coarse mesh can carry the stuck vertices of an element it has already
        flattened through the element's other corners, which the solvers cannot undo, while
        most carries that flatten an element for a moment are undone by the solvers'
        iterations, and slipping there would loosen the grip (measured in docs/design-notes.md,
        "Simulator contact").
        """
        touching = self._touching(state, previous_centre, _CONTACT_BAND)
        stuck = touching[(state[touching] - previous_centre) @ (centre - previous_centre) >= 0.0]
        targets = state[stuck] + (centre - previous_centre)
        kept = self._kept_moves(state, stuck, targets, slip)
        state[stuck[kept]] = targets[kept]
        return stuck[kept]

    def _kept_moves(self, state: np.ndarray, vertices: np.ndarray, targets: np.ndarray, slip: bool) -> np.ndarray:
        """Mask of the moves of `vertices` to `targets` (k, 3) to make: all of them, or with `slip`
        those that together take no incident element below FLAT_VOLUME_RATIO of its rest volume,
        nor one already below it further down (the moves of every corner of such an element are
        dropped, until there is none)."""
        keep = np.ones(vertices.size, dtype=bool)
        if not slip or vertices.size == 0:
            return keep
        tetrahedra = self.rest_mesh.tetrahedra
        moved = np.zeros(self.rest_mesh.vertex_count, dtype=bool)
        moved[vertices] = True
        incident_elements = np.flatnonzero(moved[tetrahedra].any(axis=1))
        incident = tetrahedra[incident_elements]
        before = self._volume_ratios(state, incident_elements)
        floor = np.minimum(before, FLAT_VOLUME_RATIO)  # an element below the floor may not shrink
        trial = state.copy()
        while keep.any():
            trial[vertices] = np.where(keep[:, None], targets, state[vertices])
            flattened = ~(self._volume_ratios(trial, incident_elements) >= floor)
            culprits = keep & np.isin(vertices, incident[flattened])
            if not culprits.any():
                break
            keep &= ~culprits
        return keep
