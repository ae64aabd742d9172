"""Synthetic recordings: a scenario of `core.scenarios` written as a self-contained rosbag2.

A recording holds what the live system would see (tool poses, segmented depth clouds, the
camera pose), the initial mesh the estimator starts from, the ground truth per step, and the
scenario's metadata on /meshfg/scenario (std_msgs/String, JSON) so that replay and evaluation
need nothing but the file: grasped vertices, the estimator's nominal simulator model and
overrides, the measurement noise, the observed faces of camera-less scenes, and the seed.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from meshfg_ros.core.scenarios import FIRST_STAMP_NS, Scenario, generate
from meshfg_ros.io.messages import MeshState, PoseRecord, RosbagsMessageFactory
from meshfg_ros.io.pointcloud import encode_xyz
from meshfg_ros.io.recording import (
    InvalidRecordedMessageError,
    RecordingExistsError,
    RecordingReader,
    RecordingWriter,
    TopicTypeError,
)
from meshfg_ros.topics import (
    CAMERA_POSE_TOPIC,
    GROUND_TRUTH_TOPIC,
    INITIAL_MESH_TOPIC,
    POINTS_TOPIC,
    SCENARIO_TOPIC,
    TOOL_POSE_TOPIC,
)

FRAME_ID = "world"
STRING = "std_msgs/msg/String"
METADATA_FORMAT = 1


@dataclass(frozen=True)
class ScenarioMetadata:
    """The JSON on /meshfg/scenario: what replay and evaluation need besides the messages.

    observed_triangles: indices into the initial mesh's surface_triangles of the faces the
    measurements are drawn from (camera-less scenes only, else None).
    """

    scenario: str
    seed: int
    description: str
    noise_sigma_m: float
    simulator: dict
    grasped_vertices: tuple[int, ...]
    estimator_overrides: dict
    observed_triangles: tuple[int, ...] | None
    max_points: int | None

    def to_json(self) -> str:
        return json.dumps({"format": METADATA_FORMAT, **asdict(self)}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ScenarioMetadata:
        """Parse the topic's JSON; raises ValueError naming what is missing or malformed."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"scenario metadata is not JSON: {error}") from None
        if not isinstance(data, dict) or data.get("format") != METADATA_FORMAT:
            raise ValueError(f"scenario metadata must be a JSON object with format {METADATA_FORMAT}")
        missing = sorted(set(cls.__dataclass_fields__) - set(data))
        if missing:
            raise ValueError(f"scenario metadata lacks {', '.join(missing)}")
        observed = data["observed_triangles"]
        return cls(
            scenario=str(data["scenario"]),
            seed=int(data["seed"]),
            description=str(data["description"]),
            noise_sigma_m=float(data["noise_sigma_m"]),
            simulator=dict(data["simulator"]),
            grasped_vertices=tuple(int(v) for v in data["grasped_vertices"]),
            estimator_overrides=dict(data["estimator_overrides"]),
            observed_triangles=None if observed is None else tuple(int(f) for f in observed),
            max_points=None if data["max_points"] is None else int(data["max_points"]),
        )


def scenario_metadata(scenario: Scenario, max_points: int | None = None) -> ScenarioMetadata:
    """Metadata of `scenario` (observed faces as indices into its surface_triangles)."""
    observed = None
    if scenario.observed_triangles is not None:
        observed = tuple(int(f) for f in np.flatnonzero(scenario.observed_triangles))
    simulator = {key: (list(value) if isinstance(value, tuple) else value)
                 for key, value in asdict(scenario.simulator_config).items()}
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


def read_metadata(reader: RecordingReader) -> ScenarioMetadata | None:
    """The /meshfg/scenario metadata of a recording, or None if it has none."""
    if SCENARIO_TOPIC not in reader.topics:
        return None
    info = reader.topics[SCENARIO_TOPIC]
    if info.msgtype != STRING:
        raise TopicTypeError(f"topic {SCENARIO_TOPIC} holds {info.msgtype}, expected {STRING}")
    message = next(iter(reader.messages([SCENARIO_TOPIC]))).data
    try:
        return ScenarioMetadata.from_json(message.data)
    except ValueError as error:
        raise InvalidRecordedMessageError(f"{SCENARIO_TOPIC}: {error}") from None


def _mesh_state(scenario: Scenario, positions: np.ndarray, stamp_ns: int, step: int) -> MeshState:
    mesh = scenario.initial_mesh
    return MeshState(stamp_ns=stamp_ns, frame_id=FRAME_ID, step=step, positions=positions,
                     tetrahedra=mesh.tetrahedra, surface_triangles=mesh.surface_triangles,
                     fixed_vertices=mesh.fixed_vertices)


def _subsample(points: np.ndarray, labels: np.ndarray, max_points: int | None, rng: np.random.Generator):
    """At most max_points of the cloud, drawn without replacement, in their original order."""
    if max_points is None or len(points) <= max_points:
        return points, labels
    keep = np.sort(rng.choice(len(points), size=max_points, replace=False))
    return points[keep], labels[keep]


def write_scenario(scenario: Scenario, path: str | Path, max_points: int | None = None) -> dict[str, int]:
    """Write `scenario` as a zstd-compressed MCAP rosbag2 at `path` (never overwrites).

    Step 0 (the initial mesh, its tool pose, the camera pose, the metadata) is stamped
    FIRST_STAMP_NS; step k carries its tool pose, cloud (FLOAT32 x y z label, label 0 = target
    tissue, >0 = segmentation leak) and ground truth at its own stamp. max_points caps the
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
        for index, step in enumerate(scenario.steps, start=1):
            writer.write(TOOL_POSE_TOPIC, PoseRecord(step.stamp_ns, FRAME_ID, step.tool_pose))
            points, labels = _subsample(step.points, step.point_labels, max_points, rng)
            cloud = encode_xyz(points, FRAME_ID, step.stamp_ns, factory, extra_fields={"label": labels})
            writer.write(POINTS_TOPIC, cloud)
            writer.write(GROUND_TRUTH_TOPIC, _mesh_state(scenario, step.truth, step.stamp_ns, index))
        return dict(writer.counts)


def synthesize(name: str, path: str | Path, seed: int = 0, max_points: int | None = None) -> dict[str, int]:
    """Generate scenario `name` from `seed` and write it to `path` (see write_scenario)."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        # Checked before the (slow) generation as well as by the writer.
        raise RecordingExistsError(f"{path} exists already; recordings are never overwritten")
    return write_scenario(generate(name, seed), path, max_points)
