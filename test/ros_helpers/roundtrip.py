"""Child process of the DDS round-trip tests: publish or receive one message, via real DDS.

    python -m ros_helpers.roundtrip publish  TYPE IN.npz OUT.npz  # publishes until OUT.npz exists
    python -m ros_helpers.roundtrip receive  TYPE OUT.npz         # writes the received fields

TYPE is TetraMesh or EstimatorStatus; the fields travel through .npz files so the parent
compares what was sent with what arrived. The receiver writes OUT.npz atomically; its
appearance is the publisher's signal to stop (waiting for DDS to report the subscriber gone
instead depends on Fast DDS noticing a departed participant, which a loaded machine can
delay past any fixed timeout).
"""
import os
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from meshfg_msgs.msg import EstimatorStatus, TetraMesh

TOPIC = "roundtrip"
QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
TYPES = {"TetraMesh": TetraMesh, "EstimatorStatus": EstimatorStatus}


def fields_to_arrays(msg) -> dict:
    out = {"header.stamp.sec": np.array(msg.header.stamp.sec),
           "header.stamp.nanosec": np.array(msg.header.stamp.nanosec),
           "header.frame_id": np.array(msg.header.frame_id)}
    for name in msg.get_fields_and_field_types():
        if name != "header":
            out[name] = np.asarray(getattr(msg, name))
    return out


def arrays_to_msg(msg_type, arrays) -> object:
    msg = msg_type()
    msg.header.stamp.sec = int(arrays["header.stamp.sec"])
    msg.header.stamp.nanosec = int(arrays["header.stamp.nanosec"])
    msg.header.frame_id = str(arrays["header.frame_id"])
    for name, kind in msg.get_fields_and_field_types().items():
        if name == "header":
            continue
        value = arrays[name]
        if kind.startswith("sequence"):
            setattr(msg, name, value)
        elif kind == "string":
            setattr(msg, name, str(value))
        elif kind == "boolean":
            setattr(msg, name, bool(value))
        elif kind == "double":
            setattr(msg, name, float(value))
        else:
            setattr(msg, name, int(value))
    return msg


def main(mode: str, type_name: str, path: str, received_path: str = "",
         timeout_s: float = 60.0) -> int:
    msg_type = TYPES[type_name]
    rclpy.init()
    node = rclpy.create_node(f"roundtrip_{mode}")
    try:
        deadline = time.monotonic() + timeout_s
        if mode == "publish":
            publisher = node.create_publisher(msg_type, TOPIC, QOS)
            publisher.publish(arrays_to_msg(msg_type, dict(np.load(path))))
            # Transient-local + reliable: the late-joining subscriber gets it; stay alive
            # until the receiver has written what it got.
            while not Path(received_path).exists():
                if time.monotonic() > deadline:
                    print("receiver never confirmed", file=sys.stderr)
                    return 2
                rclpy.spin_once(node, timeout_sec=0.05)
            return 0
        received = []
        node.create_subscription(msg_type, TOPIC, received.append, QOS)
        while not received and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        if not received:
            print("no message received", file=sys.stderr)
            return 2
        partial = f"{path}.partial.npz"
        np.savez(partial, **fields_to_arrays(received[0]))
        os.replace(partial, path)
        return 0
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:5]))
