"""bag_player's pacing, in the test process against a virtual clock: no DDS traffic, no wall time.

The player's `time.monotonic` and `time.sleep` are replaced by a clock that advances only when
the player sleeps, and its publish calls are recorded instead of sent, so the schedule it
follows is exact (test_nodes.py plays over real DDS and checks what arrives).
"""
import numpy as np
import pytest
import rclpy

from meshfg_ros.io.messages import MeshState, PointCloudRecord, PoseRecord
from meshfg_ros.io.recording import RecordingReader, RecordingWriter
from meshfg_ros.nodes import bag_player
from meshfg_ros.nodes.bag_player import BagPlayer

S = 1_000_000_000  # ns per second
STAMPS_NS = [S + k * S // 5 for k in range(4)]  # 0.2 s apart


class VirtualClock:
    """time.monotonic / time.sleep for the player: sleeping is what moves the clock."""

    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds >= 0.0
        self.now += seconds


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Initial mesh (one message: played first, latched), then a tool pose and a cloud per stamp."""
    path = tmp_path_factory.mktemp("bag") / "small"
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with RecordingWriter(path) as writer:
        writer.write("/rec/initial_mesh", MeshState(S, "world", 0, vertices, [[0, 1, 2, 3]],
                                                    [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], [0]))
        for k, stamp in enumerate(STAMPS_NS):
            writer.write("/rec/tool_pose", PoseRecord(stamp, "world", [0.01 * k, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]))
            writer.write("/rec/points", PointCloudRecord(stamp, "world", np.full((3, 3), float(k))))
    return path


@pytest.fixture(scope="module")
def context():
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.mark.parametrize("rate", [1.0, 2.0, 0.5])
def test_messages_are_due_at_their_recorded_offsets_over_the_rate(context, recording, monkeypatch, rate):
    clock = VirtualClock()
    monkeypatch.setattr(bag_player, "time", clock)
    with RecordingReader(recording) as reader:
        player = BagPlayer(reader)
        published, clock_stamps = [], []
        player._publish = lambda message: published.append((clock.now, message.topic, message.log_time_ns))
        player._publish_clock = lambda stamp_ns: clock_stamps.append((clock.now, stamp_ns))
        player.rate, player.wait_for_subscribers, player.delay = rate, 0.0, 0.0
        try:
            player.play()
        finally:
            player.destroy_node()
    assert published[0] == (0.0, "/rec/initial_mesh", S)  # the latched topic first, at once
    streamed = published[1:]
    assert sorted((stamp, topic) for _, topic, stamp in streamed) == sorted(
        (stamp, topic) for stamp in STAMPS_NS for topic in ("/rec/points", "/rec/tool_pose"))
    # Each message is published when (its stamp - the first stamp) / rate has passed, not before.
    for at, _, stamp in streamed:
        assert at == pytest.approx((stamp - STAMPS_NS[0]) / 1e9 / rate, abs=1e-9)
    # /clock: monotonic, never more than 1 / clock_frequency apart while playing, and reading
    # the first stamp plus rate times the time played.
    times = [at for at, _ in clock_stamps]
    stamps = [stamp for _, stamp in clock_stamps]
    assert stamps == sorted(stamps) and stamps[-1] == STAMPS_NS[-1]
    assert max(np.diff(times)) <= 1.0 / player.clock_frequency + 1e-12
    assert len(clock_stamps) > (STAMPS_NS[-1] - STAMPS_NS[0]) / 1e9 / rate * player.clock_frequency
    for at, stamp in clock_stamps[1:]:
        assert stamp == pytest.approx(STAMPS_NS[0] + at * rate * 1e9, abs=1.0)


class FakeGraph:
    """Who subscribes to which topic, as the player's node would see it on the ROS graph."""

    def __init__(self, clock: VirtualClock, subscribed: dict[str, float | tuple[float, ...]]) -> None:
        # topic -> virtual time its subscriber appears, or the times of each of its subscribers
        self.clock = clock
        self.subscribed = {topic: np.atleast_1d(times) for topic, times in subscribed.items()}

    def count(self, topic: str) -> int:
        return int(np.count_nonzero(self.subscribed.get(topic, np.zeros(0)) <= self.clock.now))


def wait_with(recording, monkeypatch, subscribed: dict[str, float | tuple[float, ...]], wait_s: float = 60.0,
              topics: list[str] | None = None, subscribers: int = 1) -> float:
    """The virtual time the player's wait for subscribers takes."""
    clock = VirtualClock()
    monkeypatch.setattr(bag_player, "time", clock)
    graph = FakeGraph(clock, subscribed)
    with RecordingReader(recording) as reader:
        player = BagPlayer(reader, topics)
        player.wait_for_subscribers, player.subscribers = wait_s, subscribers
        monkeypatch.setattr(player, "count_subscribers", graph.count)
        for name, publisher in player._topic_publishers.items():
            monkeypatch.setattr(publisher, "get_subscription_count", lambda name=name: graph.count(name))
        player._wait_for_subscribers()
        player.destroy_node()
    return clock.now


def within_a_poll(waited: float, expected: float) -> bool:
    """The player stops waiting at `expected` (never before: its loop checks time >= it) or at the
    poll after, on the virtual clock."""
    return expected <= waited <= expected + 2 * bag_player._POLL_S


def test_the_player_waits_only_for_topics_that_nodes_subscribe_to(context, recording, monkeypatch):
    settle = bag_player._SETTLE_S
    # one topic subscribed from the start, nobody on the others: it plays once the graph settled
    assert within_a_poll(wait_with(recording, monkeypatch, {"/rec/points": 0.0}), settle)
    # a second node appears later: the player waits for it, then settles again
    assert within_a_poll(wait_with(recording, monkeypatch, {"/rec/points": 0.0, "/rec/tool_pose": 0.3}),
                         0.3 + settle)
    # nobody at all: it waits the whole wait_for_subscribers, and no longer
    assert within_a_poll(wait_with(recording, monkeypatch, {}, wait_s=5.0), 5.0)
    # topics the user names are all waited for, subscribed or not yet
    named = ["/rec/points", "/rec/tool_pose"]
    assert within_a_poll(wait_with(recording, monkeypatch, {"/rec/points": 0.0}, wait_s=5.0, topics=named), 5.0)
    assert within_a_poll(wait_with(recording, monkeypatch, {"/rec/points": 0.0, "/rec/tool_pose": 2.0},
                                   topics=named), 2.0 + settle)


def test_the_player_waits_for_the_number_of_subscribers_it_is_told(context, recording, monkeypatch):
    """With subscribers=2 a topic one node has matched is not ready: the player waits for the
    second node (1.5 s late here), where with the default it would have started without it."""
    settle = bag_player._SETTLE_S
    named = ["/rec/points", "/rec/tool_pose"]
    two_each = {"/rec/points": (0.0, 1.5), "/rec/tool_pose": (0.0, 0.2)}
    assert within_a_poll(wait_with(recording, monkeypatch, two_each, topics=named), settle)
    assert within_a_poll(wait_with(recording, monkeypatch, two_each, topics=named, subscribers=2), 1.5 + settle)
