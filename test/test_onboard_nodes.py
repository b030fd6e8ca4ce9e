"""Onboard nodes as separate processes, started from their console scripts with the YAML.

Truth is independent of the code under test: the simulator's exact poses recorded in
the sample bag, frames rendered by the simulator at known poses, and a target pasted
into a scene through a known homography.
"""
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PolygonStamped, PoseStamped, PoseWithCovarianceStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Bool, Header
from visualization_msgs.msg import ImageMarker

from conftest import REPO, wait_for
from uav_vs.graph import executable, stop
from uav_vs.flight.onboard_replay import replay_onboard_bag
from uav_vs.ros.convert import (bgr_to_compressed, bgr_to_image, msg_to_pose, msg_to_pose_cov_in,
                                ns_to_stamp, polygon_to_array, pose_to_msg, stamp_to_ns)
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config

CONFIG = REPO / 'config' / 'onboard.yaml'
BAG = REPO / 'bags' / 'onboard'
RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
# Lossless delivery for the tests (a recorded stream, not a live camera).
POSE_NODE_ARGS = ['--params-file', str(CONFIG), '-p', 'homography_pose.image_qos:=reliable',
                  '-p', 'homography_pose.diagnostics_period:=0.1']


@pytest.fixture(scope='module')
def cfg():
    return load_onboard_config(read_params_file(CONFIG))


# ------------------------------------------------------------------ pose node

def test_sample_bag_through_the_pose_node_meets_accuracy(tmp_path):
    """Nearly every frame gives a pose: position RMSE <= 2 % of the camera height (each
    error over that frame's true height), attitude RMSE <= 1 deg, over the whole bag,
    against the simulator's truth. The recording is replayed at its rate, losslessly
    (reliable image subscription), as a bag should be."""
    report = replay_onboard_bag(BAG, CONFIG, tmp_path,
                                extra_args=['-p', 'homography_pose.image_qos:=reliable'])
    print(report.summary())
    assert report.frames == 151
    assert report.poses >= 0.97 * report.frames
    assert report.relative_rmse <= 0.02
    assert report.attitude_rmse_deg <= 1.0
    assert report.return_codes == [0]


def _params_file(tmp_path: Path, changes: dict) -> Path:
    """config/onboard.yaml with dotted keys changed (None deletes the key)."""
    doc = yaml.safe_load(CONFIG.read_text())
    for key, value in changes.items():
        node = doc['/**']['ros__parameters']
        *parents, leaf = key.split('.')
        for name in parents:
            node = node[name]
        if value is None:
            del node[leaf]
        else:
            node[leaf] = value
    out = tmp_path / 'broken.yaml'
    out.write_text(yaml.safe_dump(doc))
    return out


@pytest.mark.parametrize('changes, expected', [
    ({'camera.K': [500.0, 0.0, 319.5, 0.0, 500.0, 239.5]}, 'camera.K: expected 9 numbers'),
    ({'camera.D': None}, 'camera.D: missing'),
    ({'homography.method': 'ransack'}, 'homography.method: expected a string (one of ransac'),
    ({'init.position': [0.0, 0.0, -1.0]}, 'init.position: the camera must be above'),
    ({'init.mode': 'reference_points', 'init.image_points': [1.0, 2.0, 3.0, 4.0]},
     'init.image_points'),
    ({'klt.win_size': 16}, 'klt.win_size: expected an odd number'),
    ({'init.mode': 'pose_topic', 'init.pose_topic': ''}, 'init.pose_topic: expected a topic'),
])
def test_bad_parameter_stops_pose_node_with_one_line(tmp_path, changes, expected):
    run = subprocess.run([executable('homography_pose_node'), '--ros-args', '--params-file',
                          str(_params_file(tmp_path, changes))],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and expected in fatal[0], run.stdout + run.stderr


@pytest.mark.parametrize('old, new, expected', [
    ('D: [-0.06, 0.012, 0.0004, -0.0003, 0.0]', 'D: [-0.06, 0.012, 0.0004, -0.0003, 0]',
     'camera.D: list mixes double (-0.06) and integer (0)'),
    ('D: [-0.06, 0.012, 0.0004, -0.0003, 0.0]', 'D: [-0.06, 0.012, none, -0.0003, 0.0]',
     'camera.D: list mixes double (-0.06) and string (none)'),
    ('camera:', 'camera: [', 'not valid YAML'),
])
def test_params_file_rcl_would_refuse_stops_pose_node_with_one_line(tmp_path, old, new, expected):
    """rcl refuses these files with a traceback from rclpy.init (exit 1); the node says
    why in one line naming the parameter first, before rclpy.init."""
    text = CONFIG.read_text()
    assert text.count(old) == 1
    cfg = tmp_path / 'params.yaml'
    cfg.write_text(text.replace(old, new))
    run = subprocess.run([executable('homography_pose_node'), '--ros-args', '--params-file',
                          str(cfg)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and 'FATAL' in lines[0] and expected in lines[0], run.stderr


class Probe:
    """Test-side view of the pose node: its poses by stamp and its last diagnostics."""

    def __init__(self, ros_node, name: str = '/homography_pose_node') -> None:
        self.poses: dict[int, PoseStamped] = {}
        self.status = None
        self.image = ros_node.create_publisher(Image, '/onboard/image_raw', RELIABLE)
        self.compressed = ros_node.create_publisher(CompressedImage,
                                                    '/onboard/image_raw/compressed', RELIABLE)
        ros_node.create_subscription(
            PoseStamped, '/onboard/pose',
            lambda m: self.poses.setdefault(stamp_to_ns(m.header.stamp), m), RELIABLE)
        ros_node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)
        self.name = name

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == self.name:
                self.status = status

    def value(self, key: str) -> str | None:
        values = {} if self.status is None else {kv.key: kv.value for kv in self.status.values}
        return values.get(key)

    def ready(self) -> bool:
        return (self.image.get_subscription_count() > 0
                and self.compressed.get_subscription_count() > 0)


def header(k: int) -> Header:
    """Header of the k-th test frame (15 frames per second)."""
    return Header(stamp=ns_to_stamp(1_000_000_000 + k * 66_666_667),
                  frame_id='onboard_camera_optical')


def level_pose(x: float, y: float, z: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.from_euler('z', yaw).as_matrix(), np.array([x, y, z])


def counted(probe: Probe, publish, before: int) -> int:
    """Publish a malformed message until the node's `malformed` count passes `before`;
    the count once it has settled."""
    def count() -> int:
        return int(probe.value('malformed') or 0)
    for _ in range(20):
        publish()
        if wait_for(lambda: count() > before, 1.0):
            break
    time.sleep(1.0)        # copies still in flight are counted too
    assert count() > before, f'the node never counted a malformed message: {probe.status}'
    return count()


def test_malformed_images_are_counted_skipped_and_the_node_goes_on(ros_node, processes, cfg):
    proc = processes('homography_pose_node', POSE_NODE_ARGS)
    probe = Probe(ros_node)
    assert wait_for(probe.ready, 30)
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=1)
    good = scene.render(*level_pose(0.0, 0.0, 1.0, 0.0))      # the configured first pose
    wrong_encoding = Image(header=header(0), height=480, width=640, encoding='32FC1', step=2560)
    wrong_encoding.data = bytes(480 * 2560)
    garbage = CompressedImage(header=header(2), format='jpeg')
    garbage.data = b'\xff\xd8 not a jpeg at all'
    # Each topic's first message may be published before the node hears the test's
    # publisher: sent until counted, the counts below are taken from there.
    malformed = counted(probe, lambda: probe.image.publish(wrong_encoding), 0)
    malformed = counted(probe, lambda: probe.compressed.publish(garbage), malformed)
    probe.image.publish(bgr_to_image(good[:240, :320], header(1)))           # wrong size
    # The same frame on both topics: processed once, the copy is skipped as stale.
    probe.image.publish(bgr_to_image(good, header(3)))
    probe.compressed.publish(bgr_to_compressed(good, header(3)))
    assert wait_for(lambda: probe.value('stale') == '1'
                    and probe.value('malformed') == str(malformed + 1), 15), probe.status
    assert list(probe.poses) == [stamp_to_ns(header(3).stamp)]
    p, q = msg_to_pose(probe.poses[stamp_to_ns(header(3).stamp)])
    assert probe.poses[stamp_to_ns(header(3).stamp)].header.frame_id == 'world'
    assert np.allclose(p, [0.0, 0.0, 1.0], atol=1e-9) and abs(q[3]) == pytest.approx(1.0)
    assert proc.poll() is None
    log = processes.log('homography_pose_node')
    assert 'unsupported encoding' in log and 'expected 640x480' in log and 'cannot decode' in log


def test_textureless_and_blurred_frames_give_no_pose_and_diagnostics_say_why(
        ros_node, processes, cfg):
    processes('homography_pose_node', POSE_NODE_ARGS)
    probe = Probe(ros_node)
    assert wait_for(probe.ready, 30)
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=2)
    blank = OnboardScene(cfg.camera, cfg.camera_to_body, np.full((8, 8, 3), 140, np.uint8), seed=2)
    truth = [level_pose(0.0, 0.0, 1.0, 0.0), level_pose(0.01, 0.0, 1.0, 0.0),
             level_pose(0.02, -0.01, 1.01, 0.01), level_pose(0.03, -0.01, 1.02, 0.02),
             level_pose(0.04, -0.02, 1.03, 0.03)]
    frames = [scene.render(*truth[0]), scene.render(*truth[1]),
              blank.render(*truth[2]),                                 # texture-less
              scene.render(*truth[3], blur_sigma=6.0),                  # defocused
              scene.render(*truth[4])]
    for k, img in enumerate(frames[:4]):
        probe.compressed.publish(bgr_to_compressed(img, header(k)))
    assert wait_for(lambda: probe.value('frames') == '4', 15), probe.status
    stamps = [stamp_to_ns(header(k).stamp) for k in range(5)]
    assert sorted(probe.poses) == stamps[:2]
    assert probe.status.level == DiagnosticStatus.WARN
    assert probe.status.message.startswith('tracking lost: blurred or texture-less')
    assert probe.value('lost') == '2' and probe.value('lost_frames') == '2'
    assert probe.value('last_loss_stamp') == f'{stamps[3] * 1e-9:.3f}'
    # The next sharp frame is tracked again, and correctly.
    probe.compressed.publish(bgr_to_compressed(frames[4], header(4)))
    assert wait_for(lambda: probe.value('frames') == '5', 15), probe.status
    assert sorted(probe.poses) == [stamps[0], stamps[1], stamps[4]]
    assert probe.status.level == DiagnosticStatus.OK and probe.value('poses') == '3'
    assert probe.value('relocalisations') == '0'      # the last good frame still predicts it
    R, p_true = truth[4]
    p, q = msg_to_pose(probe.poses[stamps[4]])
    assert np.linalg.norm(p - p_true) < 0.01 * p_true[2]
    assert np.degrees((Rotation.from_matrix(R).inv() * Rotation.from_quat(q)).magnitude()) < 0.5


def test_each_pose_comes_with_its_covariance_on_pose_cov(ros_node, processes, cfg):
    """onboard/pose_cov carries every pose of onboard/pose (same stamp, same pose) with a
    covariance (uav_vs.vision.plane_pose_covariance): the first frame's the init sigmas',
    the tracked ones larger by their fit's; the diagnostics give the pixel noise taken."""
    processes('homography_pose_node', POSE_NODE_ARGS)
    probe = Probe(ros_node)
    covs: dict[int, PoseWithCovarianceStamped] = {}
    ros_node.create_subscription(PoseWithCovarianceStamped, '/onboard/pose_cov',
                                 lambda m: covs.setdefault(stamp_to_ns(m.header.stamp), m),
                                 RELIABLE)
    assert wait_for(probe.ready, 30)
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=3)
    for k in range(4):
        frame = scene.render(*level_pose(0.01 * k, -0.005 * k, 1.0 + 0.01 * k, 0.01 * k))
        probe.compressed.publish(bgr_to_compressed(frame, header(k)))
    assert wait_for(lambda: len(covs) == 4 and len(probe.poses) == 4, 15), probe.status
    assert sorted(covs) == sorted(probe.poses)
    first = cfg.params.init_position_sigma ** 2, cfg.params.init_angle_sigma ** 2
    for k, stamp in enumerate(sorted(covs)):
        position, q, cov = msg_to_pose_cov_in(covs[stamp], 'world')   # a covariance
        p, q_pose = msg_to_pose(probe.poses[stamp])
        assert np.allclose(position, p) and np.allclose(q, q_pose)
        variances = np.diag(cov)
        if k == 0:
            assert np.allclose(variances, [first[0]] * 3 + [first[1]] * 3)
        else:
            assert np.all(variances[:3] > first[0]) and np.all(variances[3:] > first[1])
    assert wait_for(lambda: probe.value('pixel_sigma') not in (None, ''), 5), probe.status
    assert float(probe.value('pixel_sigma')) >= cfg.params.pixel_sigma_floor


def test_initialised_at_the_ground_pose_at_its_first_frames_stamp(ros_node, processes, cfg):
    """init.mode pose_topic: the vehicle moves (0.2 m/s, 0.1 rad/s) and the ground poses
    come at 30 Hz, none at a frame's stamp. The first frame waits for the pose after it
    and starts at the poses either side interpolated; one with no pose near it is lost
    and says why; a pose in another frame is counted and skipped."""
    processes('homography_pose_node', [*POSE_NODE_ARGS, '-p', 'init.mode:=pose_topic'])
    probe = Probe(ros_node)
    ground = ros_node.create_publisher(PoseStamped, '/ground/pose', RELIABLE)
    assert wait_for(lambda: probe.ready() and ground.get_subscription_count() > 0, 30)
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=3)

    def truth(t: float) -> tuple[np.ndarray, np.ndarray]:
        return level_pose(0.3 + 0.2 * t, -0.2, 1.2, 0.4 + 0.1 * t)

    def send(t: float, frame_id: str = 'world') -> None:
        R, p = truth(t)
        ground.publish(pose_to_msg(p, Rotation.from_matrix(R).as_quat(),
                                   Header(stamp=ns_to_stamp(round(t * 1e9)), frame_id=frame_id)))

    received = frames = 0

    def frame(k: int) -> float:
        nonlocal frames
        t = stamp_to_ns(header(k).stamp) * 1e-9
        probe.compressed.publish(bgr_to_compressed(scene.render(*truth(t)), header(k)))
        frames += 1
        assert wait_for(lambda: probe.value('frames') == str(frames), 15), probe.status
        return t

    def sent(*stamps: float) -> None:
        nonlocal received
        for t in stamps:
            send(t)
        received += len(stamps)
        assert wait_for(lambda: probe.value('init_poses') == str(received), 15), probe.status

    for _ in range(20):         # until the node hears the publisher
        send(0.5, 'map')
        if wait_for(lambda: probe.value('malformed_init_poses') not in (None, '0'), 1.0):
            break
    sent(0.5, 0.533)
    frame(0)                    # at 1.0 s: no pose after it yet, it waits
    assert probe.value('reason') == 'waiting for ground/pose at the first frame', probe.status
    sent(1.3)                   # the poses either side are 0.8 s apart, neither within 0.02 s
    assert wait_for(lambda: probe.value('lost') == '1', 15), probe.status
    assert probe.value('last_loss') == ('no ground/pose pose at the first frame: none within '
                                        '0.02 s of the image'), probe.status
    t6 = stamp_to_ns(header(6).stamp) * 1e-9       # 1.4 s
    sent(1.311, 1.344, 1.378)
    frame(6)
    frame(7)                    # while the first frame waits: lost, the first one kept
    assert not probe.poses and probe.value('lost') == '2', probe.status
    assert probe.value('last_loss') == 'the first frame waits for ground/pose'
    sent(1.411)                 # the pose after it: initialised at the two interpolated
    stamp6 = stamp_to_ns(header(6).stamp)
    assert wait_for(lambda: stamp6 in probe.poses, 15), probe.status
    R, p_true = truth(t6)
    p, q = msg_to_pose(probe.poses[stamp6])
    assert np.linalg.norm(p - p_true) < 1e-3, (p, p_true)
    assert np.degrees((Rotation.from_matrix(R).inv() * Rotation.from_quat(q)).magnitude()) < 0.05
    t8 = frame(8)               # tracked from there, no pose needed
    p, q = msg_to_pose(probe.poses[stamp_to_ns(header(8).stamp)])
    assert np.linalg.norm(p - truth(t8)[1]) < 0.01 * 1.2
    assert probe.value('init_poses') == '7' and probe.value('malformed_init_poses') != '0'
    assert probe.value('lost') == '2' and probe.value('poses') == '2'


# --------------------------------------------------------------- target node

ASSETS = REPO / 'uav_vs' / 'sim' / 'assets'


def pasted_box() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """box.png pasted into an aerial image through a known H (rotated, scaled, in
    perspective): (scene, the aerial image alone, H's template corners and centre)."""
    template = cv2.imread(str(ASSETS / 'box.png'), cv2.IMREAD_GRAYSCALE)
    h, w = template.shape
    c, s = 0.85 * np.cos(np.radians(25)), 0.85 * np.sin(np.radians(25))
    H = np.array([[c, -s, 260.0], [s, c, 90.0], [3e-4, -2e-4, 1.0]])
    ground = cv2.imread(str(ASSETS / 'aero3.jpg'))
    scene = ground.copy()
    inside = cv2.warpPerspective(np.full_like(template, 255), H, (640, 480)) > 0
    scene[inside] = cv2.cvtColor(cv2.warpPerspective(template, H, (640, 480)),
                                 cv2.COLOR_GRAY2BGR)[inside]
    ref = np.array([[0, 0], [w, 0], [w, h], [0, h], [w / 2, h / 2]], float)
    return scene, ground, cv2.perspectiveTransform(ref[None], H)[0]


def test_target_found_at_a_known_homography_and_not_where_it_is_absent(ros_node, processes):
    """The box pasted through a known H: the five published points are H's corners and
    centre to 2 px; the aerial image alone: not found."""
    processes('target_tracker_node', ['--params-file', str(CONFIG),
                                      '-p', f"target.template:={ASSETS / 'box.png'}",
                                      '-p', 'target.image_qos:=reliable',
                                      '-p', 'target.diagnostics_period:=0.1'])
    scene, ground, expected = pasted_box()
    targets: list[PolygonStamped] = []
    found: list[bool] = []
    ros_node.create_subscription(PolygonStamped, '/onboard/target', targets.append, RELIABLE)
    ros_node.create_subscription(Bool, '/onboard/target_found', lambda m: found.append(m.data),
                                 RELIABLE)
    outlines: list[ImageMarker] = []
    outline_sub = ros_node.create_subscription(ImageMarker, '/onboard/target_outline',
                                               outlines.append, RELIABLE)
    pub = ros_node.create_publisher(CompressedImage, '/onboard/image_raw/compressed', RELIABLE)
    assert wait_for(lambda: pub.get_subscription_count() > 0
                    and outline_sub.get_publisher_count() > 0, 30)
    pub.publish(bgr_to_compressed(scene, header(0)))
    pub.publish(bgr_to_compressed(ground, header(1)))
    assert wait_for(lambda: len(found) == 2 and len(outlines) == 2, 30), found
    assert found == [True, False] and len(targets) == 1
    assert targets[0].header.stamp == header(0).stamp
    assert targets[0].header.frame_id == 'onboard_camera_optical'
    got = polygon_to_array(targets[0])
    assert got.shape == (5, 3)
    assert np.abs(got[:, :2] - expected).max() < 2.0, got[:, :2] - expected
    # The annotation: the outline through the four corners found, none where none was.
    drawn = np.array([(p.x, p.y) for p in outlines[0].points]).reshape(4, 2, 2)
    np.testing.assert_allclose(drawn[:, 0], got[:4, :2])
    assert outlines[0].header == targets[0].header and outlines[1].points == []


def start_in(cwd: Path, ros_args: list[str]) -> tuple[subprocess.Popen, Path]:
    """target_tracker_node started from working directory cwd, as `ros2 run` anywhere."""
    log = cwd / 'target_tracker_node.log'
    with open(log, 'wb') as out:
        proc = subprocess.Popen([executable('target_tracker_node'), '--ros-args', *ros_args],
                                cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
    return proc, log


def test_yaml_template_is_found_from_any_working_directory(tmp_path, ros_node):
    """The YAML's relative target.template (uav_vs/sim/assets/box.png) is not under the
    working directory: it is found in the package, and the node finds the target with it."""
    proc, log = start_in(tmp_path, ['--params-file', str(CONFIG),
                                    '-p', 'target.image_qos:=reliable'])
    try:
        found: list[bool] = []
        ros_node.create_subscription(Bool, '/onboard/target_found',
                                     lambda m: found.append(m.data), RELIABLE)
        pub = ros_node.create_publisher(CompressedImage, '/onboard/image_raw/compressed',
                                        RELIABLE)
        assert wait_for(lambda: pub.get_subscription_count() > 0
                        and 'template ' in log.read_text(), 30), log.read_text()
        assert f"template {ASSETS / 'box.png'} (" in log.read_text()
        pub.publish(bgr_to_compressed(pasted_box()[0], header(0)))
        assert wait_for(lambda: found == [True], 30), (found, log.read_text())
    finally:
        assert stop([proc]) == [0], log.read_text()


def test_relative_template_is_taken_from_the_working_directory_first(tmp_path):
    own = tmp_path / 'uav_vs' / 'sim' / 'assets' / 'box.png'
    own.parent.mkdir(parents=True)
    cv2.imwrite(str(own), cv2.imread(str(ASSETS / 'aero1.jpg'))[:200, :300])
    proc, log = start_in(tmp_path, ['--params-file', str(CONFIG)])
    try:
        assert wait_for(lambda: 'template ' in log.read_text() or proc.poll() is not None, 30)
        assert f'template {own} (300x200 px)' in log.read_text(), log.read_text()
    finally:
        assert stop([proc]) == [0], log.read_text()


@pytest.mark.parametrize('template, expected', [
    ('/nonexistent/helipad.png', "cannot read an image from '/nonexistent"),
    ('no/such/helipad.png', "cannot read an image from 'no/such/helipad.png' (no such file: "),
    (str(ASSETS / 'README.md'), 'cannot read an image'),
    ('blank.png', 'features'),                  # readable, but nothing to match
])
def test_unusable_template_stops_target_node_with_one_line(tmp_path, template, expected):
    if template == 'blank.png':
        template = str(tmp_path / template)
        cv2.imwrite(template, np.full((200, 300), 128, np.uint8))
    run = subprocess.run([executable('target_tracker_node'), '--ros-args', '--params-file',
                          str(CONFIG), '-p', f'target.template:={template}'],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert run.returncode == 2
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1, run.stdout + run.stderr
    assert 'target.template: ' in fatal[0] and expected in fatal[0], fatal[0]
