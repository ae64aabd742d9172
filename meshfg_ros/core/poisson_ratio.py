"""Estimate of the tissue's compressibility: the simulator's Poisson ratio, raised online.

Soft tissue is nearly incompressible (nu 0.45-0.5), and a tissue model is commonly given a lower
nu than the tissue's, as linear tetrahedra lock near 0.5. Pushed, a less compressible body
bulges more: away from the tool it moves where the model does not, on the hidden side too. The
factor graph corrects the visible surface, but the physics prior carries that correction to the
hidden side through the nominal stiffness, with the wrong sign there (docs/design-notes.md,
"The airway over its steps"). Only a prediction from the right compressibility moves the
hidden side right.

`PoissonRatioEstimate` fits, after each update, the change of nu whose small-strain response
best explains the update's correction (after the body load's share, core/body_load.py) where
the measurements see it: along the surface normals, each surface vertex weighted by the
estimate's information about it, 1 / position_std^2 (core/estimator.py):

    S = dX/dnu = -K_ff^-1 (dK/dnu u)_f,    dnu = sum_v w_v (n_v . S_v)(n_v . r_v) / sum_v w_v (n_v . S_v)^2

u is the prediction's displacement from rest, f the dofs of the vertices that move freely
(neither fixed, grasped nor stuck to the tool, whose positions the boundary prescribes), K the
rest stiffness (linear in the Lame parameters, so dK/dnu is exact), r the correction less the
load's, n_v the vertex normal. A point-to-surface factor measures the normal component only;
the tangential and hidden parts of a correction are the prior's extension of it through the
model being fitted, and fitting them reads noise as a change of nu (on the cube of the accuracy
suite, whose corrections are noise, the whole correction gave excursions of +0.002 that cost it
up to 7 %; its normal components consistently ask for less than the user's nu). As the body
load, it is an integrator: the next correction measures what nu still misses.

The user's nu is a lower bound: the fit may only make the model less compressible, up to
CEILING. Where another mismatch (a stiff inclusion, a tilted contact, a load) looks like a more
compressible body, a free fit runs towards FLOOR and loses (liver-push went from 0.45 to 0.30 and
lost 1.1x of the simulation alone). The bound is applied to what the simulator uses, not to the
integrator: clipping the integrator itself would ratchet noise upward (a noisy increment below
the bound is lost, one above it kept), while a sum kept within [FLOOR, CEILING] and used as
max(sum, nominal) lets noise cancel.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.simulator import ElasticSimulator

__all__ = ["CEILING", "FLOOR", "PoissonRatioEstimate"]

# Below 0.5, where lambda diverges; the simulator's volumetric term stays well conditioned.
CEILING = 0.49
# The integrator's lower limit (anti-windup): no soft tissue is this compressible.
FLOOR = 0.30


class PoissonRatioEstimate:
    """The Poisson ratio of `simulator`, raised from (prediction, correction, posterior std)
    triples (module docstring); the user's nu stays its lower bound."""

    def __init__(self, simulator: ElasticSimulator):
        self.simulator = simulator
        self.nominal = float(simulator.poisson_ratio)
        self._mesh = simulator.rest_mesh
        self._movable = simulator.movable_vertices
        self._movable_dofs = (3 * self._movable[:, None] + np.arange(3)).reshape(-1)
        self._sum = self.nominal

    @property
    def poisson_ratio(self) -> float:
        """The Poisson ratio the simulator uses now."""
        return float(self.simulator.poisson_ratio)

    def sensitivity(self, predicted: np.ndarray) -> np.ndarray:
        """dX/dnu (N, 3) of the small-strain equilibrium at the prediction's displacement, the
        fixed, grasped and stuck vertices held (zero rows)."""
        youngs, nu = self.simulator.config.youngs_modulus, self.simulator.poisson_ratio
        d_mu = -youngs / (2.0 * (1.0 + nu) ** 2)
        d_lambda = youngs * (1.0 + 2.0 * nu**2) / ((1.0 + nu) ** 2 * (1.0 - 2.0 * nu) ** 2)
        displacement = (predicted - self._mesh.vertices).reshape(-1)
        shear, volumetric = self.simulator.linear_stiffness_parts  # K = mu A + lambda B: dK/dnu exact
        force = -(d_mu * (shear @ displacement) + d_lambda * (volumetric @ displacement))
        sensitivity = np.zeros_like(predicted)
        if self._movable.size:
            sensitivity[self._movable] = self.simulator.rest_response(
                force[self._movable_dofs], held=self.simulator.stuck_vertices).reshape(-1, 3)
        return sensitivity

    def update(self, predicted: np.ndarray, correction: np.ndarray, position_std: np.ndarray) -> float:
        """Add the change of nu that explains `correction` (N, 3: the estimate less the
        prediction, less the body load's response) at `predicted` (N, 3), each surface vertex
        weighted by 1 / `position_std`^2 (N,; zero std: a vertex the estimate does not move,
        left out); returns the Poisson ratio the simulator uses from now on."""
        normals = self._mesh.vertex_normals(predicted)  # zero rows off the surface
        position_std = np.asarray(position_std, dtype=np.float64)
        weights = np.zeros(len(position_std))
        known = np.flatnonzero((position_std > 0.0) & np.isfinite(position_std))
        weights[known] = 1.0 / position_std[known] ** 2
        along_sensitivity = np.einsum("ij,ij->i", normals, self.sensitivity(predicted))
        along_correction = np.einsum("ij,ij->i", normals, correction)
        energy = float(weights @ along_sensitivity**2)
        if energy > 0.0:
            step = float(weights @ (along_sensitivity * along_correction)) / energy
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
