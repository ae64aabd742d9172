"""Synthetic recordings: a scenario of `synthetic.scenarios` written as a self-contained rosbag2.

A recording holds what the live system would see (tool poses, segmented depth clouds, the
camera pose, the element slots a cut removes at the step it happens: the request the simulation
node takes on /meshfg/remove_elements), the initial mesh the estimator starts from, the ground
truth per step (on the topology of its step: a cut's removed elements and invalid vertices), and the
scenario's metadata on /meshfg/scenario (std_msgs/String, JSON) so that replay and evaluation
need nothing but the file: grasped vertices, the estimator's nominal simulator model and
overrides, the measurement noise, the observed faces of camera-less scenes, and the seed.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from meshfg_ros.synthetic.scenarios import FIRST_STAMP_NS, Scenario, generate
from meshfg_ros.io.scenario_metadata import STRING, ScenarioMetadata
from meshfg_ros.io.messages import MeshState, PoseRecord, RosbagsMessageFactory
from meshfg_ros.io.pointcloud import encode_xyz
from meshfg_ros.io.recording import RecordingExistsError, RecordingWriter
from meshfg_ros.topics import (
    CAMERA_POSE_TOPIC,
    GROUND_TRUTH_TOPIC,
    INITIAL_MESH_TOPIC,
    POINTS_TOPIC,
    REMOVE_ELEMENTS_TOPIC,
    SCENARIO_TOPIC,
    TOOL_POSE_TOPIC,
)

FRAME_ID = "world"
UINT32_MULTI_ARRAY = "std_msgs/msg/UInt32MultiArray"
# SimulatorConfig fields that are settings of the closed loop, not of the scene's nominal model:
# left out of the metadata, so a replay takes them from its parameters like any estimator setting.
NOT_THE_MODEL = ("estimate_body_load", "estimate_poisson_ratio")


def scenario_metadata(scenario: Scenario, max_points: int | None = None) -> ScenarioMetadata:
    """Metadata of `scenario` (observed faces as indices into its surface_triangles)."""
    observed = None
    if scenario.observed_triangles is not None:
        observed = tuple(int(f) for f in np.flatnonzero(scenario.observed_triangles))
    simulator = {key: (list(value) if isinstance(value, tuple) else value)
                 for key, value in asdict(scenario.simulator_config).items() if key not in NOT_THE_MODEL}
    return ScenarioMetadata(
        scenario=scenario.name,
        seed=int(scenario.seed),
        description=scenario.description,
        noise_sigma_m=float(scenario.noise_sigma_m),
        simulator=simulator,
        grasped_vertices=tuple(int(v) for v in scenario.grasped_vertices),
        estimator_overrides=dict(scenario.estimator_overrides),
        observed_triangles=observed,
        max_points=max_points,
    )


def _mesh_state(scenario: Scenario, positions: np.ndarray, stamp_ns: int, step: int,
                removed_elements: np.ndarray = np.zeros(0, np.int64)) -> MeshState:
    mesh = scenario.initial_mesh.without_elements(removed_elements)
    return MeshState.of_mesh(mesh, stamp_ns, FRAME_ID, step, positions)


def _remove_elements_msg(slots: np.ndarray, factory: RosbagsMessageFactory):
    """std_msgs/UInt32MultiArray of element slots (the simulation node's remove_elements request)."""
    layout = factory.make("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    return factory.make(UINT32_MULTI_ARRAY, layout=layout, data=factory.sequence(slots, np.uint32))


def _subsample(points: np.ndarray, labels: np.ndarray, max_points: int | None, rng: np.random.Generator):
    """At most max_points of the cloud, drawn without replacement, in their original order."""
    if max_points is None or len(points) <= max_points:
        return points, labels
    keep = np.sort(rng.choice(len(points), size=max_points, replace=False))
    return points[keep], labels[keep]


def write_scenario(scenario: Scenario, path: str | Path, max_points: int | None = None) -> dict[str, int]:
    """Write `scenario` as a zstd-compressed MCAP rosbag2 at `path` (never overwrites).

    Step 0 (the initial mesh, its tool pose, the camera pose, the metadata) is stamped
    FIRST_STAMP_NS; step k carries its tool pose, the element slots removed so far when a cut
    changed them at this step, its cloud (FLOAT32 x y z label, label 0 = target tissue, >0 =
    segmentation leak) and ground truth at its own stamp. max_points caps the
    points per cloud (seeded subsampling, to keep bundled recordings small).
    Returns the message count per topic.
    """
    factory = RosbagsMessageFactory()
    rng = np.random.default_rng(scenario.seed)
    metadata = scenario_metadata(scenario, max_points)
    with RecordingWriter(path, compress=True) as writer:
        writer.write(SCENARIO_TOPIC, factory.make(STRING, data=metadata.to_json()), FIRST_STAMP_NS)
        initial = _mesh_state(scenario, scenario.initial_mesh.vertices, FIRST_STAMP_NS, 0)
        writer.write(INITIAL_MESH_TOPIC, initial)
        writer.write(GROUND_TRUTH_TOPIC, initial)
        if scenario.camera_pose is not None:
            writer.write(CAMERA_POSE_TOPIC, PoseRecord(FIRST_STAMP_NS, FRAME_ID, scenario.camera_pose))
        writer.write(TOOL_POSE_TOPIC, PoseRecord(FIRST_STAMP_NS, FRAME_ID, scenario.initial_tool_pose))
        removed = np.zeros(0, np.int64)
        for index, step in enumerate(scenario.steps, start=1):
            writer.write(TOOL_POSE_TOPIC, PoseRecord(step.stamp_ns, FRAME_ID, step.tool_pose))
            if not np.array_equal(step.removed_elements, removed):
                removed = step.removed_elements
                writer.write(REMOVE_ELEMENTS_TOPIC, _remove_elements_msg(removed, factory), step.stamp_ns)
            points, labels = _subsample(step.points, step.point_labels, max_points, rng)
            cloud = encode_xyz(points, FRAME_ID, step.stamp_ns, factory, extra_fields={"label": labels})
            writer.write(POINTS_TOPIC, cloud)
            writer.write(GROUND_TRUTH_TOPIC, _mesh_state(scenario, step.truth, step.stamp_ns, index,
                                                         step.removed_elements))
        return dict(writer.counts)


def synthesize(name: str, path: str | Path, seed: int = 0, max_points: int | None = None,
               progress=None) -> dict[str, int]:
    """Generate scenario `name` from `seed` and write it to `path` (see write_scenario);
    `progress` as `generate`'s."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        # Checked before the (slow) generation as well as by the writer.
        raise RecordingExistsError(f"{path} exists already; recordings are never overwritten")
    return write_scenario(generate(name, seed, progress=progress), path, max_points)
