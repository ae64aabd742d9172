"""The nodes' listener of /tf and /tf_static: inputs in any frame, handed on in world_frame.

A thin shell over core.inputs.world_frame.WorldFrameInputs (the replay uses the same placement through
parameters.world_frame_inputs): it subscribes tf2_msgs/TFMessage on /tf and /tf_static (static
transforms latched, as tf2_ros publishes them), feeds the transform buffer, and hands each
placed input to `on_placed(FramedInput)` and each one that cannot be placed to
`on_set_aside(Unplaceable)`, in arrival order, from the executor thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from meshfg_ros.core.inputs.world_frame import FramedInput, Unplaceable, WorldFrameInputs
from meshfg_ros.io.tf_messages import TF_STATIC_TOPIC, TF_TOPIC, tf_message_to_transforms

TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
_RELEASE_PERIOD_S = 0.02


class FrameInputs:
    """Places a node's inputs into world_frame (module docstring)."""

    def __init__(self, node: Node, placer: WorldFrameInputs, on_placed: Callable[[FramedInput], None],
                 on_set_aside: Callable[[Unplaceable], None]) -> None:
        self.placer = placer
        self._on_placed, self._on_set_aside = on_placed, on_set_aside
        self._logger = node.get_logger()
        node.create_subscription(TFMessage, TF_TOPIC, lambda msg: self._on_transforms(msg, False), TF_QOS)
        node.create_subscription(TFMessage, TF_STATIC_TOPIC, lambda msg: self._on_transforms(msg, True),
                                 TF_STATIC_QOS)
        node.create_timer(_RELEASE_PERIOD_S, self.release, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def add(self, item: FramedInput) -> None:
        """Take an input in its own frame."""
        self._hand_on(*self.placer.add(item, time.monotonic()))

    def release(self) -> None:
        """Hand on what the transforms received so far place, and give up on what waited too long."""
        if self.placer.waiting:
            self._hand_on(*self.placer.release(time.monotonic()))

    def _on_transforms(self, msg: TFMessage, static: bool) -> None:
        for reason in self.placer.transforms.set_transforms(tf_message_to_transforms(msg), static=static):
            self._logger.warning(f"{TF_STATIC_TOPIC if static else TF_TOPIC}: transform rejected: {reason}",
                                 throttle_duration_sec=1.0)
        self.release()

    def _hand_on(self, placed: list[FramedInput], set_aside: list[Unplaceable]) -> None:
        for item in set_aside:
            self._on_set_aside(item)
        for item in placed:
            self._on_placed(item)
