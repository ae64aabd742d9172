"""Clouds and tool poses in any frame, moved into world_frame at their own stamps, without ROS.

A camera on a moving arm (an endoscope) gives clouds in its optical frame and a robot gives tool
poses in its base frame; /tf and /tf_static say where those frames are over time
(core/inputs/frames.py). `WorldFrameInputs` releases each input moved into world_frame as soon as the
transform buffer can place it at its stamp. An input whose frame is not known yet, or whose
stamp lies beyond the newest transform of a moving frame, waits (at most `wait_s` of the
caller's clock, or until `flush`); after that it is set aside with the lookup's reason. Inputs
wait in one queue per kind and frame, so the order of each stream is kept and an input in an
unknown frame holds up no other frame's; what one call releases comes in arrival order. Frames
with a static fallback pose (the camera_pose parameter) are used when the buffer knows nothing
of them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from meshfg_ros.core.inputs.frames import FrameLookupError, TransformBuffer, transform_points

CLOUD, POSE = "cloud", "pose"


@dataclass(frozen=True, eq=False)
class FramedInput:
    """A cloud (K, 3) or a tool pose (7,) in `frame_id` at `stamp_ns`, received at `arrival_s`.

    A placed cloud carries `viewpoint`, the sensor's centre in world_frame at its stamp (the
    origin of WorldFrameInputs' `viewpoint_frame`), or None where that frame cannot be placed."""

    kind: str
    stamp_ns: int
    frame_id: str
    data: np.ndarray
    arrival_s: float = 0.0
    viewpoint: np.ndarray | None = None


@dataclass(frozen=True)
class Unplaceable:
    """An input that could not be moved into world_frame, and why (one line)."""

    item: FramedInput
    reason: str


def pose_in(matrix: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The pose (7,: xyz, quaternion xyzw) given in a frame, expressed through `matrix` (4x4, that
    frame's points into the target frame)."""
    rotation = Rotation.from_matrix(matrix[:3, :3]) * Rotation.from_quat(pose[3:])
    return np.concatenate([matrix[:3, :3] @ pose[:3] + matrix[:3, 3], rotation.as_quat()])


# Wall time an input waits for /tf to place it (the transform_timeout parameter's default).
DEFAULT_TRANSFORM_WAIT_S = 0.5


class WorldFrameInputs:
    """The FIFO of inputs waiting for their frame (module docstring)."""

    def __init__(self, world_frame: str, transforms: TransformBuffer | None = None,
                 fallback: dict[str, np.ndarray] | None = None, wait_s: float = DEFAULT_TRANSFORM_WAIT_S,
                 viewpoint_frame: str | None = None) -> None:
        self.world_frame = world_frame
        self.viewpoint_frame = viewpoint_frame  # the sensor's frame: its origin is each cloud's viewpoint
        self.transforms = transforms if transforms is not None else TransformBuffer()
        self.fallback = dict(fallback or {})  # frame -> 4x4 (its points into world_frame)
        self.wait_s = wait_s
        self._queues: dict[tuple[str, str], deque[tuple[int, FramedInput]]] = {}
        self._arrivals = 0

    @property
    def waiting(self) -> int:
        """Inputs held for a transform."""
        return sum(len(queue) for queue in self._queues.values())

    def add(self, item: FramedInput, now_s: float = 0.0) -> tuple[list[FramedInput], list[Unplaceable]]:
        """Queue an input; returns the inputs now placed in world_frame (in arrival order) and
        those set aside."""
        self._queues.setdefault((item.kind, item.frame_id), deque()).append((self._arrivals, item))
        self._arrivals += 1
        return self.release(now_s)

    def release(self, now_s: float = 0.0, flush: bool = False) -> tuple[list[FramedInput], list[Unplaceable]]:
        """Place what the buffer can now place (call after new transforms and periodically)."""
        placed, set_aside = [], []
        for queue in self._queues.values():
            while queue:
                arrival, item = queue[0]
                try:
                    placed.append((arrival, self._placed(item)))
                except FrameLookupError as error:
                    waited = now_s - item.arrival_s
                    if not flush and waited < self.wait_s and error.reason != FrameLookupError.TOO_OLD:
                        break
                    set_aside.append(Unplaceable(item, str(error)))
                queue.popleft()
        self._queues = {key: queue for key, queue in self._queues.items() if queue}
        return [item for _, item in sorted(placed, key=lambda entry: entry[0])], set_aside

    def matrix_to_world(self, frame_id: str, stamp_ns: int | None) -> np.ndarray:
        """4x4 mapping points in frame_id into world_frame at stamp_ns (None: at the newest stamp
        the transforms between them allow, as tf2's time zero), placed as inputs are (with the
        static fallback poses); FrameLookupError when it cannot be."""
        if stamp_ns is None:
            try:
                stamp_ns = self.transforms.newest_stamp(self.world_frame, frame_id)
            except FrameLookupError:
                pass  # a fallback frame, or the lookup below says why it cannot be placed
        matrix = self._matrix(frame_id, 0 if stamp_ns is None else stamp_ns)
        return np.eye(4) if matrix is None else matrix

    def _matrix(self, frame_id: str, stamp_ns: int) -> np.ndarray | None:
        """frame_id's points into world_frame at stamp_ns (None: the identity), or FrameLookupError."""
        if frame_id == self.world_frame:
            return None
        try:
            return self.transforms.lookup(self.world_frame, frame_id, stamp_ns)
        except FrameLookupError as error:
            if frame_id not in self.fallback or error.reason != FrameLookupError.UNKNOWN_FRAME:
                raise
            return self.fallback[frame_id]

    def _viewpoint(self, item: FramedInput, matrix: np.ndarray | None) -> np.ndarray | None:
        """viewpoint_frame's origin at the cloud's stamp (`matrix`: the cloud frame's, reused when
        the cloud comes in viewpoint_frame), or None where it cannot be placed."""
        if self.viewpoint_frame is None:
            return None
        if item.frame_id != self.viewpoint_frame:
            try:
                matrix = self._matrix(self.viewpoint_frame, item.stamp_ns)
            except FrameLookupError:
                return None
        return np.zeros(3) if matrix is None else np.array(matrix[:3, 3], dtype=np.float64)

    def _placed(self, item: FramedInput) -> FramedInput:
        matrix = self._matrix(item.frame_id, item.stamp_ns)
        if item.kind == CLOUD:
            points = item.data if matrix is None else transform_points(matrix, item.data)
            return FramedInput(CLOUD, item.stamp_ns, self.world_frame, points, item.arrival_s,
                               viewpoint=self._viewpoint(item, matrix))
        if matrix is None:
            return item
        return FramedInput(POSE, item.stamp_ns, self.world_frame, pose_in(matrix, item.data), item.arrival_s)
