"""frames_node and the TF tree it publishes (REP-105).

Truth: where config/ground_trinocular.yaml says each camera stands and looks (cam1 at
(6.2, 0.8, 3.6) m looking at (0, 0, 1.1) m, no roll, ...); OpenCV's projection of
world points carried into the camera frame by the published transform (read with
scipy's Rotation), which must land on the pixels uav_vs.vision.camera projects them
to; the onboard mounting docs/onboard.md describes (looking straight down, image top towards
the vehicle's front); and the poses the test itself publishes.
"""
import dataclasses
import subprocess
import time

import cv2
import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovariance
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from conftest import REPO, wait_for
from uav_vs.graph import executable
from uav_vs.ros.convert import (MessageError, msg_to_transform, ns_to_stamp, pose_to_msg,
                                transform_to_msg)
from uav_vs.vision.camera import Camera
from uav_vs.vision.frame_tree import camera_transform, frame_name_problem, mounting_transform
from uav_vs.vision.ground_config import load_ground_config, read_params_file
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import camera_pose

GROUND = REPO / 'config' / 'ground_trinocular.yaml'
ONBOARD = REPO / 'config' / 'onboard.yaml'
FRAMES = REPO / 'config' / 'frames.yaml'
NODE = '/frames_node'
# Where the comments of config/ground_trinocular.yaml put each camera; all look at AIM.
MASTS = {'cam1': (6.2, 0.8, 3.6), 'cam2': (-3.6, 5.6, 3.9), 'cam3': (-3.0, -5.9, 3.8)}
AIM = np.array([0.0, 0.0, 1.1])
RNG = np.random.default_rng(105)


def ground_cameras() -> list[Camera]:
    return load_ground_config(read_params_file(GROUND)).cameras


def into_child(translation, quaternion, points: np.ndarray) -> np.ndarray:
    """World points in the child frame of a transform world -> child (x_w = R x_c + t)."""
    return Rotation.from_quat(quaternion).inv().apply(np.asarray(points) - translation)


def assert_projects_as_the_camera(camera: Camera, translation, quaternion) -> None:
    """Points of the flight volume carried into the camera by the transform and projected
    by K (and D) land where the camera model projects them."""
    world = RNG.uniform([-2.0, -2.0, 0.0], [2.0, 2.0, 2.5], (200, 3))
    in_camera = into_child(translation, quaternion, world)
    assert (in_camera[:, 2] > 0).all()
    pinhole = in_camera @ camera.K.T
    pinhole = pinhole[:, :2] / pinhole[:, 2:]
    undistorted = dataclasses.replace(camera, D=np.zeros(5))
    np.testing.assert_allclose(pinhole, undistorted.project(world), atol=1e-6)
    distorted, _ = cv2.projectPoints(in_camera, np.zeros(3), np.zeros(3), camera.K, camera.D)
    np.testing.assert_allclose(distorted.reshape(-1, 2), camera.project(world), atol=1e-6)


def assert_is_the_mast(name: str, translation, quaternion) -> None:
    """At the mast, optical axis (z) at AIM, image x horizontal (no roll), image y down."""
    np.testing.assert_allclose(translation, MASTS[name], atol=1e-6)
    x, y, z = Rotation.from_quat(quaternion).as_matrix().T
    np.testing.assert_allclose(z, (AIM - MASTS[name]) / np.linalg.norm(AIM - MASTS[name]),
                               atol=1e-6)
    assert abs(x[2]) < 1e-6 and y[2] < 0


@pytest.mark.parametrize('index', range(3))
def test_camera_frame_is_the_calibrated_camera(index):
    camera = ground_cameras()[index]
    t = camera_transform('world', camera)
    assert (t.parent, t.child) == ('world', f'{camera.name}_optical')
    assert_is_the_mast(camera.name, t.translation, t.quaternion)
    assert_projects_as_the_camera(camera, t.translation, t.quaternion)


def test_onboard_camera_looks_down_with_the_image_top_forward():
    cfg = load_onboard_config(read_params_file(ONBOARD))
    t = mounting_transform('base_link', 'onboard_camera_optical', cfg.camera_to_body)
    np.testing.assert_allclose(t.translation, [0.0, 0.0, -0.05])
    x, y, z = Rotation.from_quat(t.quaternion).as_matrix().T
    np.testing.assert_allclose(z, [0, 0, -1], atol=1e-12)     # optical axis: down
    np.testing.assert_allclose(-y, [1, 0, 0], atol=1e-12)     # image top: forward
    np.testing.assert_allclose(x, [0, -1, 0], atol=1e-12)     # image right: the right side


def test_chained_vehicle_and_mounting_transforms_project_as_the_estimator():
    """world -> base_link -> onboard_camera_optical, chained, is the camera the plane
    pose estimator projects the ground with (plane_pose.camera_pose)."""
    cfg = load_onboard_config(read_params_file(ONBOARD))
    mount = mounting_transform('base_link', 'onboard_camera_optical', cfg.camera_to_body)
    R_wb = Rotation.from_euler('xyz', [0.05, -0.08, 1.2])
    p_wb = np.array([0.4, -0.3, 1.5])
    R, t = camera_pose(R_wb.as_matrix(), p_wb, cfg.camera_to_body)
    camera = dataclasses.replace(cfg.camera, R=R, t=t)
    ground = np.column_stack([RNG.uniform(-0.5, 0.5, (100, 2)) + p_wb[:2], np.zeros(100)])
    in_body = into_child(p_wb, R_wb.as_quat(), ground)
    in_camera = into_child(mount.translation, mount.quaternion, in_body)
    px, _ = cv2.projectPoints(in_camera, np.zeros(3), np.zeros(3), camera.K, camera.D)
    np.testing.assert_allclose(px.reshape(-1, 2), camera.project(ground), atol=1e-6)


def test_transform_message_round_trip_and_no_rotation():
    q = Rotation.from_euler('xyz', [0.3, -0.2, 2.0]).as_quat()
    msg = transform_to_msg([1.0, -2.0, 0.5], q, Header(stamp=ns_to_stamp(7_000_000_005),
                                                       frame_id='world'), 'cam1_optical')
    assert (msg.header.frame_id, msg.child_frame_id) == ('world', 'cam1_optical')
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (7, 5)
    translation, quaternion = msg_to_transform(msg)
    np.testing.assert_array_equal(translation, [1.0, -2.0, 0.5])
    np.testing.assert_allclose(quaternion, q, atol=1e-15)
    msg.transform.rotation.w = msg.transform.rotation.x = 0.0
    msg.transform.rotation.y = msg.transform.rotation.z = 0.0
    with pytest.raises(MessageError, match='is no rotation'):
        msg_to_transform(msg)


@pytest.mark.parametrize('frames, problem', [
    ({'a': 'world', 'b': 'base_link'}, None),
    ({'a': 'world', 'b': 'world'}, "b: 'world' is also a"),
    ({'a': ''}, "a: '' is no frame name"),
    ({'a': '/world'}, "a: '/world' is no frame name"),
    ({'a': 'base link'}, "a: 'base link' is no frame name"),
])
def test_frame_names_that_cannot_make_a_tree_are_named(frames, problem):
    found = frame_name_problem(frames)
    assert found == problem if problem is None else found.startswith(problem)


# ------------------------------------------------------------- the node as a process

class Probe:
    def __init__(self, node):
        self.node = node
        self.tf: list = []
        self.diag: dict[str, str] = {}
        self.messages: list[str] = []     # every diagnostics message of the node
        node.create_subscription(TFMessage, '/tf', lambda m: self.tf.extend(m.transforms),
                                 100)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)
        self.pubs = {'ground': node.create_publisher(PoseStamped, '/ground/pose', 10),
                     'onboard': node.create_publisher(PoseStamped, '/onboard/pose', 10),
                     'odom': node.create_publisher(Odometry, '/autopilot/odom', 10)}

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == NODE:
                self.diag = {'message': s.message, **{kv.key: kv.value for kv in s.values}}
                self.messages.append(s.message)

    def connected(self) -> bool:
        return (all(p.get_subscription_count() for p in self.pubs.values())
                and self.node.count_publishers('/tf') > 0 and bool(self.diag))

    def publish(self, source: str, position, quaternion, stamp_ns: int, frame='world') -> None:
        header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame)
        pose = pose_to_msg(position, quaternion, header)
        if source == 'odom':
            pose = Odometry(header=header, child_frame_id='base_link', pose=PoseWithCovariance(
                pose=pose.pose))
        self.pubs[source].publish(pose)

    def transforms(self, stamp_ns: int) -> dict:
        """{child: (parent, translation, quaternion)} of the /tf transforms so stamped."""
        return {t.child_frame_id: (t.header.frame_id, *msg_to_transform(t)) for t in self.tf
                if t.header.stamp == ns_to_stamp(stamp_ns)}


def start(processes, *overrides):
    args = [a for f in (FRAMES, GROUND, ONBOARD) for a in ('--params-file', str(f))]
    args += ['-p', 'frames.diagnostics_period:=0.1']
    for kv in overrides:
        args += ['-p', kv]
    return processes('frames_node', args, label='frames')


def test_static_frames_reach_a_late_subscriber(ros_node, processes):
    proc = start(processes)
    probe = Probe(ros_node)
    assert wait_for(lambda: probe.diag, 30), processes.log('frames')   # spinning: sent
    got = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros_node.create_subscription(TFMessage, '/tf_static', got.append, latched)
    assert wait_for(lambda: got, 10), processes.log('frames')
    time.sleep(0.5)
    assert len(got) == 1     # one message with all: a depth-1 latched topic keeps only one
    transforms = {t.child_frame_id: t for t in got[0].transforms}
    assert sorted(transforms) == ['cam1_optical', 'cam2_optical', 'cam3_optical',
                                  'onboard_camera_optical']
    for camera in ground_cameras():
        t = transforms[camera.frame_id]
        assert t.header.frame_id == 'world'
        assert_is_the_mast(camera.name, *msg_to_transform(t))
        assert_projects_as_the_camera(camera, *msg_to_transform(t))
    onboard = transforms['onboard_camera_optical']
    assert onboard.header.frame_id == 'base_link'
    expected = mounting_transform('base_link', 'onboard_camera_optical',
                                  load_onboard_config(read_params_file(ONBOARD)).camera_to_body)
    translation, quaternion = msg_to_transform(onboard)
    np.testing.assert_allclose(translation, expected.translation, atol=1e-12)
    error = Rotation.from_quat(quaternion) * Rotation.from_quat(expected.quaternion).inv()
    assert error.magnitude() <= 1e-12
    assert proc.poll() is None


def test_ros2_topic_echo_shows_the_static_frames(ros_node, processes, ros2_cli):
    """The real `ros2 topic echo /tf_static` (the shared wheels), as a late subscriber."""
    start(processes)
    probe = Probe(ros_node)
    assert wait_for(lambda: probe.diag, 30), processes.log('frames')   # spinning: sent
    echo = ros2_cli('topic', 'echo', '--once', '--no-daemon', '--timeout', '30',
                    '--qos-reliability', 'reliable', '--qos-durability', 'transient_local',
                    '/tf_static', 'tf2_msgs/msg/TFMessage')
    assert echo.returncode == 0, echo.stdout + echo.stderr
    shown = yaml.safe_load(echo.stdout.split('---')[0])['transforms']
    frames = {(t['header']['frame_id'], t['child_frame_id']): t['transform'] for t in shown}
    assert sorted(frames) == [('base_link', 'onboard_camera_optical'), ('world', 'cam1_optical'),
                              ('world', 'cam2_optical'), ('world', 'cam3_optical')]
    for camera in ground_cameras():
        t = frames[('world', camera.frame_id)]
        translation = [t['translation'][k] for k in 'xyz']
        quaternion = [t['rotation'][k] for k in 'xyzw']
        assert_projects_as_the_camera(camera, np.array(translation), np.array(quaternion))


@pytest.mark.parametrize('base_link_source', ['ground', 'odom', 'none'])
def test_each_pose_places_its_frame_with_its_stamp(ros_node, processes, base_link_source):
    start(processes, f'frames.base_link_source:={base_link_source}')
    probe = Probe(ros_node)
    assert wait_for(probe.connected, 30), processes.log('frames')
    yaw = Rotation.from_euler('z', 0.7).as_quat()
    poses = {'ground': ((1.0, 2.0, 1.5), yaw, 1_000_000_001),
             'onboard': ((1.1, 2.1, 1.4), Rotation.from_euler('xyz', [0.1, 0, 0.7]).as_quat(),
                         1_000_000_002),
             'odom': ((0.9, 1.9, 1.6), yaw, 1_000_000_003)}
    for source, (position, quaternion, stamp) in poses.items():
        probe.publish(source, position, quaternion, stamp)
    children = {'ground': 'base_link_ground', 'onboard': 'base_link_onboard',
                'odom': 'base_link_odom'}
    expected_count = 3 + (base_link_source != 'none')
    assert wait_for(lambda: len(probe.tf) >= expected_count, 10), processes.log('frames')
    time.sleep(0.3)
    assert len(probe.tf) == expected_count
    for source, (position, quaternion, stamp) in poses.items():
        got = probe.transforms(stamp)
        expected = {children[source]}
        if source == base_link_source:
            expected.add('base_link')
        assert set(got) == expected
        for parent, translation, q in got.values():
            assert parent == 'world'
            np.testing.assert_allclose(translation, position)
            np.testing.assert_allclose(q, quaternion, atol=1e-12)


def test_malformed_poses_are_counted_and_skipped(ros_node, processes):
    proc = start(processes)
    probe = Probe(ros_node)
    assert wait_for(probe.connected, 30), processes.log('frames')
    unit = (0.0, 0.0, 0.0, 1.0)
    probe.publish('ground', (1.0, 2.0, 1.0), (0.0, 0.0, 0.0, 0.0), 11)           # no rotation
    probe.publish('onboard', (float('nan'), 2.0, 1.0), unit, 12)                 # NaN position
    probe.publish('ground', (1.0, 2.0, 1.0), unit, 13, frame='map')              # wrong frame
    probe.publish('odom', (1.0, 2.0, 1.0), (0.0, 0.0, float('inf'), 1.0), 14)    # no rotation
    probe.publish('ground', (3.0, 4.0, 1.0), (0.0, 0.0, 0.0, 2.0), 15)           # normalised
    assert wait_for(lambda: probe.transforms(15), 10), processes.log('frames')
    assert wait_for(lambda: probe.diag.get('malformed') == '4', 5), probe.diag
    assert {t.header.stamp.nanosec for t in probe.tf} == {15}
    got = probe.transforms(15)
    assert set(got) == {'base_link_ground', 'base_link'}
    np.testing.assert_allclose(got['base_link'][1], (3.0, 4.0, 1.0))
    np.testing.assert_allclose(got['base_link'][2], unit)
    assert probe.diag['ground'] == '1'
    assert any('malformed poses skipped' in m for m in probe.messages), probe.messages
    log = processes.log('frames')
    assert 'is no rotation' in log and 'non-finite position' in log and "frame 'map'" in log
    assert proc.poll() is None


def test_a_source_that_stops_is_reported_silent_until_it_comes_back(ros_node, processes):
    """Only a source that has placed its frame can go silent; one never heard is not."""
    start(processes, 'frames.silence_timeout:=2.0')
    probe = Probe(ros_node)
    assert wait_for(probe.connected, 30), processes.log('frames')
    assert probe.diag['silent'] == ''
    unit = (0.0, 0.0, 0.0, 1.0)
    probe.publish('odom', (1.0, 2.0, 1.0), unit, 21)
    assert wait_for(lambda: probe.transforms(21), 10), processes.log('frames')
    assert wait_for(lambda: probe.diag.get('silent') == 'odom', 10), probe.diag
    assert 'silent: odom for' in probe.diag['message']
    probe.publish('odom', (1.0, 2.0, 1.0), unit, 22)
    assert wait_for(lambda: probe.transforms(22) and probe.diag.get('silent') == '', 10), \
        probe.diag


@pytest.mark.parametrize('overrides, files, expected', [
    (['frames.onboard.child_frame:=base_link_ground'], (FRAMES, GROUND, ONBOARD),
     "frames.onboard.child_frame: 'base_link_ground' is also frames.ground.child_frame"),
    (['cameras.cam2.frame_id:=base_link'], (FRAMES, GROUND, ONBOARD),
     "cameras.cam2.frame_id: 'base_link' is also frames.base_link_frame"),
    (['frames.sources:=[ground]', 'frames.base_link_source:=odom'], (FRAMES, GROUND),
     "frames.base_link_source: 'odom' is not in frames.sources"),
    (['frames.world_frame:=/world'], (FRAMES, GROUND), "frames.world_frame: '/world'"),
    ([], (FRAMES,), 'cameras.names: missing'),
])
def test_a_configuration_that_makes_no_tree_stops_with_one_line(overrides, files, expected):
    cmd = [executable('frames_node'), '--ros-args',
           *[a for f in files for a in ('--params-file', str(f))],
           *[a for kv in overrides for a in ('-p', kv)]]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    output = run.stdout + run.stderr
    fatal = [line for line in output.splitlines() if 'FATAL' in line]
    assert run.returncode == 2, output
    assert len(fatal) == 1 and expected in fatal[0], output
    assert 'Traceback' not in output
