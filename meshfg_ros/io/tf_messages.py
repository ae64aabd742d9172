"""tf2_msgs/TFMessage (/tf, /tf_static) <-> the StampedTransforms of core.inputs.frames.

Fields are read by name, so both rosbags' classes and the rosidl-generated ones of rclpy work;
building a message takes a MessageFactory of io.messages (rosbags by default). Nothing here
imports rclpy.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from meshfg_ros.core.inputs.frames import StampedTransform
from meshfg_ros.io.messages import MessageFactory, RosbagsMessageFactory, header_msg, stamp_ns_from_msg

__all__ = ["TF_MESSAGE", "TF_STATIC_TOPIC", "TF_TOPIC", "tf_message_to_transforms", "transforms_to_tf_message"]

TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"


def tf_message_to_transforms(msg: Any) -> list[StampedTransform]:
    """The transforms of a TFMessage of either flavour, in message order."""
    transforms = []
    for stamped in msg.transforms:
        translation, rotation = stamped.transform.translation, stamped.transform.rotation
        transforms.append(StampedTransform(
            parent=stamped.header.frame_id,
            child=stamped.child_frame_id,
            stamp_ns=stamp_ns_from_msg(stamped.header.stamp),
            translation=(translation.x, translation.y, translation.z),
            rotation=(rotation.x, rotation.y, rotation.z, rotation.w),
        ))
    return transforms


def transforms_to_tf_message(transforms: Iterable[StampedTransform], factory: MessageFactory | None = None) -> Any:
    """A TFMessage holding `transforms` (factory: rosbags by default, or rclpy)."""
    factory = RosbagsMessageFactory() if factory is None else factory
    stamped = []
    for transform in transforms:
        x, y, z, qx, qy, qz, qw = (float(value) for value in transform.pose)
        stamped.append(factory.make(
            "geometry_msgs/msg/TransformStamped",
            header=header_msg(transform.stamp_ns, transform.parent, factory),
            child_frame_id=transform.child,
            transform=factory.make(
                "geometry_msgs/msg/Transform",
                translation=factory.make("geometry_msgs/msg/Vector3", x=x, y=y, z=z),
                rotation=factory.make("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
            ),
        ))
    return factory.make(TF_MESSAGE, transforms=stamped)
