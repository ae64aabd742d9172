"""Estimate of a uniform body load the tissue model does not know.

Real tissue carries loads its model leaves out: gravity from another direction than the one
the mesh was segmented under (the table tilts, the patient is moved), the pull of neighbouring
organs and ligaments, the drag of a sticky tool. The quasi-static simulator relaxes every
estimate back to the model's equilibrium, so without that load each update has to make the
same correction to its prediction again, and the physics prior holds most of it back.

`BodyLoadEstimate` fits, after each update, the uniform body acceleration whose small-strain
response best explains the update's correction c = estimate - prediction in the stiffness
metric, and adds it to what the simulator applies from then on. It is an integrator: the next
correction measures what the load still misses.

    dg = argmin_g (c - K0^-1 F g)^T K0 (c - K0^-1 F g) = (F^T K0^-1 F)^-1 F^T c

F holds the lumped masses (F g is m_i g at every movable vertex) and K0 is the rest stiffness
on the movable dofs. F^T c is the mass-weighted sum of the correction, so the three numbers of
dg average over the whole body: a local correction (a leak near the tool, noise) moves them
little, a correction of the whole body (a sag, a pull) moves them fully. F^T K0^-1 F (3 x 3)
is computed once, from three solves with K0's factor.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.simulator import ElasticSimulator

__all__ = ["BodyLoadEstimate"]


class BodyLoadEstimate:
    """The unmodelled uniform body load of `simulator`, updated from (prediction, estimate) pairs
    and applied as the simulator's `body_acceleration` (module docstring)."""

    def __init__(self, simulator: ElasticSimulator):
        self.simulator = simulator
        self._movable = simulator.movable_vertices
        self._mass = simulator.vertex_mass[self._movable]
        self._unit_loads = np.kron(self._mass[:, None], np.eye(3))  # (3 n, 3): F, one column per axis
        self._compliance_at: float | None = None  # the Poisson ratio F^T K0^-1 F was computed at

    @property
    def acceleration(self) -> np.ndarray:
        """The load applied now, as a uniform acceleration (3,) in m/s^2."""
        return self.simulator.body_acceleration

    def _compliance(self) -> np.ndarray:
        """F^T K0^-1 F at the simulator's Poisson ratio (core/poisson_ratio.py may change it)."""
        if self._compliance_at != self.simulator.poisson_ratio:
            self._compliance_matrix = self._unit_loads.T @ self.simulator.rest_response(self._unit_loads)
            self._compliance_at = self.simulator.poisson_ratio
        return self._compliance_matrix

    def response(self, acceleration: np.ndarray) -> np.ndarray:
        """The small-strain displacement (N, 3) of the uniform load `acceleration` (3,)."""
        displacement = np.zeros((self.simulator.rest_mesh.vertex_count, 3))
        displacement[self._movable] = self.simulator.rest_response(self._unit_loads @ acceleration).reshape(-1, 3)
        return displacement

    def update(self, predicted: np.ndarray, estimate: np.ndarray) -> np.ndarray:
        """Add the load that explains the correction `estimate` - `predicted` (both (N, 3), the
        estimate of the prediction's stamp); returns the added acceleration (3,)."""
        correction = (estimate - predicted)[self._movable]
        added = np.linalg.solve(self._compliance(), self._mass @ correction)
        self.simulator.body_acceleration = self.simulator.body_acceleration + added
        return added

    def reset(self) -> None:
        """Forget the load (a new timeline starts from the initial mesh)."""
        self.simulator.body_acceleration = np.zeros(3)
