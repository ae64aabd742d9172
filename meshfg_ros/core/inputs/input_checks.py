"""Checks of hostile but well-formed input: stamps, coordinates far outside the scene, and the
prediction's innovation against the cloud. ROS-free; the estimator, the offline replay and the
nodes share them, so that they treat every input alike.

Stamps (the one rule of meshfg_ros):
- A stamp is an integer number of nanoseconds (a Python or numpy integer, never a bool or a
  float) in [0, 2**63): `check_stamp`. `SlidingWindowEstimator.update` raises
  EstimatorStampError for anything else and for a stamp that is not newer than its last one.
- A stream of stamped messages (the clouds of the estimator node and of the replay, the tool
  poses of the simulation node and of the replay) is taken in arrival order: the order of
  reception live, the log-time order of a recording offline. `stamp_order` classifies each
  stamp against the newest one taken so far:
    INVALID    outside [0, 2**63) (a negative header time): dropped and counted;
    NEWER      newer than it: taken;
    STALE      equal to it, or older by at most clock_jump_threshold (a repeated or re-ordered
               message): dropped and counted;
    JUMP_BACK  older by more than clock_jump_threshold (a looped recording, a restarted
               sensor): the stream restarts, and so does the estimator (or the simulator's
               timeline) from the initial mesh; the stamp is taken.

Scene: the initial mesh's axis-aligned bounding box, with centre c and diagonal L (`Scene`). A
coordinate is far outside it when it lies more than FAR_DIAGONALS * L from c along an axis. The
estimator drops (and counts) far cloud points, rejects a far prediction (the step runs degraded
on the copy-forward) and ignores a far tool pose; the simulation node and the replay drop far tool
poses, the simulation node far estimates. An initial mesh itself must lie within
MAX_WORLD_COORDINATE of the world origin (`check_initial_mesh`).

Innovation: a prediction is rejected when the cloud contradicts it far beyond the measurement
noise (`innovation_spread`, see core/estimation/measurement_selection.py's `innovation_test`).

Every rejection the estimator makes is one of the REJECTIONS below: its status message carries
the reason's text, and the nodes count them by it (`rejections_in`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshfg_ros.core.geometry.mesh import inverted_elements

__all__ = [
    "FAR_DIAGONALS",
    "INVALID",
    "JUMP_BACK",
    "MAX_STAMP_NS",
    "MAX_WORLD_COORDINATE",
    "NEWER",
    "REJECTIONS",
    "STALE",
    "Scene",
    "SceneError",
    "StampError",
    "check_initial_mesh",
    "check_stamp",
    "flat_elements",
    "innovation_sample",
    "innovation_spread",
    "DEFAULT_CLOCK_JUMP_THRESHOLD_S",
    "NS_PER_S",
    "rejections_in",
    "stamp_order",
]

NS_PER_S = 1_000_000_000
# A stamp this much older than its stream's newest is a jump back (a looped recording), not a
# late message: the default of every stream's rule (the clock_jump_threshold parameter).
DEFAULT_CLOCK_JUMP_THRESHOLD_S = 1.0
MAX_STAMP_NS = 2**63  # stamps are int64 nanoseconds (builtin_interfaces/Time: int32 s, uint32 ns, >= 0 here)
INVALID, NEWER, STALE, JUMP_BACK = "invalid", "newer", "stale", "jump back"

# Far = beyond this many bounding-box diagonals of the initial mesh from its centre (per axis).
# Tissue held by its boundary deforms by a fraction of its size, and the free bodies of the
# scenes move by less than their size over a recording: ten diagonals leave an order of magnitude
# for real motion, and for background points of a wide camera view (which the gate drops anyway),
# while everything that passes stays at the scene's scale, where the squares and fourth powers of
# coordinate differences taken by the closest-point projection, the FEM and the solver can neither
# overflow nor round the mesh's own size away (a vertex at 1e20 m or a point at 1e308 m did).
FAR_DIAGONALS = 10.0
# An initial mesh must lie within this many metres of the world origin: the range of the
# camera_pose parameter, the workspace of a robot's world frame.
MAX_WORLD_COORDINATE = 1e3
# Robust spread (1.4826 median) of a normal's absolute values.
_MEDIAN_ABSOLUTE_TO_SIGMA = 1.4826
# The innovation test looks at most this many points of a cloud (evenly strided): the median of
# 256 distances is within ~8 % (one standard error) of the whole cloud's, far inside the test's
# margins, and their query costs 0.4 ms on the paper-scale surface.
INNOVATION_SAMPLE = 256

# Rejections the estimator makes, by the name of the estimator node's counter of them: the
# reason's text, which the status message carries.
REJECTIONS = {
    "clouds_with_far_points": "point(s) far outside the scene dropped",
    "predictions_rejected_far": "prediction rejected: far outside the scene",
    "predictions_rejected_inverted": "prediction rejected: inverted or flat elements",
    "predictions_rejected_innovation": "prediction rejected: contradicted by the cloud",
    "tool_poses_ignored_far": "tool pose ignored: far outside the scene",
}


class StampError(ValueError):
    """A stamp that is not an integer number of nanoseconds in [0, 2**63)."""


class SceneError(ValueError):
    """An initial mesh with non-finite coordinates, no extent, or far from the world origin."""


def check_stamp(stamp_ns) -> int:
    """`stamp_ns` as an int, or StampError: an integer (not a bool) in [0, 2**63)."""
    if isinstance(stamp_ns, (bool, np.bool_)) or not isinstance(stamp_ns, (int, np.integer)):
        raise StampError(f"stamp must be an integer number of nanoseconds, got {type(stamp_ns).__name__}")
    stamp = int(stamp_ns)
    if not 0 <= stamp < MAX_STAMP_NS:
        raise StampError(f"stamp {stamp} ns is outside [0, 2**63)")
    return stamp


def stamp_order(newest_ns: int | None, stamp_ns: int, jump_ns: int) -> str:
    """INVALID, NEWER, STALE or JUMP_BACK: the integer `stamp_ns` against the newest stamp taken
    so far (None: none yet) in a stream whose clock_jump_threshold is `jump_ns` (module doc)."""
    if not 0 <= stamp_ns < MAX_STAMP_NS:
        return INVALID
    if newest_ns is None or stamp_ns > newest_ns:
        return NEWER
    return STALE if newest_ns - stamp_ns <= jump_ns else JUMP_BACK


@dataclass(frozen=True)
class Scene:
    """The initial mesh's bounding box: centre (3,), diagonal L [m] and the far limit [m] per axis."""

    centre: np.ndarray
    diagonal: float

    @classmethod
    def of(cls, vertices: np.ndarray) -> Scene:
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        return cls(0.5 * (low + high), float(np.linalg.norm(high - low)))

    @property
    def limit(self) -> float:
        """Distance from the centre along an axis beyond which a coordinate is far."""
        return FAR_DIAGONALS * self.diagonal

    def far(self, positions: np.ndarray) -> np.ndarray:
        """(K,) whether each position (K, 3) (finite) is far outside the scene."""
        return np.abs(positions - self.centre).max(axis=1, initial=0.0) > self.limit

    def describe(self, positions: np.ndarray) -> str:
        """Where the farthest of `positions` lies, for a rejection's message."""
        offsets = np.abs(positions - self.centre).max(axis=1)
        worst = int(np.argmax(offsets))
        return f"{offsets[worst]:.3g} m from the scene's centre (limit {self.limit:.3g} m, index {worst})"


def check_initial_mesh(vertices: np.ndarray) -> Scene:
    """The scene of an initial mesh's vertices (N, 3), or SceneError."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not len(vertices) or not np.all(np.isfinite(vertices)):
        raise SceneError(f"initial mesh vertices must be finite with shape (N, 3), got {vertices.shape}")
    largest = float(np.abs(vertices).max())
    if largest > MAX_WORLD_COORDINATE:
        raise SceneError(f"initial mesh has a vertex {largest:.3g} m from the world origin "
                         f"(at most {MAX_WORLD_COORDINATE:g} m)")
    scene = Scene.of(vertices)
    if not scene.diagonal > 0.0:
        raise SceneError("initial mesh has no extent (all vertices coincide)")
    return scene


def flat_elements(vertices: np.ndarray, tetrahedra: np.ndarray) -> int:
    """How many tetrahedra of `vertices` (N, 3) have a volume <= 0 (or NaN)."""
    return int(inverted_elements(vertices, tetrahedra).size)


def innovation_spread(distances: np.ndarray) -> float:
    """Robust spread 1.4826 median(distances) of a cloud's distances to a surface [m]."""
    return _MEDIAN_ABSOLUTE_TO_SIGMA * float(np.median(distances))


def innovation_sample(values: np.ndarray) -> np.ndarray:
    """At most INNOVATION_SAMPLE of a cloud's `values` (K, ...): its points or their distances,
    evenly strided through the cloud."""
    stride = max(1, -(-len(values) // INNOVATION_SAMPLE))
    return values[::stride]


def rejections_in(message: str) -> list[str]:
    """Counter names (REJECTIONS keys) of the rejections a status message reports."""
    return [name for name, reason in REJECTIONS.items() if reason in message]
