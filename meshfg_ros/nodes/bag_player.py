"""bag_player: plays a rosbag2 recording over DDS at its recorded rate, publishing /clock.

    bag_player BAG [--rate R] [--topics T ...] [--loop] [--wait-for-subscribers S] --ros-args ...

`ros2 bag play` is not on PyPI; this is the part of it the live pipeline needs. Topics keep
their recorded names (remap them with --ros-args -r OLD:=NEW) and types; messages are read
with RecordingReader and converted to rclpy messages (PointCloud2 re-encoded as FLOAT32
x, y, z: other point fields are not replayed). A topic with a single message (initial_mesh,
scenario metadata, camera pose) is published first, reliable and transient-local, like a latched
topic; the player then waits (at most --wait-for-subscribers seconds) until every played topic
has a matched subscriber, and `delay` seconds more for those subscribers to match the player
in turn (a best-effort reader drops samples of unmatched writers), and plays the others at
their recorded rate times --rate, publishing /clock (rosgraph_msgs/Clock) at clock_frequency
for nodes with use_sim_time. It exits when done (or loops with --loop).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from rosgraph_msgs.msg import Clock

from meshfg_ros.io.recording import RecordingError, RecordingReader
from meshfg_ros.nodes.ros_conversions import RCLPY_FACTORY, rclpy_message
from meshfg_ros.nodes.runtime import init_without_signal_handlers

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
STREAM_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
_ACK_TIMEOUT_S = 5.0
_POLL_S = 0.02


def _descriptor(description: str, low: float, high: float) -> ParameterDescriptor:
    return ParameterDescriptor(description=description,
                               floating_point_range=[FloatingPointRange(from_value=low, to_value=high)])


class BagPlayer(Node):
    """Publishes the topics of one recording (see the module docstring)."""

    def __init__(self, reader: RecordingReader, topics: list[str] | None = None, **kwargs) -> None:
        """reader: the open recording (the player reads it, the caller closes it); topics: default all."""
        super().__init__("bag_player", **kwargs)
        self.rate = self.declare_parameter(
            "rate", 1.0, _descriptor("Playback speed: 1 is the recorded rate, 2 twice as fast.", 1e-3, 1e3)).value
        self.wait_for_subscribers = self.declare_parameter(
            "wait_for_subscribers", 10.0,
            _descriptor("Seconds to wait for a subscriber on every played topic before playing.", 0.0, 3600.0)).value
        self.clock_frequency = self.declare_parameter(
            "clock_frequency", 100.0,
            _descriptor("Rate of /clock messages between recorded ones (Hz).", 1.0, 1e4)).value
        self.delay = self.declare_parameter(
            "delay", 0.5, _descriptor("Seconds between finding the subscribers and playing: best-effort readers "
                                      "drop messages of a writer they have not matched yet.", 0.0, 3600.0)).value
        self.loop = self.declare_parameter(
            "loop", False, ParameterDescriptor(description="Start again at the end of the recording.")).value
        self._reader = reader
        names = list(dict.fromkeys(topics)) if topics else sorted(reader.topics)
        self._latched = [name for name in names if self._reader.topics[name].count == 1]
        self._streamed = [name for name in names if name not in self._latched]
        self._topic_publishers = {
            name: self.create_publisher(RCLPY_FACTORY.message_class(self._reader.topics[name].msgtype), name,
                                        LATCHED_QOS if name in self._latched else STREAM_QOS)
            for name in names
        }
        self._clock_publisher = self.create_publisher(Clock, "/clock", CLOCK_QOS)
        self.published = 0

    def play(self) -> int:
        """Publish the recording (again and again with loop); the number of messages published."""
        for message in self._reader.messages(self._latched) if self._latched else ():  # [] would mean all
            self._publish_clock(message.log_time_ns)
            self._publish(message)
        self._wait_for_subscribers()
        time.sleep(self.delay)
        while True:
            self._play_streamed()
            if not self.loop:
                break
        for publisher in self._topic_publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=_ACK_TIMEOUT_S))
        return self.published

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.wait_for_subscribers
        while time.monotonic() < deadline:
            if all(publisher.get_subscription_count() for publisher in self._topic_publishers.values()):
                return
            time.sleep(_POLL_S)
        lonely = [name for name, publisher in self._topic_publishers.items() if not publisher.get_subscription_count()]
        if lonely:
            self.get_logger().warning(f"playing without subscribers on {', '.join(lonely)}")

    def _play_streamed(self) -> None:
        if not self._streamed:
            return
        start_ns, start_s = None, time.monotonic()
        for message in self._reader.messages(self._streamed):
            if start_ns is None:
                start_ns = message.log_time_ns
            due_s = start_s + (message.log_time_ns - start_ns) / 1e9 / self.rate
            while (remaining := due_s - time.monotonic()) > 0.0:
                time.sleep(min(remaining, 1.0 / self.clock_frequency))
                elapsed_s = min(time.monotonic(), due_s) - start_s
                self._publish_clock(start_ns + int(elapsed_s * self.rate * 1e9))
            self._publish_clock(message.log_time_ns)
            self._publish(message)

    def _publish(self, message) -> None:
        self._topic_publishers[message.topic].publish(rclpy_message(message.data))
        self.published += 1

    def _publish_clock(self, stamp_ns: int) -> None:
        clock = Clock()
        clock.clock.sec, clock.clock.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self._clock_publisher.publish(clock)


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    """Command line without the ROS arguments (argv[0] is the program name)."""
    parser = argparse.ArgumentParser(prog="bag_player", description="Play a rosbag2 recording over DDS.")
    parser.add_argument("bag", type=Path, help="recording directory (with metadata.yaml)")
    parser.add_argument("--rate", type=float, help="playback speed (overrides parameter rate)")
    parser.add_argument("--topics", nargs="+", help="play only these topics (default: all)")
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument("--wait-for-subscribers", type=float,
                        help="seconds to wait for subscribers (overrides the parameter)")
    return parser.parse_args(remove_ros_args(argv)[1:])


def main(args=None) -> int:
    """Console script `bag_player`."""
    argv = sys.argv if args is None else args
    options = parse_arguments(argv)
    if options.rate is not None and options.rate <= 0.0:
        print("bag_player: --rate must be > 0", file=sys.stderr)
        return 2
    try:
        reader = RecordingReader(options.bag)
        for topic in options.topics or ():
            reader.require(topic)
    except RecordingError as error:
        print(f"bag_player: {error}", file=sys.stderr)
        return 1
    init_without_signal_handlers(argv)
    player = None
    try:
        player = BagPlayer(reader, options.topics)
        if options.rate is not None:
            player.rate = options.rate
        if options.wait_for_subscribers is not None:
            player.wait_for_subscribers = options.wait_for_subscribers
        player.loop = player.loop or options.loop
        count = player.play()
        player.get_logger().info(f"played {count} messages from {options.bag}")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RecordingError as error:  # a corrupt message found while playing
        print(f"bag_player: {error}", file=sys.stderr)
        return 1
    finally:
        reader.close()
        if player is not None:
            player.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
