"""Estimate of the tissue's compressibility: the simulator's Poisson ratio, raised online.

Soft tissue is nearly incompressible (nu 0.45-0.5), and a tissue model is commonly given a lower
nu than the tissue's, as linear tetrahedra lock near 0.5. Pushed, a less compressible body
bulges more: away from the tool it moves where the model does not, on the hidden side too. The
factor graph corrects the visible surface, but the physics prior carries that correction to the
hidden side through the nominal stiffness, with the wrong sign there (docs/design-notes.md,
"The airway over its steps"). Only a prediction from the right compressibility moves the
hidden side right.

`PoissonRatioEstimate` fits, after each update, the change of nu whose small-strain response
best explains the update's correction (after the body load's share, core/body_load.py):

    S = dX/dnu = -K_ff^-1 (dK/dnu u)_f,    dnu = S . r / S . S

u is the prediction's displacement from rest, f the dofs of the vertices that move freely
(neither fixed, grasped nor stuck to the tool, whose positions the boundary prescribes), K the
rest stiffness (linear in the Lame parameters, so dK/dnu is exact), r the correction less the
load's. As the body load, it is an integrator: the next correction measures what nu still
misses.

The user's nu is a lower bound: the fit may only make the model less compressible, up to
CEILING. A free fit runs away where another mismatch (a leak, a tilted contact) looks like
a more compressible body in the first updates: on liver-push (truth 0.48) it ran from 0.45 to
0.30 and lost 1.1x of the simulation alone. The bound is applied to what the simulator uses,
not to the integrator: clipping the integrator itself would ratchet noise upward (a noisy
increment below the bound is lost, one above it kept), while a sum kept within the physical
range [FLOOR, CEILING] and used as max(sum, nominal) lets noise cancel.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.fem import ElasticModel, lame_parameters
from meshfg_ros.core.simulator import ElasticSimulator
from meshfg_ros.core.sparse_cholesky import SparseCholesky

__all__ = ["CEILING", "FLOOR", "PoissonRatioEstimate"]

# Below 0.5, where lambda diverges; the simulator's volumetric term stays well conditioned.
CEILING = 0.49
# The integrator's lower limit (anti-windup): no soft tissue is this compressible.
FLOOR = 0.30


class PoissonRatioEstimate:
    """The Poisson ratio of `simulator`, raised from (prediction, correction) pairs (module
    docstring); the user's nu stays its lower bound."""

    def __init__(self, simulator: ElasticSimulator):
        self.simulator = simulator
        self.nominal = float(simulator.poisson_ratio)
        mesh = simulator.rest_mesh
        self._rest = mesh.vertices
        self._kinematic = np.setdiff1d(np.arange(mesh.vertex_count), simulator.movable_vertices)
        # K = mu A + lambda B: A the rest stiffness at (mu, lambda) = (1, 0) (E 2, nu 0), B at (0, 1).
        self._shear = ElasticModel(mesh.vertices, mesh.tetrahedra, 2.0, 0.0).stiffness(kind="linear").tocsr()
        unit_both = ElasticModel(mesh.vertices, mesh.tetrahedra, 2.5, 0.25).stiffness(kind="linear").tocsr()
        self._volumetric = unit_both - self._shear
        self._sum = self.nominal

    @property
    def poisson_ratio(self) -> float:
        """The Poisson ratio the simulator uses now."""
        return float(self.simulator.poisson_ratio)

    def sensitivity(self, predicted: np.ndarray) -> np.ndarray:
        """dX/dnu (N, 3) of the small-strain equilibrium at the prediction's displacement, the
        fixed, grasped and stuck vertices held (zero rows)."""
        youngs, nu = self.simulator.config.youngs_modulus, self.simulator.poisson_ratio
        mu, lam = lame_parameters(youngs, nu)
        d_mu = -youngs / (2.0 * (1.0 + nu) ** 2)
        d_lambda = youngs * (1.0 + 2.0 * nu**2) / ((1.0 + nu) ** 2 * (1.0 - 2.0 * nu) ** 2)
        held = np.zeros(len(self._rest), dtype=bool)
        held[self._kinematic] = True
        held[self.simulator.stuck_vertices] = True
        free = np.flatnonzero(~held)
        sensitivity = np.zeros_like(self._rest)
        if free.size == 0:
            return sensitivity
        dofs = (3 * free[:, None] + np.arange(3)).reshape(-1)
        displacement = (predicted - self._rest).reshape(-1)
        force = -(d_mu * (self._shear @ displacement) + d_lambda * (self._volumetric @ displacement))[dofs]
        stiffness = (mu * self._shear + lam * self._volumetric)[dofs][:, dofs]
        sensitivity.reshape(-1)[dofs] = SparseCholesky(stiffness, node_size=3).solve(force)
        return sensitivity

    def update(self, predicted: np.ndarray, correction: np.ndarray) -> float:
        """Add the change of nu that explains `correction` (N, 3: the estimate less the
        prediction, less the body load's response) at `predicted` (N, 3); returns the
        Poisson ratio the simulator uses from now on."""
        sensitivity = self.sensitivity(predicted)
        energy = float(np.einsum("ij,ij->", sensitivity, sensitivity))
        if energy > 0.0:
            step = float(np.einsum("ij,ij->", sensitivity, correction)) / energy
            self._sum = float(np.clip(self._sum + step, FLOOR, CEILING))
        applied = max(self._sum, self.nominal)
        if applied != self.simulator.poisson_ratio:
            self.simulator.poisson_ratio = applied
        return applied

    def reset(self) -> None:
        """Back to the user's nu (a new timeline starts from the initial mesh)."""
        self._sum = self.nominal
        if self.simulator.poisson_ratio != self.nominal:
            self.simulator.poisson_ratio = self.nominal
