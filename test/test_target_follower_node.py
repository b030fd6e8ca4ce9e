"""target_follower_node: tracker polygons and vehicle poses in, setpoints out (section 5).

The polygons are the projections of a known ground target through the onboard camera
of config/onboard.yaml, so every output has an analytic answer; malformed input is
counted and skipped, a bad parameter stops the node with one line."""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point32, PolygonStamped, PoseStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header

from conftest import REPO, refused_at_start, wait_for
from uav_vs.ros.convert import (msg_to_pose, ns_to_stamp, odometry_to_msg, points_to_polygon,
                                pose_to_msg, yaw_of)
from uav_vs.sim.ground_scene import rot_z
from uav_vs.vision.body_pose import quaternion_xyzw
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import camera_pose

CONFIG = REPO / 'config' / 'onboard.yaml'
RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
CFG = load_onboard_config(read_params_file(CONFIG))


def target_polygon(R_wb, p_wb, centre, heading, size=(0.4, 0.28)) -> np.ndarray:
    """Corners TL TR BR BL (the top edge at the front) and centre of a ground rectangle,
    projected into the raw image of the onboard camera."""
    f, l = np.array([math.cos(heading), math.sin(heading)]), np.array([-math.sin(heading),
                                                                     math.cos(heading)])
    half_w, half_l = size[0] / 2, size[1] / 2
    ground = [centre + half_l * f + half_w * l, centre + half_l * f - half_w * l,
              centre - half_l * f - half_w * l, centre - half_l * f + half_w * l, centre]
    R, t = camera_pose(R_wb, p_wb, CFG.camera_to_body)
    points = np.column_stack([np.array(ground), np.zeros(5)])
    px, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, CFG.camera.K, CFG.camera.D)
    return px.reshape(-1, 2)


def stamped(k: int, frame_id: str) -> Header:
    return Header(stamp=ns_to_stamp(1_000_000_000 + k * 100_000_000), frame_id=frame_id)


def tilted(yaw: float, roll: float, pitch: float) -> np.ndarray:
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    return rot_z(yaw) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ \
        np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])


def test_follows_a_target_and_skips_malformed_input(ros_node, processes):
    """The vehicle is tilted by 8 and 5 degrees; its vision pose is level (as the
    trinocular station's is), the autopilot's attitude has the tilt and a yaw 0.3 rad
    off: the target is placed from the pose's position and yaw and the autopilot's tilt."""
    processes('target_follower_node', ['--params-file', str(CONFIG), '-p', 'follow.lead:=0.0',
                                       '-p', 'follow.height:=1.7', '-p', 'follow.yaw:=0.3',
                                       '-p', 'follow.diagnostics_period:=0.1'],
              label='follower')
    setpoints: list[PoseStamped] = []
    targets: list[PoseStamped] = []
    diagnostics: list[dict] = []
    ros_node.create_subscription(PoseStamped, '/setpoint', setpoints.append, RELIABLE)
    ros_node.create_subscription(PoseStamped, '/target/pose', targets.append, RELIABLE)
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diagnostics.extend(
        {'message': s.message, **{kv.key: kv.value for kv in s.values}} for s in m.status
        if s.name == '/target_follower_node'), RELIABLE)
    pose_pub = ros_node.create_publisher(PoseStamped, '/ground/pose', RELIABLE)
    odom_pub = ros_node.create_publisher(Odometry, '/autopilot/odom', RELIABLE)
    target_pub = ros_node.create_publisher(PolygonStamped, '/onboard/target', RELIABLE)
    assert wait_for(lambda: pose_pub.get_subscription_count() > 0
                    and odom_pub.get_subscription_count() > 0
                    and target_pub.get_subscription_count() > 0, 30)

    R_wb, p_wb = tilted(1.2, math.radians(8), math.radians(-5)), np.array([0.5, -0.3, 1.4])
    R_level, R_autopilot = rot_z(1.2), tilted(1.5, math.radians(8), math.radians(-5))
    centre, heading = np.array([0.65, -0.2]), 2.5
    # Malformed: a pose in another frame, a polygon of three points, a NaN corner.
    pose_pub.publish(pose_to_msg(p_wb, quaternion_xyzw(R_level), stamped(0, 'map')))
    bad = PolygonStamped(header=stamped(0, 'onboard_camera_optical'))
    bad.polygon.points = [Point32(x=1.0, y=2.0) for _ in range(3)]
    target_pub.publish(bad)
    nan = target_polygon(R_wb, p_wb, centre, heading)
    nan[2, 0] = np.nan
    target_pub.publish(points_to_polygon(nan, stamped(0, 'onboard_camera_optical')))
    for k in (1, 2):
        pose_pub.publish(pose_to_msg(p_wb, quaternion_xyzw(R_level), stamped(k, 'world')))
        odom_pub.publish(odometry_to_msg(p_wb, quaternion_xyzw(R_autopilot), np.zeros(3),
                                         np.zeros(3), stamped(k, 'world'), 'base_link'))
        assert wait_for(lambda: diagnostics and diagnostics[-1]['poses'] == str(k)
                        and diagnostics[-1]['attitudes'] == str(k), 10), diagnostics[-1:]
        target_pub.publish(points_to_polygon(target_polygon(R_wb, p_wb, centre, heading),
                                             stamped(k, 'onboard_camera_optical')))
    assert wait_for(lambda: len(setpoints) == 2 and len(targets) == 2, 10), diagnostics[-1:]
    assert wait_for(lambda: diagnostics and diagnostics[-1]['malformed'] == '3', 10), \
        diagnostics[-1:]
    for setpoint, target, k in zip(setpoints, targets, (1, 2)):
        assert setpoint.header == stamped(k, 'world') and target.header == stamped(k, 'world')
        position, q = msg_to_pose(setpoint)
        assert np.allclose(position, [*centre, 1.7], atol=1e-6) and yaw_of(q) == \
            pytest.approx(0.3)
        position, q = msg_to_pose(target)
        assert np.allclose(position, [*centre, 0.0], atol=1e-6)
        assert yaw_of(q) == pytest.approx(heading, abs=1e-6)
    assert wait_for(lambda: diagnostics[-1]['setpoints'] == '2', 10), diagnostics[-1]

    # Images with no vehicle pose near their stamps (the last is 0.6 s older): the first
    # waits for its pose, then, an image 0.6 s newer having come, is not placed, and the
    # diagnostics and the log say why; nothing is published for it.
    seen = target_polygon(R_wb, p_wb, centre, heading)
    target_pub.publish(points_to_polygon(seen, stamped(8, 'onboard_camera_optical')))
    assert wait_for(lambda: diagnostics[-1]['waiting'] == '1', 10), diagnostics[-1]
    assert diagnostics[-1]['waiting_for'] == \
        "waiting for the vehicle pose and attitude at the image's stamp"
    target_pub.publish(points_to_polygon(seen, stamped(14, 'onboard_camera_optical')))
    why = 'target not placed: vehicle pose: none within 0.1 s of the image'
    assert wait_for(lambda: diagnostics[-1]['not_placed'] == '1'
                    and diagnostics[-1]['message'] == why, 10), diagnostics[-1]
    assert len(setpoints) == 2 and len(targets) == 2
    assert wait_for(lambda: why in processes.log('follower'), 10), processes.log('follower')


def test_a_bad_parameter_stops_the_node_with_one_line(tmp_path: Path):
    fatal = refused_at_start('target_follower_node', ['--params-file', str(CONFIG),
                                                      '-p', 'follow.height:=-1.0'], tmp_path)
    assert 'follow.height' in fatal, fatal


def test_every_follow_parameter_is_in_the_yaml_with_its_default():
    from uav_vs.nodes.target_follower_node import PARAMS

    yaml = {k: v for k, v in read_params_file(CONFIG).items() if k.startswith('follow.')}
    assert yaml == {spec.name: spec.default for spec in PARAMS}
