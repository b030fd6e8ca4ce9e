"""Message <-> numpy conversions on the per-message path (uav_vs.ros.convert).

Each case is the conversion a node makes per message, with every check it applies,
next to the bare library call that does the same work without them: rclpy's own
deserialization for raw images, cv2.imdecode for compressed ones, plain attribute
reads for a pose. The image is a 640x480 crop of a real aerial photo (the simulator's
ground texture).
"""
from pathlib import Path

import cv2
import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from bench.common import report, timeit
from uav_vs.ros.convert import (bgr_to_compressed, bgr_to_image, compressed_to_bgr,
                                image_from_cdr, image_to_bgr, msg_to_pose, pose_to_msg, yaw_of)

SIZE = (640, 480)
PHOTO = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets' / 'aero1.jpg'


def frame() -> np.ndarray:
    img = cv2.imread(str(PHOTO), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(img[:SIZE[1], :SIZE[0]])


def raw_image() -> None:
    header = Header(frame_id='cam1_optical')
    header.stamp.sec = 1
    data = serialize_message(bgr_to_image(frame(), header))

    def ours():
        return image_to_bgr(image_from_cdr(data), SIZE)

    def rclpy_way():
        msg = deserialize_message(data, Image)
        return np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width, 3)

    assert np.array_equal(ours(), rclpy_way())
    report('convert', 'convert/image_raw_bgr8_640x480', timeit(ours, 2000),
           reference='rclpy deserialize + frombuffer', ref_ms=timeit(rclpy_way, 500))


def compressed_image() -> None:
    msg = bgr_to_compressed(frame(), Header(frame_id='cam1_optical'))
    buffer = np.frombuffer(msg.data, np.uint8)

    def ours():
        return compressed_to_bgr(msg, SIZE)

    def opencv():
        return cv2.imdecode(buffer, cv2.IMREAD_COLOR)

    assert np.array_equal(ours(), opencv())
    report('convert', 'convert/image_jpeg_640x480', timeit(ours, 300),
           reference='cv2.imdecode', ref_ms=timeit(opencv, 300))


def pose() -> None:
    q = np.array([0.0, 0.0, np.sin(0.6), np.cos(0.6)])
    msg = pose_to_msg(np.array([1.0, -2.0, 1.5]), q, Header(frame_id='world'))

    def ours():
        position, quaternion = msg_to_pose(msg)
        return position, yaw_of(quaternion)

    def attributes():
        p, o = msg.pose.position, msg.pose.orientation
        return np.array([p.x, p.y, p.z]), np.arctan2(2 * o.w * o.z, 1 - 2 * o.z * o.z)

    assert abs(ours()[1] - attributes()[1]) < 1e-12
    report('convert', 'convert/pose_to_numpy_and_yaw', timeit(ours, 20000),
           reference='attribute reads + atan2', ref_ms=timeit(attributes, 20000))


def main() -> None:
    raw_image()
    compressed_image()
    pose()


if __name__ == '__main__':
    main()
