"""Onboard camera simulator and sample-bag writer against analytic geometry (section 4, eq 27)."""
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from uav_vs.sim.onboard_bag import START_NS, main, write_bag
from uav_vs.sim.onboard_scene import GRAVITY, OnboardScene, Trajectory, Waypoint
from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import camera_pose

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'onboard.yaml'


@pytest.fixture(scope='module')
def cfg():
    return load_onboard_config(read_params_file(CONFIG))


def dot_texture(centres_px: np.ndarray, size: int = 600, sigma: float = 1.5) -> np.ndarray:
    """Dark texture with a bright Gaussian dot at each texture pixel in centres_px."""
    u, v = np.meshgrid(np.arange(size), np.arange(size))
    img = np.zeros((size, size), np.float64)
    for cu, cv in centres_px:
        img += np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2))
    return cv2.cvtColor(np.uint8(20 + 200 * img), cv2.COLOR_GRAY2BGR)


def centroid(gray: np.ndarray, guess: np.ndarray, radius: int = 10) -> np.ndarray:
    x0, y0 = np.rint(guess).astype(int)
    win = gray[y0 - radius:y0 + radius + 1, x0 - radius:x0 + radius + 1].astype(np.float64) - 20
    win = np.clip(win, 0, None)
    v, u = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    return np.array([x0 + (u * win).sum() / win.sum(), y0 + (v * win).sum() / win.sum()])


@pytest.mark.parametrize('distorted', [False, True])
def test_rendered_dots_land_where_the_projection_says(cfg, distorted):
    """Texture points rendered by the plane homography (warp or distortion remap) sit
    where K [R|t] (eq 27) and the lens model put them."""
    D = cfg.camera.D if distorted else np.zeros(5)
    cam = Camera('onboard', 640, 480, cfg.camera.K, D, np.eye(3), np.zeros(3))
    rng = np.random.default_rng(3)
    dots_px = np.column_stack([rng.uniform(150, 450, 12), rng.uniform(180, 420, 12)])
    scene = OnboardScene(cam, cfg.camera_to_body, dot_texture(dots_px), metres_per_pixel=0.005,
                         origin_px=(300.0, 300.0), noise_sigma=0.0)
    R_wb = Rotation.from_euler('xyz', [0.08, -0.12, 0.5]).as_matrix()
    p_wb = np.array([0.1, -0.2, 1.6])
    gray = cv2.cvtColor(scene.render(R_wb, p_wb), cv2.COLOR_BGR2GRAY)
    R, t = camera_pose(R_wb, p_wb, cfg.camera_to_body)
    plane = scene.texture_to_plane(dots_px)
    expected = Camera('c', 640, 480, cam.K, D, R, t).project(np.column_stack([plane, np.zeros(12)]))
    inside = np.all((expected > 20) & (expected < [620, 460]), axis=1)
    assert inside.sum() >= 8
    found = np.array([centroid(gray, e) for e in expected[inside]])
    assert np.abs(found - expected[inside]).max() < 0.05


def test_texture_to_plane_is_metric_and_north_up():
    scene = OnboardScene(Camera('c', 64, 48, np.array([[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]]),
                                np.zeros(5), np.eye(3), np.zeros(3)), None,
                         metres_per_pixel=0.005, origin_px=(319.5, 239.5))
    xy = scene.texture_to_plane(np.array([[319.5, 239.5], [519.5, 239.5], [319.5, 39.5]]))
    assert np.allclose(xy, [[0, 0], [1.0, 0], [0, 1.0]])


def test_sensor_noise_has_the_stated_sigma(cfg):
    flat = np.full((32, 32, 3), 128, np.uint8)
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, flat, noise_sigma=2.0, seed=5)
    img = scene.render(np.eye(3), np.array([0.0, 0.0, 2.0])).astype(np.float64)
    assert abs(img.mean() - 128) < 0.05
    assert abs(img.std() - 2.0) < 0.05


def test_trajectory_passes_the_waypoints_level_at_rest():
    traj = Trajectory()
    for wp in traj.waypoints:
        R, p = traj.sample(wp.t)
        assert np.allclose(p, wp.position, atol=1e-12)
        assert np.allclose(R, Rotation.from_euler('z', wp.yaw).as_matrix(), atol=1e-12)
    assert traj.duration == pytest.approx(10.0)


def test_trajectory_tilts_like_a_multirotor():
    """Body z (thrust) is parallel to acceleration + g, from finite differences of position."""
    traj = Trajectory((Waypoint(0.0, (0, 0, 2), 0.0), Waypoint(2.0, (3, 1, 2), 0.8)))
    h = 1e-4
    for t in (0.3, 0.7, 1.5):
        R, p = traj.sample(t)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        accel = (traj.sample(t + h)[1] - 2 * p + traj.sample(t - h)[1]) / h**2
        thrust = accel + [0, 0, GRAVITY]
        assert np.linalg.norm(np.cross(R[:, 2], thrust / np.linalg.norm(thrust))) < 1e-6
        heading = R[:, 0].copy()
        heading[2] = 0
        yaw = np.arctan2(heading[1], heading[0])
        assert yaw == pytest.approx(0.8 * (10 * (t / 2)**3 - 15 * (t / 2)**4 + 6 * (t / 2)**5))
    assert np.degrees(np.arccos(traj.sample(0.3)[0][2, 2])) > 2.0   # visibly tilted


def test_bad_waypoints_are_refused():
    with pytest.raises(ValueError, match='waypoints'):
        Trajectory((Waypoint(1.0, (0, 0, 1), 0), Waypoint(1.0, (1, 0, 1), 0)))


def test_bag_holds_images_calibration_and_truth_on_common_stamps(cfg, tmp_path):
    out = tmp_path / 'bag'
    assert write_bag(out, CONFIG, rate=10.0, duration=0.4, seed=7) == 5
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Reader(out) as reader:
        counts = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        msgs: dict = {}
        for conn, t, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == t
            msgs.setdefault(conn.topic, []).append(msg)
    assert counts == {'onboard/image_raw/compressed': ('sensor_msgs/msg/CompressedImage', 5),
                      'onboard/camera_info': ('sensor_msgs/msg/CameraInfo', 5),
                      'truth/pose': ('geometry_msgs/msg/PoseStamped', 5)}
    traj = Trajectory()
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=7)
    for k in range(5):
        image, info, truth = (msgs[t][k] for t in ('onboard/image_raw/compressed',
                                                  'onboard/camera_info', 'truth/pose'))
        stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in (image, info, truth)}
        assert stamps == {divmod(START_NS + k * 100_000_000, 10**9)}
        assert image.header.frame_id == info.header.frame_id == 'onboard_camera_optical'
        assert truth.header.frame_id == 'world' and image.format == 'jpeg'
        assert np.allclose(info.k, cfg.camera.K.ravel()) and np.allclose(info.d, cfg.camera.D)
        R, p = traj.sample(k / 10.0)
        pos = truth.pose.position
        q = truth.pose.orientation
        assert np.allclose([pos.x, pos.y, pos.z], p)
        assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), R)
        decoded = cv2.imdecode(image.data, cv2.IMREAD_COLOR).astype(np.float64)
        assert np.abs(decoded - scene.render(R, p)).mean() < 3.0    # JPEG q90


def test_bag_command_line_refuses_to_clobber(tmp_path, capsys):
    out = tmp_path / 'bag'
    out.mkdir()
    with pytest.raises(SystemExit) as exc:
        main(['--out', str(out), '--duration', '0'])
    assert exc.value.code == 2 and '--out' in capsys.readouterr().err
    main(['--out', str(out), '--duration', '0', '--overwrite'])
    assert '1 frames' in capsys.readouterr().out
