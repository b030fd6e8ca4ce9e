"""Orientations read from messages (uav_vs.ros.convert): normalised, or refused when they
are no rotation; and the relay forwarding vision poses on the same rules.

Truth: the yaw a quaternion is built from (q = (0, 0, sin(yaw/2), cos(yaw/2))), which
any positive multiple of q shares; a zero or non-finite quaternion names no rotation.
"""
import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import Header

from conftest import wait_for
from test_mavlink_relay_node import BareAutopilot, Probe, forward_vision, start_relay
from uav_vs.ros import convert as cv
from uav_vs.ros.convert import MessageError, ns_to_stamp, pose_to_msg


def about_z(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def odometry(q) -> Odometry:
    msg = Odometry(child_frame_id='base_link')
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    return msg


@pytest.mark.parametrize('scale', [1.0, 2.0, 0.5, 9.0, 0.2])
@pytest.mark.parametrize('yaw', [math.radians(30), math.radians(-120), math.radians(179)])
def test_a_scaled_quaternion_is_normalised_and_keeps_its_yaw(yaw, scale):
    q = scale * about_z(yaw)
    _, unit = cv.msg_to_pose(pose_to_msg([1.0, 2.0, 3.0], q, Header()))
    np.testing.assert_allclose(unit, about_z(yaw), atol=1e-15)
    assert cv.yaw_of(q) == pytest.approx(yaw, abs=1e-12)
    assert cv.yaw_of(unit) == pytest.approx(yaw, abs=1e-12)
    _, odom_q, _, _ = cv.msg_to_odometry(odometry(q))
    np.testing.assert_allclose(odom_q, about_z(yaw), atol=1e-15)


def test_a_hand_written_quaternion_is_read_as_its_rotation():
    _, q = cv.msg_to_pose(pose_to_msg([0.0, 0.0, 0.0], [0.0, 0.0, 0.707, 0.707], Header()))
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    assert cv.yaw_of(q) == pytest.approx(math.pi / 2, abs=1e-12)


def test_a_unit_quaternion_comes_back_unchanged():
    q = np.array([0.1, -0.2, 0.3, math.sqrt(1 - 0.14)])
    assert np.array_equal(cv.msg_to_pose(pose_to_msg([0.0, 0.0, 0.0], q, Header()))[1], q)


@pytest.mark.parametrize('q', [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, math.nan, 1.0),
                               (math.inf, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.09),
                               (0.0, 0.0, 8.0, 8.0), (1e200, 0.0, 0.0, 0.0)])
def test_a_quaternion_that_is_no_rotation_raises(q):
    msg = pose_to_msg([0.0, 0.0, 0.0], q, Header())
    with pytest.raises(MessageError, match='is no rotation'):
        cv.msg_to_pose(msg)
    with pytest.raises(MessageError, match='is no rotation'):
        cv.yaw_of(q)
    with pytest.raises(MessageError, match='is no rotation'):
        cv.msg_to_odometry(odometry(q))


def test_relay_forwards_a_scaled_quaternion_as_its_rotation_and_skips_a_zero_one(
        ros_node, processes):
    # Nose north (ENU yaw +90 deg) is NED yaw 0, at twice unit length as at unit length;
    # the zero quaternion is counted as malformed and never forwarded (it would read yaw 0
    # too: the x that tells them apart is 5 against 1).
    autopilot = BareAutopilot()
    try:
        start_relay(processes, f'udpout:127.0.0.1:{autopilot.port}',
                    'vision_pose_topic:=ground/pose')
        probe = Probe(ros_node)
        pub = ros_node.create_publisher(PoseStamped, '/ground/pose', 10)
        probe.wait_diag(link='connected')
        assert wait_for(lambda: pub.get_subscription_count() > 0, 20)
        header = Header(stamp=ns_to_stamp(1_700_000_000_250_000_000), frame_id='world')
        scaled = pose_to_msg([2.0, 1.0, 3.0], 2.0 * about_z(math.pi / 2), header)
        zero = pose_to_msg([2.0, 5.0, 3.0], [0.0, 0.0, 0.0, 0.0], header)

        forwarded = forward_vision(pub, autopilot, scaled, zero)
        diag = probe.wait_diag(vision=str(len(forwarded)))
        assert int(diag['malformed']) >= 1
        for v in forwarded:
            assert (v.x, v.y) == (1.0, 2.0)
            assert abs(v.yaw) < 1e-6 and abs(v.roll) < 1e-6 and abs(v.pitch) < 1e-6
        assert 'is no rotation' in processes.log('relay')
    finally:
        autopilot.close()
