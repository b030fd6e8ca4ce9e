"""Publish recorded (raw CDR) messages with real rclpy publishers of the recorded type,
and convert QoS between rclpy and bag metadata."""
import importlib
import time
from typing import Callable, Sequence

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)

from uav_vs.bag.reader import BagMessage, QosOffer


def message_class(msgtype: str) -> type:
    """'sensor_msgs/msg/Image' -> sensor_msgs.msg.Image."""
    package, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def lossless_qos(offer: QosOffer, force_reliable: bool = False) -> QoSProfile:
    """KEEP_ALL with the offer's reliability (RELIABLE if forced) and durability."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        reliability=(ReliabilityPolicy.RELIABLE if offer.reliable or force_reliable
                     else ReliabilityPolicy.BEST_EFFORT),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if offer.transient_local
                    else DurabilityPolicy.VOLATILE))


def bag_qos(profile: QoSProfile) -> Qos:
    """An rclpy QoS profile as bag metadata records it (same enum values as rmw)."""
    def time(d: Duration) -> QosTime:
        return QosTime(*divmod(d.nanoseconds, 10**9))

    return Qos(QosHistory(int(profile.history)), profile.depth,
               QosReliability(int(profile.reliability)), QosDurability(int(profile.durability)),
               time(profile.deadline), time(profile.lifespan),
               QosLiveliness(int(profile.liveliness)), time(profile.liveliness_lease_duration),
               profile.avoid_ros_namespace_conventions)


class RawPublishers:
    """One lossless (reliable, keep-all) publisher per topic, created on first use."""

    QOS = lossless_qos(QosOffer())

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

    def play(self, messages: Sequence[BagMessage], rate: float,
             after_each: Callable[[], None] | None = None) -> int:
        """Publish `messages` at their recorded times scaled by 1 / rate (0: at once),
        calling `after_each` after every one; return the wall time (ns) of the first."""
        t0_bag, t0, start = messages[0].t_ns, time.monotonic(), time.time_ns()
        for m in messages:
            if rate > 0:
                delay = (m.t_ns - t0_bag) * 1e-9 / rate - (time.monotonic() - t0)
                if delay > 0:
                    time.sleep(delay)
            self.publish(m.topic, m.msgtype, m.raw)
            if after_each is not None:
                after_each()
        return start

    def wait_for_all_acked(self, timeout_s: float) -> bool:
        return all(p.wait_for_all_acked(Duration(seconds=timeout_s)) for p in self._pubs.values())
