"""The simulator together with what it learns of the tissue from the estimates.

`LearningSimulator` owns the elastic simulator (core/physics/simulator.py) and the two things it
learns online from each estimate's correction of its prediction: the unmodelled uniform body
load (core/physics/body_load.py) and the tissue's Poisson ratio (core/physics/poisson_ratio.py),
fitted jointly (core/physics/model_fit.py). Each is learnt only where its configuration field
asks for it (estimate_body_load, estimate_poisson_ratio) and the mesh has vertices that move.

The prediction scheduler (core/scheduler.py) decides when it predicts, from which state, and
which estimate it learns from; this class answers how the model adapts: what a prediction
applies, what an estimate teaches, what a cut and a restart keep.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.physics.body_load import BodyLoadEstimate
from meshfg_ros.core.physics import model_fit
from meshfg_ros.core.physics.poisson_ratio import PoissonRatioEstimate
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig

__all__ = ["LearningSimulator"]


class LearningSimulator:
    """An ElasticSimulator whose body load and Poisson ratio follow the estimates (module docstring)."""

    def __init__(self, mesh: TetMesh, config: SimulatorConfig, grasped_vertices: np.ndarray | None = None) -> None:
        self.elastic = ElasticSimulator(mesh, config, grasped_vertices)
        movable = self.elastic.movable_vertices.size > 0
        # None: not learnt (switched off, or nothing moves)
        self.body_load = BodyLoadEstimate(self.elastic) if config.estimate_body_load and movable else None
        self.poisson_ratio_estimate = (PoissonRatioEstimate(self.elastic)
                                       if config.estimate_poisson_ratio and movable else None)

    @property
    def rest_mesh(self) -> TetMesh:
        """The mesh the simulator predicts on (after a cut, without the removed elements)."""
        return self.elastic.rest_mesh

    @property
    def body_acceleration(self) -> np.ndarray | None:
        """The body load learnt so far, as a uniform acceleration (3,) in m/s^2; None when it is
        not learnt."""
        return None if self.body_load is None else self.body_load.acceleration

    @property
    def poisson_ratio(self) -> float:
        """The Poisson ratio the predictions use: the configured one, or the one learnt so far."""
        return self.elastic.poisson_ratio

    def predict(self, previous_state: np.ndarray, tool_pose: np.ndarray, dt: float) -> np.ndarray:
        """State (N, 3) after the tool moves from its previous pose to `tool_pose` over dt seconds,
        with the load and the ratio learnt so far (ElasticSimulator.predict)."""
        return self.elastic.predict(previous_state, tool_pose, dt)

    def reset(self, tool_pose: np.ndarray) -> None:
        """Start again with the tool at `tool_pose` and forget what was learnt, predicting as a
        newly made simulator would: a new timeline starts from the initial mesh, and after a
        failed prediction the learnt load may be what failed (kept, every later prediction
        could fail alike)."""
        self.elastic.reset(tool_pose)
        if self.body_load is not None:
            self.body_load.reset()
        if self.poisson_ratio_estimate is not None:
            self.poisson_ratio_estimate.reset()
        self.elastic.restart_rest_factor()

    def learn(self, predicted: np.ndarray, estimate: np.ndarray, position_std: np.ndarray | None) -> None:
        """Fit the body load's and the Poisson ratio's increments to the correction `estimate` -
        `predicted` (both (N, 3)), each vertex weighted by the estimate's `position_std` (N,), and
        apply them (core/physics/model_fit.py). Without a std of one entry per vertex nothing is
        learnt: the fit has no weights."""
        if position_std is not None and np.shape(position_std) == (len(estimate),):
            model_fit.learn(self.rest_mesh, self.body_load, self.poisson_ratio_estimate, predicted, estimate, position_std)

    def remove_elements(self, removed_elements) -> bool:
        """Cut: predict on the mesh without the element slots `removed_elements` from now on
        (ElasticSimulator.remove_elements), keeping the load and the ratio learnt and the user's
        ratio to reset to. Returns whether the topology changed; InvalidMeshError or
        NotPositiveDefiniteError, and nothing changed, for a cut the simulator cannot take."""
        if not self.elastic.remove_elements(removed_elements):
            return False
        if self.body_load is not None:
            self.body_load = BodyLoadEstimate(self.elastic)
        if self.poisson_ratio_estimate is not None:
            nominal = self.poisson_ratio_estimate.nominal
            self.poisson_ratio_estimate = PoissonRatioEstimate(self.elastic)
            self.poisson_ratio_estimate.nominal = nominal
        return True
