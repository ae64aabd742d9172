"""Accuracy of the sim_bridge path on a synthetic scene, without ROS: the estimate from an
external simulator's states and stiffness against that simulator's states alone.

The external simulator is what the authors' XPBD simulator is to the estimator: it runs on its
own, driven by the tool, from its own previous state (it never sees an estimate), with the
scene's nominal model (`Scenario.simulator_config`: the model a user knows, which the scene's
truth departs from), and answers each cloud with its current state and, with `with_stiffness`,
its corotational FEM stiffness at that state in float32 with the fixed dofs at 1e9 on the
diagonal (nodes/sim_bridge_server.py sends the same). Each answer takes the estimator node's
path from its arrays on (core/external_prior.bridge_state, EstimationScheduler: the prediction
and the prior's information made of the stiffness); test_sim_bridge_nodes.py shows that path
over DDS gives the same estimates. A cut in the scene (its steps' removed_elements) is made in
the simulator too and comes in the answers' invalid element slots.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.estimation.estimator import EstimatorConfig
from meshfg_ros.core.physics.external_prior import BridgeAnswer, bridge_state, held_dof_stiffness
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.core.geometry.mesh import inverted_elements
from meshfg_ros.core.scheduler import EstimationScheduler, Prediction
from meshfg_ros.core.physics.simulator import ElasticSimulator
from meshfg_ros.evaluation.metrics import vertex_rmse
from meshfg_ros.parameters import config_changes, shared_settings

__all__ = ["bridge_accuracy"]

def _answer(mesh, simulator, positions, model, with_stiffness: bool) -> BridgeAnswer:
    """The simulator's answer as the client reads it from the message: every slot, float32 stiffness."""
    rest = simulator.rest_mesh
    stiffness = (held_dof_stiffness(model.stiffness(positions, kind="corotational"), rest.boundary_vertices)
                 if with_stiffness else None)
    return BridgeAnswer(positions=positions.reshape(-1),
                        valid_vertex_count=mesh.vertex_count - rest.invalid_vertices.size,
                        invalid_vertices=rest.invalid_vertices, elements=mesh.all_tetrahedra.reshape(-1),
                        invalid_elements=rest.removed_elements, stiffness=stiffness)


def bridge_accuracy(scene, with_stiffness: bool = True) -> dict:
    """Per step the vertex RMSE [m] of the estimate and of the external simulator's state against
    the truth, over all vertices valid at that step, and their ratio at the last step
    ("ratio_last") and pooled over the steps ("ratio_mean": mean RMSE over mean RMSE); the steps
    whose estimate is on other elements than the simulator's ("topology_mismatches") and the
    inverted elements of all estimates ("inverted_elements")."""
    mesh = scene.initial_mesh
    # As the replay sets the estimator for a scene: the nominal tissue model and tool, the noise's sigma.
    config = EstimatorConfig(**{**shared_settings(scene.simulator_config, EstimatorConfig),
                                "measurement_sigma": scene.noise_sigma_m,
                                **config_changes(EstimatorConfig, scene.estimator_overrides)})
    simulator = ElasticSimulator(mesh, scene.simulator_config, scene.grasped_vertices)
    simulator.reset(scene.initial_tool_pose)
    scheduler = EstimationScheduler(mesh, config)
    viewpoint = None if scene.camera_pose is None else np.asarray(scene.camera_pose[:3], dtype=np.float64)
    state, previous_ns = mesh.vertices.copy(), 0
    fg, sim, topology_mismatches, inverted = [], [], 0, 0
    model = None
    for step in scene.steps:
        cut = step.removed_elements.size and simulator.remove_elements(step.removed_elements)
        if with_stiffness and (model is None or cut):  # assembled again only when a cut changes the elements
            model = ElasticModel(mesh.vertices, simulator.rest_mesh.tetrahedra, scene.simulator_config.youngs_modulus,
                                 scene.simulator_config.poisson_ratio)
        state = simulator.predict(state, step.tool_pose, (step.stamp_ns - previous_ns) * 1e-9 or 1.0)
        previous_ns = step.stamp_ns
        positions, stiffness, removed = bridge_state(_answer(mesh, simulator, state, model, with_stiffness), mesh,
                                                     np.eye(4))
        scheduler.add_tool_pose(step.stamp_ns, step.tool_pose)
        scheduler.add_cloud(step.stamp_ns, step.points, 0.0, viewpoint)
        scheduler.add_prediction(Prediction(step.stamp_ns, positions, stiffness=stiffness, removed_elements=removed))
        outcome = scheduler.run(scheduler.next_step(0.0, flush=True))
        if outcome.result is None:
            raise RuntimeError(f"step at {step.stamp_ns} ns failed: {outcome.error}")
        valid = simulator.rest_mesh.valid_vertices
        estimated_on = scheduler.estimator.mesh
        topology_mismatches += int(not np.array_equal(estimated_on.removed_elements,
                                                      simulator.rest_mesh.removed_elements))
        inverted += int(inverted_elements(outcome.result.positions, estimated_on.tetrahedra).size)
        fg.append(vertex_rmse(outcome.result.positions, step.truth, valid))
        sim.append(vertex_rmse(state, step.truth, valid))
    return {"scene": scene.name, "with_stiffness": with_stiffness, "fg_rmse": fg, "sim_rmse": sim,
            "ratio_last": fg[-1] / sim[-1], "ratio_mean": float(np.mean(fg) / np.mean(sim)),
            "topology_mismatches": topology_mismatches, "inverted_elements": inverted}
