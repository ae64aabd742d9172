"""Ground-truth solver: static equilibrium of a heterogeneous compressible neo-Hookean solid.

Energy density (the classic compressible neo-Hookean law, e.g. Bonet & Wood, Nonlinear
Continuum Mechanics for FEA, eq. 6.27), per element with its own (mu, lambda):
    Psi(F) = mu/2 (I_C - 3) - mu ln J + lambda/2 (ln J)^2,   I_C = tr(F^T F),  J = det F,
    P(F)   = mu (F - F^-T) + lambda ln J F^-T                  (first Piola-Kirchhoff stress),
    dP[dF] = mu dF + (mu - lambda ln J) F^-T dF^T F^-T + lambda (F^-T : dF) F^-T.
At F = I the tangent is small-strain elasticity with Lame parameters (mu, lambda). This is not
the estimator's stable Neo-Hookean energy (core/physics/simulator.py, core/physics/fem.py): its volumetric
term grows without bound as J -> 0 (no element can invert at finite energy) and differs from
the estimator's at finite strain, so the mismatch scenes' truth departs from the estimator's
model in its constitutive law as well as in its parameters.

P1 tetrahedra in float64. The element integrals are scikit-fem forms written with
skfem.helpers: the residual as a LinearForm, the tangent as a BilinearForm and the energy as
a Functional, with mu and lambda passed as P0 (one value per element) fields. Loads:
- fixed vertices held at their rest positions (Dirichlet);
- a uniform body force density b [N/m^3] (gravity rho g, or an unmodelled pull), as
  consistent nodal loads: the total energy is sum_e V_e Psi(F_e) - f_b . u;
- a rigid sphere tool with sticky contact (`StickySphereContact`): a free vertex the sphere
  reaches is projected onto its surface and from then on moves rigidly with the tool.

Newton's method on the free dofs with a backtracking line search on the total energy that
never accepts a state with a non-positive element volume (the energy is +inf there). A step
that moves prescribed vertices to new targets also solves K_ff dx_f = -r_f - K_fp dx_p, and
is only shortened, until no element inverts. Converged when the free-dof force residual is at
most RELATIVE_FORCE_TOLERANCE times the external force (body loads and reactions) plus a
small absolute floor; EquilibriumError otherwise.

The Newton loop, the line search and the contact active set are hand-written: scikit-fem
provides assembly (and linear `solve`/`condense`), not nonlinear solvers, and no FEM library
offers sticky (adhesive) rigid-sphere contact with an active set; the rigid-sphere contact
that exists (e.g. SfePy's penalty term) is frictionless and penalty-based, which would let
the tissue slide off the tool and make the truth depend on a penalty parameter.

Cost per evaluation, measured on this 2-core machine (shared with other jobs) on the
slab-inclusion mesh (1,532 vertices, 6,347 elements): residual 15 ms, energy 3 ms, tangent
44 ms (38 ms in scikit-fem's BilinearForm, 144 form evaluations over all elements, one per pair
of the 12 local dofs, and 6 ms to sum its element entries into a cached CSR pattern, against
20 ms for scikit-fem's own COO-to-CSR step); the Newton direction about 13 ms (a Cholesky
refactor of the free-dof tangent and its solve, `_symmetric_solve`). A ten-step scene's truth
(4 sub-steps, 1-3 contact rounds each, about 3 Newton iterations per solve) takes about 12 s,
well within a scene's budget, so scikit-fem stays in the hot path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import skfem
from skfem.helpers import ddot, det, grad, identity, inv, mul, transpose

from meshfg_ros.core.geometry.mesh import TetMesh, inverted_elements, signed_volumes
from meshfg_ros.core.solvers.sparse_cholesky import NotPositiveDefiniteError, SparseCholesky

__all__ = [
    "Equilibrium",
    "EquilibriumError",
    "HyperelasticInputError",
    "NeoHookeanSolid",
    "StickySphereContact",
    "lame_fields",
]

RELATIVE_FORCE_TOLERANCE = 1e-8
# Absolute floor of the force tolerance, as a fraction of mean(mu) * (mean edge)^2 (the force
# of unit strain on one element): binds only when the external force (nearly) vanishes.
ABSOLUTE_FORCE_TOLERANCE = 1e-12
MAX_NEWTON_ITERATIONS = 60
MAX_STEP_HALVINGS = 40
ARMIJO_SLOPE = 1e-4
# Energy rise that the line search accepts as rounding, relative to the size of the energy's
# terms (sum_e V_e (mu_e + lambda_e): each element's I_C and ln J terms are of that order, however
# small the strain): near convergence a Newton step changes the energy by less than its
# rounding error.
ENERGY_ROUNDING = 1e-14
# Diagonal shifts (times the mean diagonal of the free-dof tangent) tried in turn when the
# Newton direction is not a descent direction (the tangent is indefinite under compression).
TANGENT_SHIFTS = (1e-6, 1e-4, 1e-2, 1.0)
MAX_CONTACT_ROUNDS = 100
# A free vertex closer than (1 - this) tool radii to the tool centre penetrates the tool.
CONTACT_TOLERANCE = 1e-9


class HyperelasticInputError(ValueError):
    """A material, load, state or prescribed-vertex argument of the wrong shape or value."""


class EquilibriumError(RuntimeError):
    """Newton, its line search or the contact active set did not converge."""


def lame_fields(youngs_modulus, poisson_ratio, element_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-element Lame parameters (mu, lambda), each (element_count,), from E [Pa] and nu
    given as scalars or per-element arrays."""
    youngs = np.broadcast_to(np.asarray(youngs_modulus, dtype=np.float64), (element_count,))
    poisson = np.broadcast_to(np.asarray(poisson_ratio, dtype=np.float64), (element_count,))
    if not (np.all(np.isfinite(youngs)) and np.all(youngs > 0.0)):
        raise HyperelasticInputError("youngs_modulus must be finite and > 0 in every element")
    if not np.all((poisson > -1.0) & (poisson < 0.5)):
        raise HyperelasticInputError("poisson_ratio must lie in (-1, 0.5) in every element")
    mu = youngs / (2.0 * (1.0 + poisson))
    lam = youngs * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu.copy(), lam.copy()


# ------------------------------------------------------------------------ scikit-fem forms


def _deformation_gradient(displacement) -> np.ndarray:
    """F = I + grad u at the quadrature points, (3, 3, M, Q)."""
    displacement_gradient = grad(displacement)
    return identity(displacement_gradient) + displacement_gradient


@skfem.Functional
def _energy_density(w):
    deformation = _deformation_gradient(w["u"])
    log_volume_ratio = np.log(det(deformation))
    return (0.5 * w["mu"] * (ddot(deformation, deformation) - 3.0) - w["mu"] * log_volume_ratio
            + 0.5 * w["lam"] * log_volume_ratio**2)


@skfem.LinearForm
def _internal_force(v, w):
    deformation = _deformation_gradient(w["u"])
    inverse_transpose = transpose(inv(deformation))
    stress = w["mu"] * (deformation - inverse_transpose) + w["lam"] * np.log(det(deformation)) * inverse_transpose
    return ddot(stress, grad(v))


@skfem.BilinearForm
def _tangent_form(du, v, w):
    # F^-T and mu - lambda ln J come precomputed (NeoHookeanSolid.tangent), once per assembly
    # rather than once per pair of local dofs: this form is evaluated 144 times per assembly.
    inverse_transpose = w["inverse_transpose"]
    trial, test = grad(du), grad(v)
    return (w["mu"] * ddot(trial, test)
            + w["geometric"] * ddot(mul(mul(inverse_transpose, transpose(trial)), inverse_transpose), test)
            + w["lam"] * ddot(inverse_transpose, trial) * ddot(inverse_transpose, test))


def _unit_load(axis: int) -> skfem.LinearForm:
    """Consistent nodal loads of a unit body force density along `axis`."""
    return skfem.LinearForm(lambda v, _: v[axis])


@dataclass(frozen=True)
class Equilibrium:
    """A converged solve: positions (N, 3), Newton iterations, free-dof force residual norm
    [N] and the tolerance it met."""

    positions: np.ndarray
    iterations: int
    residual_norm: float
    tolerance: float


class NeoHookeanSolid:
    """P1 compressible neo-Hookean solid on the mesh `mesh` (its fixed vertices stay put where
    `mesh` has them, and so do the invalid vertices of a cut mesh, which no element uses).

    youngs_modulus [Pa] and poisson_ratio: scalars or per-element arrays (M,). rest_vertices
    (N, 3): the stress-free shape, `mesh.vertices` by default; another one pre-stresses the
    tissue held at `mesh`'s fixed vertices (tissue under tension, which a cut lets retract).
    Positions are (N, 3) float64 arrays; force vectors are (3N,) in the order x0 y0 z0 x1 ...
    """

    def __init__(self, mesh: TetMesh, youngs_modulus, poisson_ratio, rest_vertices=None):
        self.mesh = mesh
        self.rest_vertices = mesh.vertices if rest_vertices is None else np.asarray(rest_vertices, dtype=np.float64)
        if self.rest_vertices.shape != mesh.vertices.shape or not np.all(np.isfinite(self.rest_vertices)):
            raise HyperelasticInputError(f"rest_vertices must be finite with shape {mesh.vertices.shape}")
        self.tetrahedra = mesh.tetrahedra
        self.mu, self.lam = lame_fields(youngs_modulus, poisson_ratio, mesh.tetrahedron_count)
        self.rest_volumes = signed_volumes(self.rest_vertices, mesh.tetrahedra)
        if not np.all(self.rest_volumes > 0.0):
            raise HyperelasticInputError("rest_vertices give an element a non-positive volume")
        fem_mesh = skfem.MeshTet(np.ascontiguousarray(self.rest_vertices.T), np.ascontiguousarray(mesh.tetrahedra.T))
        # One quadrature point: P1 gradients are constant per element, so every integrand is.
        self._basis = skfem.Basis(fem_mesh, skfem.ElementVector(skfem.ElementTetP1()), intorder=1)
        material_basis = self._basis.with_element(skfem.ElementTetP0())
        self._mu_field = material_basis.interpolate(self.mu)
        self._lam_field = material_basis.interpolate(self.lam)
        self._unit_loads = np.stack([_unit_load(axis).assemble(self._basis) for axis in range(3)])  # (3, 3N)
        corners = self.rest_vertices[mesh.tetrahedra]
        mean_edge = float(np.linalg.norm(corners[:, 1:] - corners[:, :1], axis=2).mean())
        self.force_floor = ABSOLUTE_FORCE_TOLERANCE * float(self.mu.mean()) * mean_edge**2
        self._energy_rounding = ENERGY_ROUNDING * float(self.rest_volumes @ (self.mu + self.lam))
        self._tangent_pattern: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # The last free-dof tangent's Cholesky factor: the Newton steps of one set of held
        # vertices share its pattern, so they refactor it without a new ordering and analysis.
        self._tangent_factor: SparseCholesky | None = None

    @property
    def vertex_count(self) -> int:
        return self.mesh.vertex_count

    # ---------------------------------------------------------------------- evaluations

    def _checked_positions(self, positions) -> np.ndarray:
        array = np.asarray(positions, dtype=np.float64)
        if array.shape != (self.vertex_count, 3) or not np.all(np.isfinite(array)):
            raise HyperelasticInputError(f"positions must be finite with shape ({self.vertex_count}, 3), "
                                         f"got {array.shape}")
        return array

    def _displacement(self, positions) -> np.ndarray:
        return (self._checked_positions(positions) - self.rest_vertices).reshape(-1)

    def _require_positive_volumes(self, positions: np.ndarray) -> None:
        inverted = inverted_elements(positions, self.tetrahedra)
        if inverted.size:
            raise HyperelasticInputError(f"{inverted.size} elements have non-positive volume, first {inverted[0]}")

    def body_load(self, body_force) -> np.ndarray:
        """Consistent nodal forces (3N,) of a uniform body force density (3,) [N/m^3]."""
        force = np.asarray(body_force, dtype=np.float64)
        if force.shape != (3,) or not np.all(np.isfinite(force)):
            raise HyperelasticInputError(f"body_force must be 3 finite numbers, got shape {force.shape}")
        return force @ self._unit_loads

    def elastic_energy(self, positions) -> float:
        """Strain energy sum_e V_e Psi(F_e) [J]; +inf where an element volume is not positive."""
        positions = self._checked_positions(positions)
        if not np.all(signed_volumes(positions, self.tetrahedra) > 0.0):
            return np.inf
        displacement = (positions - self.rest_vertices).reshape(-1)
        return float(_energy_density.assemble(self._basis, u=displacement, mu=self._mu_field, lam=self._lam_field))

    def energy(self, positions, body_force=(0.0, 0.0, 0.0)) -> float:
        """Total potential energy [J]: strain energy minus the body force's work on the displacement."""
        return self.elastic_energy(positions) - float(self.body_load(body_force) @ self._displacement(positions))

    def residual(self, positions, body_force=(0.0, 0.0, 0.0)) -> np.ndarray:
        """dE/dx (3N,): internal forces minus body loads (the reactions on prescribed dofs)."""
        positions = self._checked_positions(positions)
        self._require_positive_volumes(positions)
        displacement = (positions - self.rest_vertices).reshape(-1)
        internal = _internal_force.assemble(self._basis, u=displacement, mu=self._mu_field, lam=self._lam_field)
        return internal - self.body_load(body_force)

    def tangent(self, positions) -> scipy.sparse.csr_matrix:
        """d residual / dx, (3N, 3N) CSR, symmetric: the scikit-fem BilinearForm's element
        entries summed into the mesh's CSR pattern."""
        positions = self._checked_positions(positions)
        self._require_positive_volumes(positions)
        deformation = _deformation_gradient(self._basis.interpolate((positions - self.rest_vertices).reshape(-1)))
        geometric = self._mu_field - self._lam_field * np.log(det(deformation))
        elemental = _tangent_form.elemental(
            self._basis, inverse_transpose=transpose(inv(deformation)), geometric=geometric,
            mu=self._mu_field, lam=self._lam_field,
        )
        if self._tangent_pattern is None:
            self._tangent_pattern = self._csr_pattern(elemental.indices)
        slots, columns, row_starts = self._tangent_pattern
        size = 3 * self.vertex_count
        values = np.bincount(slots, weights=elemental.data, minlength=columns.size)
        return scipy.sparse.csr_matrix((values, columns, row_starts), shape=(size, size))

    def _csr_pattern(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """CSR slot of every element-matrix entry (rows, columns as scikit-fem lists them), and
        the CSR column indices and row starts: summing entries into slots with one bincount
        takes 5-8 ms against 35-45 ms for scikit-fem's COO-to-CSR conversion of the same data."""
        size = 3 * self.vertex_count
        keys = indices[0].astype(np.int64) * size + indices[1]
        unique_keys, slots = np.unique(keys, return_inverse=True)
        row_starts = np.searchsorted(unique_keys // size, np.arange(size + 1))
        return slots.reshape(-1), unique_keys % size, row_starts

    # ------------------------------------------------------------------------ equilibrium

    def equilibrium(self, start, prescribed_vertices=(), prescribed_positions=None,
                    body_force=(0.0, 0.0, 0.0)) -> Equilibrium:
        """Static equilibrium from `start` (N, 3) with the mesh's fixed vertices where it has them, the
        `prescribed_vertices` (P,) at `prescribed_positions` (P, 3) and the body force density.

        Raises EquilibriumError if Newton does not converge in MAX_NEWTON_ITERATIONS.
        """
        positions = self._checked_positions(start).copy()
        self._require_positive_volumes(positions)
        held, targets = self._dirichlet(prescribed_vertices, prescribed_positions)
        held_dofs = (3 * held[:, None] + np.arange(3)).reshape(-1)
        is_free = np.ones(3 * self.vertex_count, dtype=bool)
        is_free[held_dofs] = False
        free_dofs = np.flatnonzero(is_free)
        load = self.body_load(body_force)
        load_norm_squared = float(load @ load)
        residual_norm = np.inf
        for iteration in range(MAX_NEWTON_ITERATIONS + 1):
            gradient = self.residual(positions, body_force)
            gap = (targets - positions[held]).reshape(-1)
            reactions = gradient[held_dofs]
            tolerance = (RELATIVE_FORCE_TOLERANCE * np.sqrt(load_norm_squared + float(reactions @ reactions))
                         + self.force_floor)
            residual_norm = float(np.linalg.norm(gradient[free_dofs]))
            lifting = bool(np.any(gap != 0.0))
            if not lifting and residual_norm <= tolerance:
                return Equilibrium(positions, iteration, residual_norm, tolerance)
            if iteration == MAX_NEWTON_ITERATIONS:
                break
            tangent = self.tangent(positions)
            step = np.zeros(3 * self.vertex_count)
            step[held_dofs] = gap
            free_rows = tangent[free_dofs]
            right_hand_side = -gradient[free_dofs] - free_rows[:, held_dofs] @ gap
            free_tangent = free_rows[:, free_dofs].tocsc()
            step[free_dofs] = self._descent_direction(free_tangent, right_hand_side, gradient[free_dofs], lifting)
            fraction = self._line_search(positions, step.reshape(-1, 3), gradient, body_force, lifting)
            positions = positions + fraction * step.reshape(-1, 3)
            if lifting and fraction == 1.0:
                positions[held] = targets  # exactly, not up to the rounding of the step
        raise EquilibriumError(f"Newton did not converge in {MAX_NEWTON_ITERATIONS} iterations "
                               f"(free-dof residual {residual_norm:.3g} N)")

    def _dirichlet(self, prescribed_vertices, prescribed_positions) -> tuple[np.ndarray, np.ndarray]:
        """All held vertices (fixed, then prescribed) and their targets (H, 3)."""
        prescribed = np.asarray(prescribed_vertices, dtype=np.int64).reshape(-1)
        if prescribed.size and (prescribed.min() < 0 or prescribed.max() >= self.vertex_count):
            raise HyperelasticInputError(f"prescribed_vertices out of range [0, {self.vertex_count})")
        if np.unique(prescribed).size != prescribed.size or np.intersect1d(prescribed, self.mesh.fixed_vertices).size:
            raise HyperelasticInputError("prescribed_vertices must be unique and not fixed")
        positions = np.zeros((0, 3)) if prescribed_positions is None else prescribed_positions
        positions = np.asarray(positions, dtype=np.float64)
        if positions.shape != (prescribed.size, 3) or not np.all(np.isfinite(positions)):
            raise HyperelasticInputError(f"prescribed_positions must be finite with shape ({prescribed.size}, 3), "
                                         f"got {positions.shape}")
        fixed = self.mesh.fixed_vertices
        return np.concatenate([fixed, prescribed]), np.concatenate([self.mesh.vertices[fixed], positions])

    def _descent_direction(self, free_tangent, right_hand_side, free_gradient, lifting: bool) -> np.ndarray:
        """K_ff^-1 rhs, with K_ff shifted by TANGENT_SHIFTS in turn while (on a step that holds
        every prescribed vertex) the result is not a descent direction of the energy."""
        diagonal_scale = float(free_tangent.diagonal().mean())
        identity_matrix = scipy.sparse.identity(free_tangent.shape[0], format="csc")
        for shift in (0.0, *TANGENT_SHIFTS):
            matrix = free_tangent + shift * diagonal_scale * identity_matrix if shift else free_tangent
            direction = self._symmetric_solve(matrix, right_hand_side)
            if lifting or float(free_gradient @ direction) < 0.0:
                return direction
        raise EquilibriumError("no descent direction: the tangent stays indefinite after the largest shift")

    def _symmetric_solve(self, matrix: scipy.sparse.spmatrix, right_hand_side: np.ndarray) -> np.ndarray:
        """matrix^-1 rhs for a symmetric free-dof tangent (whole vertices: its dofs come in x, y,
        z triples): by sparse Cholesky (CHOLMOD) where it is positive definite (at most Newton
        steps), else by SuperLU's LU, which also solves an indefinite tangent (a lifting step
        takes its direction whatever the energy's slope). The ten-step truths of liver-gravity and
        slab-inclusion (124 and 122 directions, about 3,900 and 3,700 free dofs) took 2.1 and
        1.6 s for their directions against 9.1 and 7.2 s with SuperLU alone, and the same
        positions to 3e-17 m."""
        csr = scipy.sparse.csr_matrix(matrix)
        csr.sort_indices()
        try:
            factor = self._tangent_factor
            if factor is not None and factor.same_pattern(csr):
                factor.refactor(csr.data)
            else:
                factor = self._tangent_factor = SparseCholesky(csr, node_size=3)
            return factor.solve(right_hand_side)
        except NotPositiveDefiniteError:
            factor = scipy.sparse.linalg.splu(csr.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                              options={"SymmetricMode": True})
            return factor.solve(right_hand_side)

    def _line_search(self, positions, step, gradient, body_force, lifting: bool) -> float:
        """Largest fraction 2^-k of `step` that keeps every volume positive and, when no
        prescribed vertex moves, satisfies Armijo's condition on the total energy."""
        if lifting:
            energy = slope = 0.0
        else:
            energy, slope = self.energy(positions, body_force), float(gradient @ step.reshape(-1))
        fraction = 1.0
        for _ in range(MAX_STEP_HALVINGS):
            trial = positions + fraction * step
            if np.all(signed_volumes(trial, self.tetrahedra) > 0.0):
                decrease = ARMIJO_SLOPE * fraction * slope
                if lifting or self.energy(trial, body_force) <= energy + decrease + self._energy_rounding:
                    return fraction
            fraction *= 0.5
        raise EquilibriumError(f"line search found no acceptable step in {MAX_STEP_HALVINGS} halvings")


class StickySphereContact:
    """Quasi-static loading history of a `NeoHookeanSolid` touched by a sticky rigid sphere.

    State: the current positions, the tool centre and body force of the last solve, and the
    attached vertices with their offsets from the tool centre. `advance(centre, body_force)`
    moves the tool (a translation) and ramps the body force linearly over `substeps`
    increments; at each it solves equilibrium with the attached vertices prescribed at
    centre + offset, then attaches every free vertex inside the sphere after projecting it
    radially onto the surface, and solves again until no free vertex penetrates. Attached
    vertices stay attached (adhesive, no release).
    """

    def __init__(self, solid: NeoHookeanSolid, tool_radius: float, tool_centre, substeps: int = 4,
                 body_force=(0.0, 0.0, 0.0)):
        if not (np.isfinite(tool_radius) and tool_radius > 0.0):
            raise HyperelasticInputError(f"tool_radius must be > 0, got {tool_radius}")
        if int(substeps) != substeps or substeps < 1:
            raise HyperelasticInputError(f"substeps must be an integer >= 1, got {substeps}")
        self.solid = solid
        self.tool_radius = float(tool_radius)
        self.substeps = int(substeps)
        self.tool_centre = self._checked_vector("tool_centre", tool_centre)
        self.body_force = self._checked_vector("body_force", body_force)
        self.positions = solid.mesh.vertices.copy()
        self.attached_vertices = np.zeros(0, dtype=np.int64)
        self._attached_offsets = np.zeros((0, 3))
        self._movable = self._movable_of(solid)

    @staticmethod
    def _movable_of(solid: NeoHookeanSolid) -> np.ndarray:
        is_movable = np.ones(solid.vertex_count, dtype=bool)
        is_movable[solid.mesh.fixed_vertices] = False
        return is_movable

    def cut(self, solid: NeoHookeanSolid) -> None:
        """Go on with `solid`, the same body after a cut (its mesh without the removed elements,
        the vertices left without one held): the positions are kept, the attached vertices that
        became invalid let go; the next `advance` finds the equilibrium the cut allows."""
        if solid.vertex_count != self.solid.vertex_count:
            raise HyperelasticInputError("a cut keeps the vertices: the solid must have as many")
        keep = ~np.isin(self.attached_vertices, solid.mesh.fixed_vertices)
        self.attached_vertices, self._attached_offsets = self.attached_vertices[keep], self._attached_offsets[keep]
        self.solid = solid
        self._movable = self._movable_of(solid)

    @staticmethod
    def _checked_vector(name: str, value) -> np.ndarray:
        vector = np.asarray(value, dtype=np.float64)
        if vector.shape != (3,) or not np.all(np.isfinite(vector)):
            raise HyperelasticInputError(f"{name} must be 3 finite numbers, got shape {vector.shape}")
        return vector

    def advance(self, tool_centre, body_force=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Equilibrium positions (N, 3) after the tool moves to `tool_centre` under `body_force`."""
        end_centre = self._checked_vector("tool_centre", tool_centre)
        end_force = self._checked_vector("body_force", body_force)
        start_centre, start_force = self.tool_centre, self.body_force
        for fraction in np.arange(1, self.substeps + 1) / self.substeps:
            centre = start_centre + fraction * (end_centre - start_centre)
            force = start_force + fraction * (end_force - start_force)
            self._settle(centre, force)
        self.tool_centre, self.body_force = end_centre, end_force
        return self.positions.copy()

    def _settle(self, centre: np.ndarray, body_force: np.ndarray) -> None:
        """Equilibrium with the tool at `centre`, attaching penetrating vertices until none is left."""
        for _ in range(MAX_CONTACT_ROUNDS):
            result = self.solid.equilibrium(self.positions, self.attached_vertices,
                                            centre + self._attached_offsets, body_force)
            self.positions = result.positions
            penetrating = self.penetrating_vertices(centre)
            if penetrating.size == 0:
                return
            offsets = self.positions[penetrating] - centre
            distances = np.maximum(np.linalg.norm(offsets, axis=1), np.finfo(float).tiny)
            vertices = np.concatenate([self.attached_vertices, penetrating])
            order = np.argsort(vertices)
            self.attached_vertices = vertices[order]
            self._attached_offsets = np.concatenate(
                [self._attached_offsets, self.tool_radius * offsets / distances[:, None]])[order]
        raise EquilibriumError(f"contact active set still growing after {MAX_CONTACT_ROUNDS} rounds")

    def penetrating_vertices(self, centre) -> np.ndarray:
        """Movable vertices, not attached, closer than (1 - CONTACT_TOLERANCE) radii to `centre`."""
        candidates = self._movable.copy()
        candidates[self.attached_vertices] = False
        offsets = self.positions - np.asarray(centre, dtype=np.float64)
        inside = np.einsum("ij,ij->i", offsets, offsets) < (self.tool_radius * (1.0 - CONTACT_TOLERANCE)) ** 2
        return np.flatnonzero(candidates & inside)
