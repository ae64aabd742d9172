"""Small synthetic scenes and recordings for the offline tests (synth, replay, eval, render, CLI).

A 2 cm cube of 27 vertices, bottom fixed, pushed down on its top by a 5 mm sphere for a few
1 Hz steps; measurements are noisy samples of the true top, +x and +y faces. Everything runs
in well under a second, unlike the full scenarios of synthetic/scenarios.py (`shared_scene`
synthesizes one of those once per test session).
"""
from __future__ import annotations

import functools
import importlib.metadata
import sys
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial.transform import Rotation

from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.synthetic.meshing import box_mesh, cube_mesh
from meshfg_ros.evaluation.metrics import sample_surface
from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS, STEP_PERIOD_NS, Scenario, ScenarioStep, generate, pose
from meshfg_ros.core.physics.simulator import ElasticSimulator, SimulatorConfig

SIDE = 0.02
TOOL_RADIUS = 5e-3
PUSH_PER_STEP = 4e-4
NOISE_SIGMA = 2e-4
POINTS_PER_STEP = 300
MESHFG = str(Path(sys.executable).with_name("meshfg"))
REPOSITORY = Path(__file__).resolve().parents[1]
BAGS = REPOSITORY / "bags"
# A robot's frames for the /tf tests: the endoscope's optical frame on its arm (ecm_link), the
# tool arm's base in the world (each [x, y, z, qx, qy, qz, qw], static).
OPTICAL = np.array([0.0, 0.0, 0.05, *Rotation.from_euler("xyz", [-90.0, 0.0, -90.0], degrees=True).as_quat()])
BASE = np.array([0.3, -0.2, 0.1, *Rotation.from_euler("xyz", [0.0, 0.0, 40.0], degrees=True).as_quat()])


def counting_progress(seen: list):
    """A progress(iterable, total) wrapper that records the total, then each step it passes on."""
    def progress(steps, total):
        seen.append(total)
        for step in steps:
            seen.append("step")
            yield step
    return progress


@functools.lru_cache(maxsize=2)
def shared_scene(name: str, seed: int) -> Scenario:
    """`generate(name, seed=seed)` once per test session, for tests that only read the scene (a
    mismatch scene's ten-step truth takes about 12 s)."""
    return generate(name, seed=seed)


def robot_statics():
    """The /tf_static transforms of OPTICAL (ecm_link -> endoscope_optical_frame) and BASE (world -> psm1_base)."""
    from meshfg_ros.core.inputs.frames import StampedTransform

    return [StampedTransform("ecm_link", "endoscope_optical_frame", 0, OPTICAL[:3], OPTICAL[3:]),
            StampedTransform("world", "psm1_base", 0, BASE[:3], BASE[3:])]


def box_stiffness(vertices: int) -> scipy.sparse.csr_matrix:
    """K + a small diagonal of a box of about `vertices` vertices: SPD, with the pattern the
    estimator factors."""
    mesh = box_mesh(vertices, (0.1, 0.1, 0.1))
    matrix = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45).stiffness(kind="linear")
    return (matrix + 1e-2 * scipy.sparse.identity(matrix.shape[0])).tocsr()


def mkl_installed() -> bool:
    """Whether Intel's `mkl` wheel is installed (requirements-core.txt: x86-64 Linux only)."""
    try:
        importlib.metadata.distribution("mkl")
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


def tiny_scenario(steps: int = 3, seed: int = 0, camera: bool = False) -> Scenario:
    """The small pushed cube; with camera=True it carries a camera pose above the cube."""
    rng = np.random.default_rng(seed)
    mesh = cube_mesh(side=SIDE, divisions=2)
    mesh = mesh.with_fixed(np.flatnonzero(np.isclose(mesh.vertices[:, 2], 0.0)))
    config = SimulatorConfig(youngs_modulus=3e3, poisson_ratio=0.45, tool_radius=TOOL_RADIUS, tool_mode="sphere",
                             substeps=4, solver_iterations=4)
    top = np.array([SIDE / 2, SIDE / 2, SIDE + TOOL_RADIUS])
    tool_poses = [pose(top - np.array([0.0, 0.0, PUSH_PER_STEP * k])) for k in range(steps + 1)]
    simulator = ElasticSimulator(mesh, config)
    simulator.reset(tool_poses[0])
    normals = mesh.triangle_normals()
    observed = (normals @ np.array([0.0, 0.0, 1.0]) > 0.99) | (normals @ np.array([1.0, 0.0, 0.0]) > 0.99) \
        | (normals @ np.array([0.0, 1.0, 0.0]) > 0.99)
    state, scenario_steps = mesh.vertices, []
    for k in range(1, steps + 1):
        state = simulator.predict(state, tool_poses[k], STEP_PERIOD_NS * 1e-9)
        clean = sample_surface(state, mesh.surface_triangles[observed], POINTS_PER_STEP, seed=int(rng.integers(2**31)))
        labels = (rng.random(len(clean)) < 0.05).astype(np.int32)  # some points labelled as leaks
        scenario_steps.append(ScenarioStep(FIRST_STAMP_NS + k * STEP_PERIOD_NS, tool_poses[k],
                                           clean + rng.normal(scale=NOISE_SIGMA, size=clean.shape), labels, state))
    camera_pose = pose([SIDE / 2, SIDE / 2, SIDE + 0.05], [1.0, 0.0, 0.0, 0.0]) if camera else None
    return Scenario(
        name="tiny-cube", seed=seed, initial_mesh=mesh, steps=tuple(scenario_steps), initial_tool_pose=tool_poses[0],
        simulator_config=config, grasped_vertices=np.zeros(0, np.int64), noise_sigma_m=NOISE_SIGMA,
        camera_pose=camera_pose, observed_triangles=None if camera else observed,
        estimator_overrides={"stiffness_kind": "corotational"}, description="2 cm cube pushed by a sphere",
    )


def write_fake_replay(scenario: Scenario, path: Path, estimate_offset: float = 0.0,
                      prediction_offset: float | None = None, estimates=None, predictions=None) -> None:
    """A replay output without running the estimator: the estimate is the truth shifted by
    estimate_offset along +z, the open-loop simulation the initial mesh, LM costs made up; with
    prediction_offset, predictions that are the truth shifted by it along +z. `estimates` and
    `predictions` (one (N, 3) array per step; the steps beyond the predictions given have none)
    replace the shifted truths."""
    from meshfg_ros.io.messages import MeshState, PointCloudRecord, RosbagsMessageFactory, StatusRecord
    from meshfg_ros.io.recording import RecordingWriter
    from meshfg_ros.topics import (
        COST_HISTORY_TOPIC,
        ESTIMATED_MESH_TOPIC,
        POINTS_TOPIC,
        PREDICTED_MESH_TOPIC,
        SIMULATION_ONLY_MESH_TOPIC,
        STATUS_TOPIC,
    )

    mesh = scenario.initial_mesh
    factory = RosbagsMessageFactory()

    def state(positions, stamp, step, std=()):
        return MeshState(stamp, "world", step, positions, mesh.tetrahedra, mesh.surface_triangles,
                         mesh.fixed_vertices, std)

    with RecordingWriter(path) as writer:
        for index, step in enumerate(scenario.steps, start=1):
            writer.write(POINTS_TOPIC, PointCloudRecord(step.stamp_ns, "world", step.points))
            estimate = step.truth + [0.0, 0.0, estimate_offset] if estimates is None else estimates[index - 1]
            writer.write(ESTIMATED_MESH_TOPIC, state(estimate, step.stamp_ns, index, np.full(mesh.vertex_count, 1e-4)))
            writer.write(SIMULATION_ONLY_MESH_TOPIC, state(mesh.vertices, step.stamp_ns, index))
            if predictions is not None:
                if index <= len(predictions):  # the later steps ran without a prediction
                    writer.write(PREDICTED_MESH_TOPIC, state(predictions[index - 1], step.stamp_ns, index))
            elif prediction_offset is not None:
                writer.write(PREDICTED_MESH_TOPIC, state(step.truth + [0.0, 0.0, prediction_offset], step.stamp_ns, index))
            writer.write(STATUS_TOPIC, StatusRecord(step.stamp_ns, "world", index, 3, 10.0, 1.0, 5.0, len(step.points),
                                                    0, min(index, 3), True, False, ""))
            history = factory.make("std_msgs/msg/Float64MultiArray",
                                   layout=factory.make("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0),
                                   data=np.array([10.0, 3.0, 1.5, 1.0]))
            writer.write(COST_HISTORY_TOPIC, history, step.stamp_ns)
