"""Publish recorded (raw CDR) messages with real rclpy publishers of the recorded type."""
import importlib

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy


def message_class(msgtype: str) -> type:
    """'sensor_msgs/msg/Image' -> sensor_msgs.msg.Image."""
    package, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


class RawPublishers:
    """One lossless (reliable, keep-all) publisher per topic, created on first use."""

    QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)

    def __init__(self, node: Node, remap: dict[str, str] | None = None) -> None:
        self._node = node
        self._remap = remap or {}
        self._pubs: dict[str, Publisher] = {}

    def publisher(self, topic: str, msgtype: str) -> Publisher:
        if topic not in self._pubs:
            self._pubs[topic] = self._node.create_publisher(
                message_class(msgtype), self._remap.get(topic, topic), self.QOS)
        return self._pubs[topic]

    def publish(self, topic: str, msgtype: str, raw: bytes) -> None:
        self.publisher(topic, msgtype).publish(raw)

    def wait_for_all_acked(self, timeout_s: float) -> bool:
        return all(p.wait_for_all_acked(Duration(seconds=timeout_s)) for p in self._pubs.values())
