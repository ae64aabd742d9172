"""Publishers on a node's input topics whose QoS cannot match the node's subscription.

DDS matches a reliable reader only with reliable writers, and a transient-local reader only with
transient-local writers; an unmatched publisher's messages never arrive, and rclpy says so once,
in the log, as "incompatible QoS". `IncompatiblePublishers.find()` inspects the ROS graph
(`get_publishers_info_by_topic`, compared with rclpy's `qos_check_compatible`) and names each
such publisher, what it offers, what the node asks and the fix, for the node's diagnostics.
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.qos import QoSCompatibility, QoSProfile, qos_check_compatible


# The fix for a publisher of the pipeline's own topics (and /tf) that cannot match.
TOPIC_TABLE_FIX = "publish it with the QoS of the README's topic table"


class IncompatiblePublishers:
    """The node's watched subscriptions: topic -> (QoS subscribed with, what to do about a
    publisher that cannot match it)."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._watched: dict[str, tuple[QoSProfile, str]] = {}
        self._logged: set[str] = set()

    def watch(self, topic: str, qos: QoSProfile, fix: str) -> None:
        """Check the publishers of `topic` (as the node resolves it) against `qos`."""
        self._watched[self._node.resolve_topic_name(topic)] = (qos, fix)

    def find(self) -> list[str]:
        """One line per publisher that cannot match its topic's subscription (empty: none); each
        is also logged, once."""
        problems = []
        for topic, (qos, fix) in self._watched.items():
            for info in self._node.get_publishers_info_by_topic(topic):
                if qos_check_compatible(info.qos_profile, qos)[0] != QoSCompatibility.ERROR:
                    continue
                publisher = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                problems.append(f"{topic} from {publisher} never arrives: it publishes {_offer(info.qos_profile)}, "
                                f"this node subscribes {_offer(qos)}: {fix}")
        for problem in problems:
            if problem not in self._logged:
                self._logged.add(problem)
                self._node.get_logger().error(problem)
        return problems


def _offer(qos: QoSProfile) -> str:
    return f"{qos.reliability.name.lower().replace('_', ' ')}, {qos.durability.name.lower().replace('_', '-')}"
