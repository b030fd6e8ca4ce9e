"""A camera input for vision nodes: raw and compressed images in, numpy frames out.

`ImageInput` subscribes `<topic>` (sensor_msgs/Image) and `<topic>/compressed`
(sensor_msgs/CompressedImage) and hands each new frame to the node as an 8-bit grey
(or, with `colour=True`, BGR) array with its header. A camera driver may publish both topics: a frame whose stamp
is not newer than the last one handed over is skipped before decoding (`stale`), so
each frame is decoded and processed once and never out of order. A frame that cannot
be converted (encoding, size, undecodable) is counted (`malformed`), logged once per
kind of defect every 5 s, and skipped. Raw images are taken serialized and read in
place (`image_from_cdr`), so a bgr8 (colour) or mono8 (grey) frame is a read-only view
of the message, not a copy.
"""
from typing import Callable

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from uav_vs.ros.convert import (MessageError, RawImage, compressed_to_bgr, compressed_to_gray,
                                image_from_cdr, image_to_bgr, image_to_gray, stamp_to_ns)
from uav_vs.ros.node_main import ThrottledWarnings

QOS_CHOICES = ('sensor_data', 'reliable')


def image_qos(name: str) -> QoSProfile:
    """sensor_data: best effort, keep last 5 (live cameras); reliable: keep last 10 (bags)."""
    if name == 'sensor_data':
        return qos_profile_sensor_data
    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


class ImageInput:
    def __init__(self, node: Node, topic: str, qos: str,
                 callback: Callable[[np.ndarray, Header], None],
                 expected_size: tuple[int, int] | None = None, warn_period_s: float = 5.0,
                 colour: bool = False) -> None:
        self._node, self._callback, self._size = node, callback, expected_size
        self._warnings = ThrottledWarnings(node, warn_period_s)
        self._last_stamp = -1
        self.counts = dict(malformed=0, stale=0)
        profile = image_qos(qos)
        raw, compressed = ((image_to_bgr, compressed_to_bgr) if colour
                           else (image_to_gray, compressed_to_gray))
        node.create_subscription(Image, topic, lambda b: self._on_serialized(b, raw), profile,
                                 raw=True)
        node.create_subscription(CompressedImage, topic + '/compressed',
                                 lambda m: self._on(m, compressed), profile)

    def _on_serialized(self, data: bytes, convert) -> None:
        try:
            msg = image_from_cdr(data)
        except MessageError as err:
            self._malformed(err)
            return
        self._on(msg, convert)

    def _on(self, msg: Image | RawImage | CompressedImage, convert) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp <= self._last_stamp:
            self.counts['stale'] += 1
            return
        try:
            frame = convert(msg, self._size)
        except MessageError as err:
            self._malformed(err)
            return
        self._last_stamp = stamp
        self._callback(frame, msg.header)

    def _malformed(self, err: MessageError) -> None:
        self.counts['malformed'] += 1
        # One warning per kind of defect: the first words of the message name it.
        self._warnings.warn(' '.join(str(err).split()[:2]), f'{err}; skipped')
