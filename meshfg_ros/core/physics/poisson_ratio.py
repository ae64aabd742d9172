"""Estimate of the tissue's compressibility: the simulator's Poisson ratio, learnt online.

Soft tissue is nearly incompressible (nu 0.45-0.5), and a tissue model is commonly given
another nu than the tissue's (lower, as linear tetrahedra lock near 0.5). Pushed, a less
compressible body bulges more: away from the tool it moves where the model does not, on the
hidden side too. The factor graph corrects the visible surface, but the physics prior carries
that correction to the hidden side through the nominal stiffness, with the wrong sign there
(docs/design-notes.md, "The airway over its steps"). Only a prediction from the right
compressibility moves the hidden side right.

`PoissonRatioEstimate` holds the ratio and gives the sensitivity of the prediction to it,

    S = dX/dnu = -K_ff^-1 (dK/dnu u)_f

u the prediction's displacement from rest, f the dofs of the vertices that move freely (neither
fixed, grasped nor stuck to the tool, whose positions the boundary prescribes), K the rest
stiffness (linear in the Lame parameters, so dK/dnu is exact). After each update the
learning simulator (core/physics/learning_simulator.py) fits the ratio's increment, jointly with
the body load's, to the correction's normal components at the surface (core/physics/model_fit.py).
As the load, it is an integrator: the next correction measures what nu still misses. The ratio stays within
[FLOOR, CEILING]; the simulator rescales its moduli and refactors K0 at each new value
(ElasticSimulator.poisson_ratio).
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.physics.simulator import ElasticSimulator

__all__ = ["CEILING", "FLOOR", "PoissonRatioEstimate"]

# Below 0.5, where lambda diverges; the simulator's volumetric term stays well conditioned.
CEILING = 0.49
# No soft tissue is this compressible.
FLOOR = 0.30


class PoissonRatioEstimate:
    """The Poisson ratio of `simulator`, learnt from the corrections (module docstring); the
    user's nu is where it starts."""

    def __init__(self, simulator: ElasticSimulator):
        self.simulator = simulator
        self.nominal = float(simulator.poisson_ratio)
        self._mesh = simulator.rest_mesh
        self._movable = simulator.movable_vertices
        self._movable_dofs = (3 * self._movable[:, None] + np.arange(3)).reshape(-1)

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

    def add(self, increment: float) -> float:
        """Move the ratio by `increment`, within [FLOOR, CEILING]; returns the ratio the simulator
        uses from now on."""
        ratio = float(np.clip(self.simulator.poisson_ratio + increment, FLOOR, CEILING))
        if ratio != self.simulator.poisson_ratio:
            self.simulator.poisson_ratio = ratio
        return ratio

    def reset(self) -> None:
        """Back to the user's nu (a new timeline starts from the initial mesh)."""
        if self.simulator.poisson_ratio != self.nominal:
            self.simulator.poisson_ratio = self.nominal
