"""`meshfg fuzz`: hostile input against the PointCloud2 decoder, the estimator's update() and the
offline replay, and the estimate's recovery from single faults.

Campaigns (case i of a campaign draws its input from the generator seeded with (seed, campaign,
i), so any case's input can be made again alone; an update case also meets the estimator as the
cases before it left it):
- decoder: PointCloud2 messages whose fields all hold legal values (uint32 sizes and offsets,
  uint8 datatypes, any bytes): random ones, and crafted ones around a known cloud (any field
  order, padding inside points and rows, either byte order, FLOAT32 or FLOAT64, NaN, inf and
  1e308 coordinates), most with one thing broken (point_step >= 2**31, an offset past the point,
  a count of 0, a missing or repeated field, a wrong datatype, short data). Passes: finite points,
  equal to the sent ones where the cloud is valid, or PointCloudError.
- update: SlidingWindowEstimator.update on the recording's mesh and settings: bad input (stamps,
  types, shapes; far, shifted, inverted and collapsed predictions; far and non-finite points; bad
  tool poses) between the recording's good steps. Passes: a finite result (good input must get
  one), or EstimatorInputError / EstimatorStepError with the window as it was.
- replay: `iterate_replay` over a copy of the recording with hostile messages added (FLOAT64
  clouds with points at 1e308 or 1e200, NaN, empty and wrong-frame clouds, repeated, backward,
  negative and looped-back stamps, far, off and wrong-frame tool poses). Passes: finite steps,
  for exactly the clouds the stamp and frame rules keep.
- recovery: one fault injected into a replay of the recording (RECOVERY_FAULTS); the estimate's
  vertex error against the fault-free replay at the faulty step and after it, and, where the
  recording has a ground truth, the factor graph's and the simulation alone's vertex RMSE
  against it at the last step, with the fault and without (the simulation alone meets the same
  fault: a tool pose or a stamp; a faulty prediction is the estimator's input only).

Each case runs in a worker process under a time limit: a case that overruns it is a hang (the
worker is replaced and the campaign goes on). Counts: crashes (an exception outside the
documented classes), hangs, nan_out (a non-finite value returned), wrong (decoded points other
than the sent ones, a failed update that changed the window, good input refused, replay steps
other than the expected ones). The goal is 0 of each.
"""

from __future__ import annotations

import json
import multiprocessing
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

__all__ = [
    "CAMPAIGNS",
    "RECOVERY_FAULTS",
    "CampaignCounts",
    "FuzzError",
    "Outcome",
    "format_report",
    "run_campaign",
    "run_fuzz",
    "save",
]

# Outcome kinds of one case.
OK, REJECTED, CRASH, NAN, WRONG, HANG = "ok", "rejected", "crash", "nan", "wrong", "hang"
_CAMPAIGN_IDS = {"decoder": 1, "update": 2, "replay": 3, "recovery": 4}
_FIRST_STAMP_NS = 10**18  # update campaign: far from 0 and from 2**63, so stamp faults go both ways
_STEP_NS = 10**6
_MAX_DATA_BYTES = 1 << 16  # random decoder messages: at most this much data
_EXAMPLES = 5  # failures kept per campaign, with their case numbers
SETUP_TIMEOUT_S = 300.0  # a worker's set-up (imports, the fault-free replay) before its first case


class FuzzError(RuntimeError):
    """The harness itself could not run (a worker that cannot start)."""


@dataclass
class Outcome:
    """What one case did: kind (OK, REJECTED, CRASH, NAN, WRONG, HANG), what it was, why."""

    kind: str
    label: str
    detail: str = ""
    figures: dict = field(default_factory=dict)


@dataclass
class CampaignCounts:
    """Outcomes of a campaign's cases; examples: (case, label, detail) of the first failures."""

    name: str
    cases: int = 0
    ok: int = 0
    rejected: int = 0
    crashes: int = 0
    hangs: int = 0
    nan_out: int = 0
    wrong: int = 0
    seconds: float = 0.0
    examples: list = field(default_factory=list)
    figures: list = field(default_factory=list)

    _FIELDS = {OK: "ok", REJECTED: "rejected", CRASH: "crashes", HANG: "hangs", NAN: "nan_out", WRONG: "wrong"}

    def add(self, index: int, outcome: Outcome) -> None:
        self.cases += 1
        name = self._FIELDS[outcome.kind]
        setattr(self, name, getattr(self, name) + 1)
        if outcome.kind not in (OK, REJECTED) and len(self.examples) < _EXAMPLES:
            self.examples.append((index, outcome.label, outcome.detail))
        if outcome.figures:
            self.figures.append(outcome.figures)

    @property
    def failures(self) -> int:
        return self.crashes + self.hangs + self.nan_out + self.wrong


def _rng(seed: int, campaign: str, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, _CAMPAIGN_IDS[campaign], index])


def _one_line(error: BaseException) -> str:
    return f"{type(error).__name__}: {' '.join(str(error).split())[:200]}"


# ------------------------------------------------------------------------------------ decoder
class DecoderCampaign:
    """PointCloud2 decoding (see the module doc)."""

    def __init__(self, seed: int, options: dict):
        from meshfg_ros.io import pointcloud

        self.seed, self.pointcloud = seed, pointcloud

    def case(self, index: int) -> Outcome:
        rng = _rng(self.seed, "decoder", index)
        if rng.random() < 0.5:
            message, expected, label = _random_cloud(rng), None, "random"
        else:
            message, expected, label = _crafted_cloud(rng, self.pointcloud)
        try:
            decoded = self.pointcloud.decode_pointcloud2(message)
        except self.pointcloud.PointCloudError:
            if expected is not None:
                return Outcome(WRONG, label, "a valid cloud was refused")
            return Outcome(REJECTED, label)
        except Exception as error:  # noqa: BLE001 - what the fuzzer looks for
            return Outcome(CRASH, label, _one_line(error))
        points = decoded.points
        if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
            return Outcome(NAN, label, f"decoded points of shape {points.shape}, finite: {np.isfinite(points).all()}")
        if expected is not None and not np.array_equal(points, expected):
            return Outcome(WRONG, label, f"decoded {len(points)} points, sent {len(expected)} finite ones")
        return Outcome(OK, label)


def _u32(rng: np.random.Generator, small: int) -> int:
    """A legal uint32, mostly below `small`, sometimes at or beyond 2**31."""
    draw = rng.random()
    if draw < 0.7:
        return int(rng.integers(0, small + 1))
    if draw < 0.8:
        return int(rng.integers(2**31, 2**32))
    if draw < 0.9:
        return 2**32 - 1
    return int(rng.integers(0, 2**32))


def _message(fields, data: bytes, height: int, width: int, point_step: int, row_step: int, big_endian: bool):
    return SimpleNamespace(fields=fields, data=data, height=height, width=width, point_step=point_step,
                           row_step=row_step, is_bigendian=big_endian,
                           header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0), frame_id="world"))


def _random_cloud(rng: np.random.Generator):
    names = ["x", "y", "z", "label", "rgb", "intensity", "", "X"]
    fields = []
    for _ in range(int(rng.integers(0, 7))):
        datatype = int(rng.integers(1, 9)) if rng.random() < 0.7 else int(rng.integers(0, 256))
        fields.append(SimpleNamespace(name=str(rng.choice(names)), offset=_u32(rng, 40), datatype=datatype,
                                      count=_u32(rng, 2)))
    height, width, point_step = _u32(rng, 4), _u32(rng, 40), _u32(rng, 40)
    choice = rng.random()
    if choice < 0.5:
        row_step = min(width * point_step + int(rng.integers(0, 9)), 2**32 - 1)
    elif choice < 0.7:
        row_step = max(width * point_step - 1, 0) % 2**32
    else:
        row_step = _u32(rng, 400)
    wanted = min(row_step * height, _MAX_DATA_BYTES)
    size = wanted + int(rng.integers(-3, 4)) if rng.random() < 0.8 else int(rng.integers(0, _MAX_DATA_BYTES))
    data = rng.bytes(max(0, min(size, _MAX_DATA_BYTES)))
    return _message(fields, data, height, width, point_step, row_step, bool(rng.random() < 0.5))


_SPECIAL_VALUES = np.array([np.nan, np.inf, -np.inf, 1e308, -1e308, 3e38, 1e-310, -0.0, 1e200])
# Crafted clouds broken in one way (each makes the cloud invalid) or changed in a legal way.
_BREAKS = ("point_step_huge", "offset_past_end", "count_zero", "missing_field", "repeated_field",
           "integer_coordinate", "unknown_datatype", "short_data", "row_step_small")
_LEGAL_CHANGES = ("longer_data", "count_three")


def _crafted_cloud(rng: np.random.Generator, pointcloud):
    """A cloud of known points with a random legal layout; most get one break or legal change.
    Returns (message, expected finite points or None when broken, label)."""
    height, width = int(rng.integers(1, 4)), int(rng.integers(0, 30))
    count = height * width
    points = rng.normal(scale=10.0 ** rng.integers(-3, 4), size=(count, 3))
    special = rng.random((count, 3)) < 0.05
    points[special] = rng.choice(_SPECIAL_VALUES, size=int(special.sum()))
    kinds = {name: (pointcloud.FLOAT32 if rng.random() < 0.6 else pointcloud.FLOAT64) for name in "xyz"}
    layout = [(name, kinds[name]) for name in "xyz"] + [("label", pointcloud.UINT8)] * int(rng.integers(0, 2))
    order = rng.permutation(len(layout))
    fields, offset = [], 0
    for position in order:
        name, datatype = layout[position]
        offset += int(rng.integers(0, 4))
        fields.append(SimpleNamespace(name=name, offset=offset, datatype=datatype, count=1))
        offset += 4 if datatype == pointcloud.FLOAT32 else 8 if datatype == pointcloud.FLOAT64 else 1
    point_step = offset + int(rng.integers(0, 9))
    row_step = width * point_step + int(rng.integers(0, 17))
    big_endian = bool(rng.random() < 0.5)
    buffer = np.frombuffer(rng.bytes(row_step * height), dtype=np.uint8).copy()  # padding holds garbage
    starts = (np.arange(height)[:, None] * row_step + np.arange(width)[None, :] * point_step).reshape(-1)
    sent = np.empty((count, 3))
    for point_field in fields:
        if point_field.name not in kinds:
            continue
        axis = "xyz".index(point_field.name)
        kind = np.dtype((">" if big_endian else "<") + ("f4" if point_field.datatype == pointcloud.FLOAT32 else "f8"))
        with np.errstate(over="ignore"):
            values = points[:, axis].astype(kind)
        sent[:, axis] = values.astype(np.float64)
        raw = np.frombuffer(values.tobytes(), dtype=np.uint8).reshape(count, kind.itemsize)
        buffer[(starts + point_field.offset)[:, None] + np.arange(kind.itemsize)] = raw
    expected = sent[np.isfinite(sent).all(axis=1)]
    label = "crafted"
    if rng.random() < 0.7:
        label = str(rng.choice(_BREAKS + _LEGAL_CHANGES))
        name = str(rng.choice(list("xyz")))
        coordinate = next(f for f in fields if f.name == name)
        if label in _BREAKS and count == 0:
            label = "crafted"  # an empty cloud decodes to no points whatever its layout
        elif label == "point_step_huge":
            point_step = int(rng.integers(2**31, 2**32))
        elif label == "offset_past_end":
            coordinate.offset = point_step - 1 if rng.random() < 0.5 else int(rng.integers(2**31, 2**32))
        elif label == "count_zero":
            coordinate.count = 0
        elif label == "missing_field":
            fields.remove(coordinate)
        elif label == "repeated_field":
            fields.append(SimpleNamespace(name=coordinate.name, offset=0, datatype=pointcloud.FLOAT32, count=1))
        elif label == "integer_coordinate":
            coordinate.datatype = int(rng.choice([pointcloud.INT8, pointcloud.UINT16, pointcloud.INT32]))
        elif label == "unknown_datatype":
            coordinate.datatype = int(rng.choice([0, 9, 255]))
        elif label == "short_data":
            buffer = buffer[:-1]
        elif label == "row_step_small":
            row_step = width * point_step - 1
        elif label == "longer_data":
            buffer = np.concatenate([buffer, np.frombuffer(rng.bytes(int(rng.integers(1, 64))), dtype=np.uint8)])
        elif label == "count_three":
            coordinate.count = 3  # the decoder reads the first of them
    broken = label in _BREAKS
    return (_message(fields, buffer.tobytes(), height, width, point_step, row_step, big_endian),
            None if broken else expected, label)


# ------------------------------------------------------------------------------------ fixture
@dataclass(frozen=True)
class _Fixture:
    """The recording's inputs, parameters and fault-free replay (shared by the update, replay
    and recovery campaigns of one worker)."""

    bag: Path
    inputs: Any
    params: dict
    steps: tuple
    truth: dict | None  # stamp -> ground-truth positions (N, 3), where the recording has them


_FIXTURES: dict = {}


def _fixture(bag) -> _Fixture:
    from meshfg_ros.replay import iterate_replay, load_inputs, replay_parameters

    bag = Path(bag)
    if bag not in _FIXTURES:
        inputs = load_inputs(bag)
        params = replay_parameters(inputs)
        _FIXTURES[bag] = _Fixture(bag, inputs, params, tuple(iterate_replay(inputs, params)), _ground_truth(bag))
    return _FIXTURES[bag]


def _ground_truth(bag: Path) -> dict | None:
    """stamp -> ground-truth positions of a synthetic recording, None for one without."""
    from meshfg_ros.evaluation.evaluate import mesh_series
    from meshfg_ros.io.recording import RecordingReader
    from meshfg_ros.topics import GROUND_TRUTH_TOPIC

    with RecordingReader(bag) as reader:
        return mesh_series(reader, GROUND_TRUTH_TOPIC)[1] if GROUND_TRUTH_TOPIC in reader.topics else None


# ------------------------------------------------------------------------------------- update
class UpdateCampaign:
    """SlidingWindowEstimator.update between good steps (see the module doc). The estimator is
    built once per worker; case i uses stamp _FIRST_STAMP_NS + i * _STEP_NS unless its fault is
    the stamp."""

    def __init__(self, seed: int, options: dict):
        from meshfg_ros.core.estimation import estimator
        from meshfg_ros.parameters import estimator_config

        self.seed, self.module = seed, estimator
        self.fixture = _fixture(options["bag"])
        self.mesh = self.fixture.inputs.initial_mesh
        self.good = [s for s in self.fixture.steps if s.predicted is not None]
        self.poses = {pose.stamp_ns: pose.pose for pose in self.fixture.inputs.poses}
        self.estimator = estimator.SlidingWindowEstimator(self.mesh, estimator_config(self.fixture.params))
        self.last_stamp: int | None = None

    def case(self, index: int) -> Outcome:
        rng = _rng(self.seed, "update", index)
        step = self.good[index % len(self.good)]
        stamp = _FIRST_STAMP_NS + index * _STEP_NS
        arguments = dict(stamp_ns=stamp, points=step.points, predicted=step.predicted,
                         tool_pose=self.poses.get(step.stamp_ns) if rng.random() < 0.8 else None)
        faults = [] if rng.random() < 0.35 else list(rng.choice(len(_UPDATE_FAULTS), size=int(rng.integers(1, 3)),
                                                                replace=False))
        labels = []
        for fault in faults:
            name, apply = _UPDATE_FAULTS[fault]
            labels.append(name)
            apply(arguments, rng, self)
        label = "+".join(labels) or "good"
        estimator = self.estimator
        before = (estimator.step, estimator.last_estimate, list(estimator.graph.keys), estimator.last_stamp_ns)
        try:
            result = estimator.update(**arguments)
        except (self.module.EstimatorInputError, self.module.EstimatorStepError) as error:
            after = (estimator.step, estimator.last_estimate, list(estimator.graph.keys), estimator.last_stamp_ns)
            if after[0] != before[0] or after[1] is not before[1] or after[2] != before[2] or after[3] != before[3]:
                return Outcome(WRONG, label, f"the window changed on a failed update ({_one_line(error)})")
            if not faults:
                return Outcome(WRONG, label, f"good input refused: {_one_line(error)}")
            return Outcome(REJECTED, label, _one_line(error))
        except Exception as error:  # noqa: BLE001 - what the fuzzer looks for
            return Outcome(CRASH, label, _one_line(error))
        values = (result.positions, result.position_std, result.initial_cost, result.final_cost, result.solve_time_ms)
        if not all(np.isfinite(np.asarray(value, dtype=np.float64)).all() for value in values):
            return Outcome(NAN, label, "non-finite values in the result")
        self.last_stamp = estimator.last_stamp_ns
        return Outcome(OK, label)


def _surface_vertex(campaign: UpdateCampaign, rng) -> int:
    free = np.setdiff1d(campaign.mesh.surface_vertices, campaign.mesh.fixed_vertices)
    return int(rng.choice(free))


def _set(name: str, value_of: Callable) -> Callable:
    def apply(arguments, rng, campaign):
        arguments[name] = value_of(arguments, rng, campaign)
    return apply


def _previous_stamp(arguments, rng, campaign):
    return campaign.last_stamp if campaign.last_stamp is not None else -1


def _predicted_with(change: Callable) -> Callable:
    def value_of(arguments, rng, campaign):
        base = arguments["predicted"]
        usable = (isinstance(base, np.ndarray) and base.dtype == np.float64
                  and base.shape == (campaign.mesh.vertex_count, 3))
        return change(np.array(base if usable else campaign.good[0].predicted), rng, campaign)
    return _set("predicted", value_of)


def _vertex_at(value: float) -> Callable:
    def change(predicted, rng, campaign):
        predicted[_surface_vertex(campaign, rng)] = value
        return predicted
    return change


def _points_with(change: Callable) -> Callable:
    def value_of(arguments, rng, campaign):
        base = arguments["points"]
        usable = isinstance(base, np.ndarray) and base.dtype == np.float64 and base.ndim == 2 and base.shape[1:] == (3,)
        return change(np.array(base if usable and len(base) else campaign.good[0].points), rng)
    return _set("points", value_of)


def _some_rows(value: float, count: int) -> Callable:
    def change(points, rng):
        rows = rng.choice(len(points), size=min(count, len(points)), replace=False)
        points[rows] = value
        return points
    return change


def _mirrored(predicted, rng, campaign):
    predicted[:, 0] = 2.0 * predicted[:, 0].mean() - predicted[:, 0]
    return predicted


def _tool_pose_at(offset: Callable) -> Callable:
    def value_of(arguments, rng, campaign):
        pose = np.array(campaign.fixture.inputs.poses[1].pose)
        pose[:3] += offset(rng)
        return pose
    return _set("tool_pose", value_of)


_UPDATE_FAULTS: tuple[tuple[str, Callable], ...] = (
    # stamps
    ("stamp repeated", _set("stamp_ns", _previous_stamp)),
    ("stamp backward", _set("stamp_ns", lambda a, rng, c: (c.last_stamp or 1) - int(rng.integers(1, 10**9)))),
    ("stamp negative", _set("stamp_ns", lambda a, rng, c: -int(rng.integers(1, 10**12)))),
    ("stamp 2**63", _set("stamp_ns", lambda a, rng, c: 2**63)),
    ("stamp 2**70", _set("stamp_ns", lambda a, rng, c: 2**70)),
    ("stamp float", _set("stamp_ns", lambda a, rng, c: float(a["stamp_ns"]))),
    ("stamp bool", _set("stamp_ns", lambda a, rng, c: True)),
    ("stamp string", _set("stamp_ns", lambda a, rng, c: str(a["stamp_ns"]))),
    ("stamp None", _set("stamp_ns", lambda a, rng, c: None)),
    ("stamp numpy int", _set("stamp_ns", lambda a, rng, c: np.int64(a["stamp_ns"]))),
    ("stamp numpy uint64 huge", _set("stamp_ns", lambda a, rng, c: np.uint64(2**64 - 1))),
    # points
    ("points (K, 2)", _set("points", lambda a, rng, c: np.zeros((5, 2)))),
    ("points 1-D", _set("points", lambda a, rng, c: np.zeros(9))),
    ("points 3-D", _set("points", lambda a, rng, c: np.zeros((2, 3, 3)))),
    ("points ragged", _set("points", lambda a, rng, c: [[0.0, 0.0, 0.0], [1.0, 2.0]])),
    ("points string", _set("points", lambda a, rng, c: "0 0 0")),
    ("points strings", _set("points", lambda a, rng, c: [["0", "0", "0"]])),
    ("points objects", _set("points", lambda a, rng, c: [[None, 1.0, 2.0]])),
    ("points complex", _set("points", lambda a, rng, c: np.ones((4, 3), dtype=complex))),
    ("points bool", _set("points", lambda a, rng, c: np.ones((4, 3), dtype=bool))),
    ("points huge int", _set("points", lambda a, rng, c: [[10**30, 0, 0]])),
    ("points empty", _set("points", lambda a, rng, c: np.zeros((0, 3)))),
    ("points list", _set("points", lambda a, rng, c: np.asarray(a["points"]).tolist())),
    ("points int", _set("points", lambda a, rng, c: np.zeros((3, 3), dtype=np.int64))),
    ("points all NaN", _points_with(lambda p, rng: np.full_like(p, np.nan))),
    ("points some inf", _points_with(_some_rows(np.inf, 7))),
    ("points 5 at 1e308", _points_with(_some_rows(1e308, 5))),
    ("points 5 at -1e308", _points_with(_some_rows(-1e308, 5))),
    ("points all at 1e200", _points_with(lambda p, rng: np.full_like(p, 1e200))),
    ("points random 1e75", _points_with(lambda p, rng: rng.normal(size=p.shape) * 1e75)),
    ("points shifted 1 m", _points_with(lambda p, rng: p + [1.0, 0.0, 0.0])),
    ("points one", _points_with(lambda p, rng: p[:1])),
    ("points all equal", _points_with(lambda p, rng: np.repeat(p[:1], len(p), axis=0))),
    # predictions
    ("predicted (3, 3)", _set("predicted", lambda a, rng, c: np.zeros((3, 3)))),
    ("predicted NaN", _predicted_with(_vertex_at(np.nan))),
    ("predicted inf", _predicted_with(_vertex_at(np.inf))),
    ("predicted vertex 1e20", _predicted_with(_vertex_at(1e20))),
    ("predicted vertex 1e200", _predicted_with(_vertex_at(1e200))),
    ("predicted vertex 1e308", _predicted_with(_vertex_at(1e308))),
    ("predicted vertex -1e308", _predicted_with(_vertex_at(-1e308))),
    ("predicted vertex 0.1 m out", _predicted_with(lambda p, rng, c: _moved_vertex(p, rng, c, 0.1))),
    ("predicted shifted 1 m", _predicted_with(lambda p, rng, c: p + [1.0, 0.0, 0.0])),
    ("predicted shifted 1 cm", _predicted_with(lambda p, rng, c: p + [0.0, 0.01, 0.0])),
    ("predicted scaled 2x", _predicted_with(lambda p, rng, c: 2.0 * p - p.mean(axis=0))),
    ("predicted collapsed", _predicted_with(lambda p, rng, c: np.repeat(p[:1], len(p), axis=0))),
    ("predicted mirrored", _predicted_with(_mirrored)),
    ("predicted shuffled", _predicted_with(lambda p, rng, c: p[rng.permutation(len(p))])),
    ("predicted noise 1 mm", _predicted_with(lambda p, rng, c: p + rng.normal(scale=1e-3, size=p.shape))),
    ("predicted string", _set("predicted", lambda a, rng, c: "mesh")),
    ("predicted ragged", _set("predicted", lambda a, rng, c: [[0.0, 0.0, 0.0], [0.0]])),
    ("predicted zeros int", _set("predicted", lambda a, rng, c: np.zeros((c.mesh.vertex_count, 3), dtype=int))),
    ("predicted missing", _set("predicted", lambda a, rng, c: None)),
    # tool poses
    ("tool pose (3,)", _set("tool_pose", lambda a, rng, c: np.zeros(3))),
    ("tool pose (8,)", _set("tool_pose", lambda a, rng, c: np.zeros(8))),
    ("tool pose NaN", _tool_pose_at(lambda rng: np.nan)),
    ("tool pose 1e20", _tool_pose_at(lambda rng: 1e20)),
    ("tool pose 1e308", _tool_pose_at(lambda rng: 1e308)),
    ("tool pose 3 mm off", _tool_pose_at(lambda rng: rng.normal(size=3) * 3e-3 / np.sqrt(3.0))),
    ("tool pose string", _set("tool_pose", lambda a, rng, c: "tool")),
)


def _moved_vertex(predicted, rng, campaign, distance: float):
    vertex = _surface_vertex(campaign, rng)
    direction = rng.normal(size=3)
    predicted[vertex] += distance * direction / np.linalg.norm(direction)
    return predicted


# ------------------------------------------------------------------------------------- replay
class ReplayCampaign:
    """iterate_replay over hostile copies of the recording (see the module doc)."""

    def __init__(self, seed: int, options: dict):
        self.seed, self.fixture = seed, _fixture(options["bag"])

    def case(self, index: int) -> Outcome:
        from meshfg_ros.core.estimation.estimator import EstimatorInputError, EstimatorStepError
        from meshfg_ros.io.recording import RecordingError
        from meshfg_ros.replay import ReplayError, iterate_replay, load_inputs, replay_parameters

        rng = _rng(self.seed, "replay", index)
        with tempfile.TemporaryDirectory(prefix="meshfg-fuzz-") as directory:
            path = Path(directory) / "hostile"
            expected, faults = _hostile_recording(self.fixture, path, rng)
            label = ", ".join(sorted(set(faults)))
            try:
                inputs = load_inputs(path)
                steps = list(iterate_replay(inputs, replay_parameters(inputs)))
            except (RecordingError, ReplayError, EstimatorInputError, EstimatorStepError) as error:
                return Outcome(REJECTED, label, _one_line(error))
            except Exception as error:  # noqa: BLE001 - what the fuzzer looks for
                return Outcome(CRASH, label, _one_line(error))
        for step in steps:
            result = step.result
            values = (result.positions, result.position_std, result.initial_cost, result.final_cost)
            if not all(np.isfinite(np.asarray(value, dtype=np.float64)).all() for value in values):
                return Outcome(NAN, label, f"non-finite values in the step at {step.stamp_ns} ns")
        stamps = [step.stamp_ns for step in steps]
        if stamps != expected:
            return Outcome(WRONG, label, f"steps at {stamps}, expected {expected}")
        return Outcome(OK, label)


def _float64_cloud(points: np.ndarray, frame_id: str, stamp_ns: int):
    """A rosbags PointCloud2 with FLOAT64 x, y, z (1e308 and 1e200 survive, as a real driver's would)."""
    from meshfg_ros.io.messages import POINT_CLOUD2, RosbagsMessageFactory, header_msg
    from meshfg_ros.io.pointcloud import FLOAT64

    factory = RosbagsMessageFactory()
    fields = [factory.make("sensor_msgs/msg/PointField", name=name, offset=8 * axis, datatype=FLOAT64, count=1)
              for axis, name in enumerate("xyz")]
    data = np.ascontiguousarray(points, dtype="<f8").view(np.uint8).reshape(-1)
    return factory.make(POINT_CLOUD2, header=header_msg(stamp_ns, frame_id, factory), height=1, width=len(points),
                        fields=fields, is_bigendian=False, point_step=24, row_step=24 * len(points),
                        data=factory.sequence(data, np.uint8), is_dense=bool(np.isfinite(points).all()))


# Hostile additions to a recording, each drawn with probability _HOSTILE_RATE per step.
_HOSTILE_CLOUDS = ("1e308 points", "1e200 cloud", "NaN cloud", "empty cloud", "wrong frame", "repeated stamp",
                   "backward stamp", "negative stamp", "looped back")
_HOSTILE_POSES = ("far pose", "pose 3 mm off", "wrong-frame pose", "repeated pose stamp")
_HOSTILE_RATE = 0.12


def _hostile_recording(fixture: _Fixture, path: Path, rng) -> tuple[list[int], list[str]]:
    """Write the fixture's recording with hostile messages added at random steps; returns the
    stamps of the clouds that must become steps, in order (by the stamp, frame and emptiness
    rules: an independent account of what the replay must keep), and the faults added."""
    from meshfg_ros.core.inputs.input_checks import NS_PER_S
    from meshfg_ros.io.messages import PoseRecord
    from meshfg_ros.io.recording import RecordingReader, RecordingWriter
    from meshfg_ros.topics import CAMERA_POSE_TOPIC, INITIAL_MESH_TOPIC, POINTS_TOPIC, SCENARIO_TOPIC, TOOL_POSE_TOPIC

    inputs = fixture.inputs
    world = fixture.params["world_frame"]
    jump_ns = int(fixture.params["clock_jump_threshold"] * NS_PER_S)
    with RecordingReader(fixture.bag) as reader:
        scenario = [(m.log_time_ns, m.data) for m in reader.messages([SCENARIO_TOPIC])]
    start = inputs.initial_state.stamp_ns
    clouds = {cloud.stamp_ns: cloud for cloud in inputs.clouds}
    expected, faults = [], []
    newest_cloud, newest_pose = None, inputs.poses[0].stamp_ns
    with RecordingWriter(path) as writer:
        log_ns = start

        def write(topic, message):
            nonlocal log_ns
            writer.write(topic, message, log_ns)
            log_ns += 1

        write(INITIAL_MESH_TOPIC, inputs.initial_state)
        for _, message in scenario:
            write(SCENARIO_TOPIC, message)
        if inputs.camera_pose is not None:
            write(CAMERA_POSE_TOPIC, inputs.camera_pose)
        write(TOOL_POSE_TOPIC, inputs.poses[0])
        for pose in inputs.poses[1:]:
            stamp = pose.stamp_ns
            log_ns = max(log_ns, stamp)
            for name in _HOSTILE_POSES:
                if rng.random() >= _HOSTILE_RATE:
                    continue
                faults.append(name)
                moved = np.array(pose.pose)
                if name == "far pose":  # newer than the last pose, dropped by the simulator
                    moved[:3] = 1e20
                    write(TOOL_POSE_TOPIC, PoseRecord(stamp - 20, world, moved))
                elif name == "pose 3 mm off":  # a kinematics glitch: this step's pose itself
                    moved[:3] += [3e-3, 0.0, 0.0]
                    pose = PoseRecord(stamp, world, moved)
                elif name == "wrong-frame pose":
                    write(TOOL_POSE_TOPIC, PoseRecord(stamp - 30, "elsewhere", moved))
                else:
                    write(TOOL_POSE_TOPIC, PoseRecord(newest_pose, world, moved))
            write(TOOL_POSE_TOPIC, pose)
            newest_pose = stamp
            cloud = clouds.get(stamp)
            if cloud is None:
                continue
            points = cloud.points
            for name in _HOSTILE_CLOUDS:
                if rng.random() >= _HOSTILE_RATE:
                    continue
                faults.append(name)
                if name == "1e308 points":  # in the step's own cloud: those 5 are dropped as far
                    points = np.concatenate([points, np.full((5, 3), 1e308)])
                    continue
                extra, extra_stamp, frame, used = points, stamp - 10, world, False
                if name == "1e200 cloud":  # a used step with no point left
                    extra, used = np.full((len(points), 3), 1e200), True
                elif name == "NaN cloud":
                    extra = np.full((len(points), 3), np.nan)
                elif name == "empty cloud":
                    extra = np.zeros((0, 3))
                elif name == "wrong frame":
                    frame = "elsewhere"
                elif name == "negative stamp":
                    extra_stamp = -5 * 10**9
                elif newest_cloud is None:
                    continue  # nothing yet to repeat or to go back from
                elif name == "repeated stamp":
                    extra_stamp = newest_cloud
                elif name == "backward stamp":
                    extra_stamp = newest_cloud - jump_ns // 2
                else:  # looped back: the estimator restarts from the initial mesh
                    extra_stamp, used = newest_cloud - 3 * jump_ns, True
                    if extra_stamp < 0:
                        continue
                write(POINTS_TOPIC, _float64_cloud(extra, frame, extra_stamp))
                if used:
                    expected.append(extra_stamp)
                    newest_cloud = extra_stamp
            write(POINTS_TOPIC, _float64_cloud(points, cloud.frame_id, stamp))
            expected.append(stamp)
            newest_cloud = stamp
    return expected, faults


# ----------------------------------------------------------------------------------- recovery
RECOVERY_FAULTS = ("prediction shifted 1 m", "predicted vertex at 1e20", "tool pose 3 mm off for one step",
                   "cloud with 5 points at 1e308", "backward stamp")
RECOVERY_STEP = 1  # index of the cloud that gets the fault (the second: the first has no predecessor)


class RecoveryCampaign:
    """Case i injects RECOVERY_FAULTS[i] once into a replay of the recording."""

    def __init__(self, seed: int, options: dict):
        self.fixture = _fixture(options["bag"])

    def case(self, index: int) -> Outcome:
        from meshfg_ros.replay import iterate_replay

        fault = RECOVERY_FAULTS[index % len(RECOVERY_FAULTS)]
        inputs, free = self.fixture.inputs, self.fixture.steps
        faulty_stamp = free[RECOVERY_STEP].stamp_ns
        alter = None
        if fault == "prediction shifted 1 m":
            def alter(stamp, predicted):
                return predicted + [1.0, 0.0, 0.0] if stamp == faulty_stamp else predicted
        elif fault == "predicted vertex at 1e20":
            vertex = int(np.setdiff1d(inputs.initial_mesh.surface_vertices, inputs.initial_mesh.fixed_vertices)[0])

            def alter(stamp, predicted):
                if stamp != faulty_stamp:
                    return predicted
                changed = predicted.copy()
                changed[vertex] = 1e20
                return changed
        elif fault == "tool pose 3 mm off for one step":
            position = [pose.stamp_ns for pose in inputs.poses].index(faulty_stamp)
            pose = inputs.poses[position]
            push = pose.pose[:3] - inputs.poses[position - 1].pose[:3]
            changed = np.array(pose.pose)
            changed[:3] += 3e-3 * push / max(np.linalg.norm(push), 1e-12)
            poses = list(inputs.poses)
            poses[position] = replace(pose, pose=changed)
            inputs = replace(inputs, poses=tuple(poses))
        else:
            position = [cloud.stamp_ns for cloud in inputs.clouds].index(faulty_stamp)
            cloud, clouds = inputs.clouds[position], list(inputs.clouds)
            if fault == "cloud with 5 points at 1e308":
                clouds[position] = replace(cloud, points=np.concatenate([cloud.points, np.full((5, 3), 1e308)]))
            else:
                clouds[position] = replace(cloud, stamp_ns=free[RECOVERY_STEP - 1].stamp_ns - 500_000_000)
            inputs = replace(inputs, clouds=tuple(clouds))  # logged where it was: it arrives late
        try:
            steps = {step.stamp_ns: step for step in iterate_replay(inputs, self.fixture.params, alter)}
        except Exception as error:  # noqa: BLE001 - what the fuzzer looks for
            return Outcome(CRASH, fault, _one_line(error))
        errors = {}
        for offset in range(len(free) - RECOVERY_STEP):
            reference = free[RECOVERY_STEP + offset]
            step = steps.get(reference.stamp_ns)
            if step is None:
                continue
            difference = np.linalg.norm(step.result.positions - reference.result.positions, axis=1)
            errors[offset] = (float(np.sqrt(np.mean(difference**2))), float(difference.max()))
        message = steps[faulty_stamp].result.message if faulty_stamp in steps else "no estimate (cloud dropped)"
        if not all(np.isfinite(value).all() for value in errors.values()):
            return Outcome(NAN, fault, "non-finite estimate")
        return Outcome(OK, fault, message, figures=dict(fault=fault, errors=errors, steps=len(free) - RECOVERY_STEP,
                                                        against_truth=self._against_truth(steps)))

    def _against_truth(self, steps: dict) -> dict | None:
        """Vertex RMSE against the ground truth at the last step that has one, estimated in
        both replays: {"factor_graph" | "simulation": (with the fault, without)}, or None."""
        from meshfg_ros.evaluation.metrics import vertex_rmse

        truth = self.fixture.truth
        free = None if truth is None else next(
            (step for step in reversed(self.fixture.steps) if step.stamp_ns in truth and step.stamp_ns in steps), None)
        if free is None:
            return None
        faulty, reference = steps[free.stamp_ns], truth[free.stamp_ns]
        figures = {"factor_graph": (vertex_rmse(faulty.result.positions, reference),
                                    vertex_rmse(free.result.positions, reference))}
        if faulty.simulation_only is not None and free.simulation_only is not None:
            figures["simulation"] = (vertex_rmse(faulty.simulation_only, reference),
                                     vertex_rmse(free.simulation_only, reference))
        return figures


CAMPAIGNS: dict[str, type] = {"decoder": DecoderCampaign, "update": UpdateCampaign, "replay": ReplayCampaign,
                              "recovery": RecoveryCampaign}


# ------------------------------------------------------------------------------------- runner
def _worker(connection, factory, seed: int, options: dict, start: int, stop: int) -> None:
    """Worker process: set the campaign up, then run cases start..stop-1, reporting each."""
    from meshfg_ros import process_settings

    process_settings.configure()
    warnings.simplefilter("ignore")  # overflow warnings are the input's, not news
    campaign = factory(seed, options)
    for index in range(start, stop):
        connection.send(("start", index))
        connection.send(("done", index, campaign.case(index)))
    connection.send(("finished",))
    connection.close()


def run_campaign(name: str, cases: int, seed: int = 0, options: dict | None = None, timeout_s: float = 60.0,
                 isolate: bool = True, factory: type | None = None,
                 progress: Callable[[int], None] | None = None) -> CampaignCounts:
    """Run cases 0..cases-1 of campaign `name` (CAMPAIGNS, or `factory`).

    isolate: in worker processes, each case under `timeout_s` (a hang is counted and the worker
    replaced); without, in this process with no time limit (fast small slices: the tests).
    progress(cases done) is called after each case."""
    factory = factory or CAMPAIGNS[name]
    options = dict(options or {})
    counts = CampaignCounts(name)
    started = time.perf_counter()
    if not isolate:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # overflow warnings are the input's, not news
            campaign = factory(seed, options)
            for index in range(cases):
                counts.add(index, campaign.case(index))
                if progress is not None:
                    progress(counts.cases)
        counts.seconds = time.perf_counter() - started
        return counts
    context = multiprocessing.get_context("spawn")  # a fork would copy the BLAS threads' state
    next_index = 0
    while next_index < cases:
        receiver, sender = context.Pipe(duplex=False)
        worker = context.Process(target=_worker, args=(sender, factory, seed, options, next_index, cases), daemon=True)
        worker.start()
        sender.close()
        current, limit = None, SETUP_TIMEOUT_S
        try:
            while True:
                if not receiver.poll(limit):
                    if current is None:
                        raise FuzzError(f"the {name} worker did not start its first case within {limit:.0f} s")
                    counts.add(current, Outcome(HANG, f"case {current}", f"still running after {timeout_s:g} s"))
                    next_index = current + 1
                    break
                try:
                    message = receiver.recv()
                except EOFError:  # the worker died (a crash in native code)
                    if current is None:
                        raise FuzzError(f"the {name} worker ended before its first case") from None
                    counts.add(current, Outcome(CRASH, f"case {current}", f"worker exit code {worker.exitcode}"))
                    next_index = current + 1
                    break
                if message[0] == "start":
                    current, limit = message[1], timeout_s
                elif message[0] == "done":
                    counts.add(message[1], message[2])
                    current, next_index = None, message[1] + 1
                    if progress is not None:
                        progress(counts.cases)
                else:
                    next_index = cases
                    break
        finally:
            receiver.close()
            if worker.is_alive():
                worker.kill()
            worker.join()
    counts.seconds = time.perf_counter() - started
    return counts


def run_fuzz(bag, decoder_cases: int = 10_000, update_calls: int = 2_000, replays: int = 20, recovery: bool = True,
             seed: int = 0, timeout_s: float = 60.0, isolate: bool = True,
             show_progress: bool = False) -> list[CampaignCounts]:
    """All campaigns on recording `bag` (the fixture of update, replay and recovery); with
    show_progress, a progress bar per campaign on stderr."""
    plan = [("decoder", decoder_cases), ("update", update_calls), ("replay", replays),
            ("recovery", len(RECOVERY_FAULTS) if recovery else 0)]
    results = []
    for name, cases in plan:
        if not cases:
            continue
        bar = None
        if show_progress:
            from tqdm import tqdm

            bar = tqdm(total=cases, desc=f"fuzz {name}", unit="case", file=sys.stderr, dynamic_ncols=True)
        try:
            report = None if bar is None else lambda done, bar=bar: bar.update(done - bar.n)
            results.append(run_campaign(name, cases, seed, {"bag": str(bag)}, timeout_s, isolate, progress=report))
        finally:
            if bar is not None:
                bar.close()
    return results


def save(results: list[CampaignCounts], path) -> None:
    """The counts, examples and recovery figures as JSON (metres for the figures)."""
    Path(path).write_text(json.dumps([asdict(counts) for counts in results], indent=2))


def format_report(results: list[CampaignCounts]) -> str:
    """The counts table, the failures' first examples and the recovery table."""
    lines = [f"{'campaign':<10}{'cases':>8}{'accepted':>10}{'rejected':>10}{'crashes':>9}{'hangs':>7}"
             f"{'NaN out':>9}{'wrong':>7}{'seconds':>9}"]
    for counts in results:
        lines.append(f"{counts.name:<10}{counts.cases:>8}{counts.ok:>10}{counts.rejected:>10}{counts.crashes:>9}"
                     f"{counts.hangs:>7}{counts.nan_out:>9}{counts.wrong:>7}{counts.seconds:>9.1f}")
    for counts in results:
        for index, label, detail in counts.examples:
            lines.append(f"  {counts.name} case {index} ({label}): {detail}")
    recovery = [figures for counts in results if counts.name == "recovery" for figures in counts.figures]
    if recovery:
        last = max(figures["steps"] for figures in recovery) - 1
        lines += ["", f"recovery: vertex error against the fault-free replay, RMS / max over vertices in mm, at the "
                      f"faulty step (+0), the next one (+1) and the last (+{last})",
                  f"{'fault':<34}{'+0':>17}{'+1':>17}{'+' + str(last):>17}"]
        for figures in recovery:
            cells = []
            for offset in (0, 1, last):
                error = figures["errors"].get(offset)
                cells.append("no estimate" if error is None else f"{1e3 * error[0]:.3g} / {1e3 * error[1]:.3g}")
            lines.append(f"{figures['fault']:<34}" + "".join(f"{cell:>17}" for cell in cells))
        judged = [figures for figures in recovery if figures.get("against_truth")]
        if judged:
            lines += ["", f"recovery: vertex RMSE against the ground truth at the last step (+{last}), in mm, with the "
                          "fault / without it",
                      f"{'fault':<34}{'factor graph':>17}{'simulation alone':>20}"]
            for figures in judged:
                cells = [figures["against_truth"].get(method) for method in ("factor_graph", "simulation")]
                cells = ["n/a" if cell is None else f"{1e3 * cell[0]:.3g} / {1e3 * cell[1]:.3g}" for cell in cells]
                lines.append(f"{figures['fault']:<34}{cells[0]:>17}{cells[1]:>20}")
    failures = sum(counts.failures for counts in results)
    lines += ["", "goal met: no crash, hang, NaN or wrong answer" if not failures else f"{failures} failure(s)"]
    return "\n".join(lines)
