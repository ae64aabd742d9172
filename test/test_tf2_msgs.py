"""The project's tf2_msgs package: the ROS 2 Jazzy interfaces (same names, fields and type hashes),
over real DDS with rclpy, and decoded and encoded alike by the rosbags typestore of recordings."""
import json
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import rclpy.executors
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation

from meshfg_ros.core.inputs.frames import StampedTransform, TransformBuffer
from meshfg_ros.io.messages import RclpyMessageFactory, meshfg_typestore
from meshfg_ros.io.recording import RecordingReader, RecordingWriter
from meshfg_ros.io.tf_messages import (
    TF_MESSAGE,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    tf_message_to_transforms,
    transforms_to_tf_message,
)

TRANSFORMS = [
    StampedTransform("world", "ecm", 1_700_000_000_123_456_789, (0.1, -0.2, 0.3), (0.0, 0.0, np.sin(0.2), np.cos(0.2))),
    StampedTransform("ecm", "endoscope_optical_frame", 1_700_000_000_123_456_789, (0.0, 0.0, 0.05),
                     (0.5, -0.5, 0.5, -0.5)),
]


def assert_same_transforms(received, sent):
    assert [(t.parent, t.child, t.stamp_ns) for t in received] == [(t.parent, t.child, t.stamp_ns) for t in sent]
    for got, expected in zip(received, sent):
        np.testing.assert_array_equal(got.pose, expected.pose)


def test_interfaces_import_with_upstream_names():
    import tf2_msgs.action
    import tf2_msgs.msg
    import tf2_msgs.srv

    assert tf2_msgs.msg.TF2Error.TRANSFORM_ERROR == 6 and tf2_msgs.msg.TF2Error.NO_ERROR == 0
    goal = tf2_msgs.action.LookupTransform.Goal(target_frame="world", source_frame="ecm", advanced=True)
    assert (goal.target_frame, goal.advanced) == ("world", True)
    assert tf2_msgs.srv.FrameGraph.Response(frame_yaml="a: b").frame_yaml == "a: b"


@pytest.mark.parametrize("name", ["TFMessage", "TF2Error"])
def test_type_hashes_are_those_of_ros2_jazzy(name):
    """The installed type descriptions hash like the Jazzy definitions rosbags ships."""
    import tf2_msgs

    prefix = Path(tf2_msgs.__file__).resolve().parents[4]  # <prefix>/lib/pythonX.Y/site-packages/tf2_msgs
    description = json.loads((prefix / "share" / "tf2_msgs" / "msg" / f"{name}.json").read_text())
    ours = next(entry["hash_string"] for entry in description["type_hashes"] if entry["type_name"] == f"tf2_msgs/msg/{name}")
    assert ours == meshfg_typestore().hash_rihs01(f"tf2_msgs/msg/{name}")


def test_rclpy_and_rosbags_decode_each_others_bytes():
    """CDR bytes of one side decode on the other (the bytes themselves may differ in padding:
    rclpy leaves alignment padding uninitialised)."""
    factory = RclpyMessageFactory()
    rclpy_bytes = serialize_message(transforms_to_tf_message(TRANSFORMS, factory))
    rosbags_bytes = bytes(meshfg_typestore().serialize_cdr(transforms_to_tf_message(TRANSFORMS), TF_MESSAGE))
    assert len(rclpy_bytes) == len(rosbags_bytes)
    assert_same_transforms(tf_message_to_transforms(meshfg_typestore().deserialize_cdr(rclpy_bytes, TF_MESSAGE)),
                           TRANSFORMS)
    assert_same_transforms(
        tf_message_to_transforms(deserialize_message(rosbags_bytes, factory.message_class(TF_MESSAGE))), TRANSFORMS)


def test_tf_topics_recorded_and_read_back_feed_a_transform_buffer(tmp_path):
    with RecordingWriter(tmp_path / "robot") as writer:
        writer.write(TF_STATIC_TOPIC, transforms_to_tf_message(TRANSFORMS[1:]), stamp_ns=TRANSFORMS[0].stamp_ns)
        writer.write(TF_TOPIC, transforms_to_tf_message(TRANSFORMS[:1]), stamp_ns=TRANSFORMS[0].stamp_ns)
    buffer = TransformBuffer()
    with RecordingReader(tmp_path / "robot") as reader:
        assert reader.topics[TF_TOPIC].msgtype == TF_MESSAGE
        for recorded in reader.messages([TF_STATIC_TOPIC, TF_TOPIC]):
            buffer.set_transforms(tf_message_to_transforms(recorded.data), static=recorded.topic == TF_STATIC_TOPIC)
    expected = np.eye(4)
    for transform in TRANSFORMS:
        step = np.eye(4)
        step[:3, :3] = Rotation.from_quat(transform.rotation).as_matrix()
        step[:3, 3] = transform.translation
        expected = expected @ step
    np.testing.assert_allclose(buffer.lookup("world", "endoscope_optical_frame", TRANSFORMS[0].stamp_ns), expected,
                               atol=1e-15)


@pytest.mark.slow  # DDS discovery
def test_tf_message_published_is_received_over_dds():
    from tf2_msgs.msg import TFMessage

    rclpy.init()
    try:
        publisher_node, subscriber_node = rclpy.create_node("tf_publisher"), rclpy.create_node("tf_subscriber")
        received = []
        subscription = subscriber_node.create_subscription(TFMessage, "/tf", received.append, 10)
        publisher = publisher_node.create_publisher(TFMessage, "/tf", 10)
        executor = rclpy.executors.SingleThreadedExecutor()
        executor.add_node(publisher_node)
        executor.add_node(subscriber_node)

        def spin_until(condition) -> bool:
            deadline = time.monotonic() + 30.0
            while not condition() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            return condition()

        assert spin_until(lambda: publisher.get_subscription_count() == 1 and subscription.get_publisher_count() == 1), (
            "publisher and subscriber did not match in 30 s")
        publisher.publish(transforms_to_tf_message(TRANSFORMS, RclpyMessageFactory()))
        assert spin_until(lambda: received), "no TFMessage arrived within 30 s"
        assert_same_transforms(tf_message_to_transforms(received[0]), TRANSFORMS)
        endpoint = subscriber_node.get_publishers_info_by_topic("/tf")[0]
        assert endpoint.topic_type == TF_MESSAGE
        assert str(endpoint.topic_type_hash) == meshfg_typestore().hash_rihs01(TF_MESSAGE)
    finally:
        rclpy.shutdown()
