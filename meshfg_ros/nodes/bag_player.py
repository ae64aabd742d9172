"""bag_player: plays a rosbag2 recording over DDS at its recorded rate, publishing /clock.

    bag_player BAG [--rate R] [--topics T ...] [--loop] [--wait-for-subscribers S] --ros-args ...

`ros2 bag play` is not on PyPI; this is the part of it the live pipeline needs. Topics keep
their recorded names (remap them with --ros-args -r OLD:=NEW) and types; messages are read
with RecordingReader and converted to rclpy messages (PointCloud2 re-encoded as FLOAT32
x, y, z: other point fields are not replayed). A topic with a single message (initial_mesh,
scenario metadata, camera pose) is published first, reliable and transient-local, like a latched
topic; the player then waits (at most --wait-for-subscribers seconds) until every topic given
with --topics, or (playing everything) every topic some node subscribes to, has `subscribers`
matched subscribers (default 1), and `delay` seconds more for those subscribers to match the player
in turn (a best-effort reader drops samples of unmatched writers), and plays the others at
their recorded rate times --rate, publishing /clock (rosgraph_msgs/Clock) at clock_frequency
for nodes with use_sim_time. It exits when done (or loops with --loop). Its parameters
(meshfg_ros.parameters.PlaybackConfig) are listed by --help.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from meshfg_ros.core.inputs.input_checks import NS_PER_S
from meshfg_ros.io.recording import RecordingError, RecordingReader
from meshfg_ros.nodes.ros_conversions import RCLPY_FACTORY, rclpy_message
from meshfg_ros.nodes.ros_parameters import declare_parameters
from meshfg_ros.nodes.runtime import ArgumentError, init_without_signal_handlers, program_arguments
from meshfg_ros.parameters import ParameterError, load_parameters, parameters_help

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
STREAM_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
_ACK_TIMEOUT_S = 5.0
_POLL_S = 0.02
_SETTLE_S = 0.5  # the subscribed topics must stay the same this long before playing starts


class BagPlayer(Node):
    """Publishes the topics of one recording (see the module docstring)."""

    def __init__(self, reader: RecordingReader, topics: list[str] | None = None, **kwargs) -> None:
        """reader: the open recording (the player reads it, the caller closes it); topics: default all."""
        super().__init__("bag_player", **kwargs)
        params = declare_parameters(self, "bag_player")
        self.rate, self.wait_for_subscribers = params["rate"], params["wait_for_subscribers"]
        self.subscribers = params["subscribers"]
        self.clock_frequency, self.delay, self.loop = params["clock_frequency"], params["delay"], params["loop"]
        self._reader = reader
        names = list(dict.fromkeys(topics)) if topics else sorted(reader.topics)
        self._chosen = bool(topics)  # topics named by the user are all waited for
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
        """Wait (at most wait_for_subscribers) until the topics to wait for are matched (each by
        `subscribers` readers) and that set has not changed for _SETTLE_S. Topics named with --topics are all waited for; when the whole
        recording plays, only those some node subscribes to (not the ground truth, the metadata)."""
        deadline = time.monotonic() + self.wait_for_subscribers
        last, settled_since = None, time.monotonic()
        while time.monotonic() < deadline:
            # by the publisher's own (remapped) topic name: count_subscribers does not remap
            wanted = frozenset(name for name, publisher in self._topic_publishers.items()
                               if self._chosen or self.count_subscribers(publisher.topic_name))
            matched = frozenset(name for name, publisher in self._topic_publishers.items()
                                if publisher.get_subscription_count() >= self.subscribers)
            if (wanted, matched) != last:
                last, settled_since = (wanted, matched), time.monotonic()
            elif wanted and wanted <= matched and time.monotonic() - settled_since >= _SETTLE_S:
                break
            time.sleep(_POLL_S)
        short = [f"{name} ({count} of {self.subscribers})" for name, publisher in self._topic_publishers.items()
                 if (count := publisher.get_subscription_count()) < self.subscribers]
        if short:
            self.get_logger().info(f"playing with fewer readers than asked for on {', '.join(short)}")

    def _play_streamed(self) -> None:
        if not self._streamed:
            return
        start_ns, start_s = None, time.monotonic()
        for message in self._reader.messages(self._streamed):
            if start_ns is None:
                start_ns = message.log_time_ns
            due_s = start_s + (message.log_time_ns - start_ns) / NS_PER_S / self.rate
            while (remaining := due_s - time.monotonic()) > 0.0:
                time.sleep(min(remaining, 1.0 / self.clock_frequency))
                elapsed_s = min(time.monotonic(), due_s) - start_s
                self._publish_clock(start_ns + int(elapsed_s * self.rate * NS_PER_S))
            self._publish_clock(message.log_time_ns)
            self._publish(message)

    def _publish(self, message) -> None:
        self._topic_publishers[message.topic].publish(rclpy_message(message.data))
        self.published += 1

    def _publish_clock(self, stamp_ns: int) -> None:
        clock = Clock()
        clock.clock.sec, clock.clock.nanosec = divmod(int(stamp_ns), NS_PER_S)
        self._clock_publisher.publish(clock)


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    """Command line without the ROS arguments (argv[0] is the program name); ArgumentError when
    the ROS arguments cannot be parsed."""
    parser = argparse.ArgumentParser(prog="bag_player", description="Play a rosbag2 recording over DDS.",
                                     epilog=parameters_help(["bag_player"]),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", type=Path, help="recording directory (with metadata.yaml)")
    parser.add_argument("--rate", type=float, help="playback speed (overrides parameter rate)")
    parser.add_argument("--topics", nargs="+", help="play only these topics (default: all)")
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument("--wait-for-subscribers", type=float,
                        help="seconds to wait for subscribers (overrides the parameter)")
    return parser.parse_args(program_arguments(argv)[1:])


def main(args=None) -> int:
    """Console script `bag_player`."""
    argv = sys.argv if args is None else args
    try:
        options = parse_arguments(argv)
    except ArgumentError as error:
        print(f"bag_player: {error}", file=sys.stderr)
        return 1
    overrides = {name: value for name, value in (("rate", options.rate),
                                                 ("wait_for_subscribers", options.wait_for_subscribers))
                 if value is not None}
    try:
        load_parameters(overrides, "bag_player")  # the options' values, checked as the parameters are
    except ParameterError as error:
        print(f"bag_player: invalid parameters: {error}", file=sys.stderr)
        return 1
    try:
        reader = RecordingReader(options.bag)
        for topic in options.topics or ():
            reader.require(topic)
    except RecordingError as error:
        print(f"bag_player: {error}", file=sys.stderr)
        return 1
    player = None
    try:
        init_without_signal_handlers(argv)
        player = BagPlayer(reader, options.topics)
        for name, value in overrides.items():  # the options win over the parameters
            setattr(player, name, value)
        player.loop = player.loop or options.loop
        count = player.play()
        player.get_logger().info(f"played {count} messages from {options.bag}")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (RecordingError, ArgumentError) as error:  # RecordingError: a corrupt message found while playing
        print(f"bag_player: {error}", file=sys.stderr)
        return 1
    except ParameterError as error:
        print(f"bag_player: invalid parameters: {error}", file=sys.stderr)
        return 1
    finally:
        reader.close()
        if player is not None:
            player.destroy_node()
        gc.collect()  # a player whose constructor raised, finalised while the context is valid (runtime.run_nodes)
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
