"""The scenario metadata of a recording: the JSON on /meshfg/scenario (std_msgs/String).

It tells replay and evaluation what they need besides the messages: grasped vertices, the
estimator's nominal simulator model and overrides, the measurement noise, the observed faces of
camera-less scenes, and the seed. Synthetic recordings write it (synthetic/recordings.py); a
recording from a real robot has none.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

from meshfg_ros.io.recording import InvalidRecordedMessageError, RecordingReader, TopicTypeError
from meshfg_ros.topics import SCENARIO_TOPIC

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
