"""Estimate of a uniform body load the tissue model does not know.

Real tissue carries loads its model leaves out: gravity from another direction than the one
the mesh was segmented under (the table tilts, the patient is moved), the pull of neighbouring
organs and ligaments, the drag of a sticky tool. The quasi-static simulator relaxes every
estimate back to the model's equilibrium, so without that load each update has to make the
same correction to its prediction again, and the physics prior holds most of it back.

`BodyLoadEstimate` holds the uniform body acceleration the simulator applies on top of its
gravity and gives the small-strain responses to it; after each update the learning simulator
(core/physics/learning_simulator.py) fits its increment, jointly with the Poisson ratio's, to the
correction's normal components at the surface (core/physics/model_fit.py) and adds it. It is an integrator: the next correction measures
what the load still misses. The responses, K0^-1 F (F the lumped masses, K0 the rest stiffness
on the movable dofs, the other vertices held), take three solves with K0's factor, again when
the Poisson ratio changes.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.physics.simulator import ElasticSimulator

__all__ = ["BodyLoadEstimate"]


class BodyLoadEstimate:
    """The unmodelled uniform body load of `simulator`, applied as its `body_acceleration`; the
    learning simulator fits the increments (module docstring)."""

    def __init__(self, simulator: ElasticSimulator):
        self.simulator = simulator
        self._movable = simulator.movable_vertices
        mass = simulator.vertex_mass[self._movable]
        self._unit_loads = np.kron(mass[:, None], np.eye(3))  # (3 n, 3): F, one column per axis
        self._responses: np.ndarray | None = None  # (3, N, 3), at the Poisson ratio _responses_at
        self._responses_at: float | None = None

    @property
    def acceleration(self) -> np.ndarray:
        """The load applied now, as a uniform acceleration (3,) in m/s^2."""
        return self.simulator.body_acceleration

    def responses(self) -> np.ndarray:
        """(3, N, 3): the small-strain displacement of a unit acceleration (1 m/s^2) along x, y, z,
        at the simulator's Poisson ratio."""
        if self._responses_at != self.simulator.poisson_ratio:
            count = self.simulator.rest_mesh.vertex_count
            self._responses = np.zeros((3, count, 3))
            columns = self.simulator.rest_response(self._unit_loads)  # (3 n, 3)
            self._responses[:, self._movable] = columns.T.reshape(3, -1, 3)
            self._responses_at = self.simulator.poisson_ratio
        return self._responses

    def add(self, increment: np.ndarray) -> None:
        """Apply `increment` (3,) m/s^2 on top of the load learnt so far."""
        self.simulator.body_acceleration = self.simulator.body_acceleration + np.asarray(increment, dtype=np.float64)

    def reset(self) -> None:
        """Forget the load (a new timeline starts from the initial mesh)."""
        self.simulator.body_acceleration = np.zeros(3)
