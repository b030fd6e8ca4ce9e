"""Camera model (eq 15-16, 20-21) and the ground calibration loader, against hand-computed
geometry and OpenCV's own projection."""
import re

import cv2
import numpy as np
import pytest

from uav_vs.vision.camera import CalibrationError, Camera, look_at, undistort_points
from uav_vs.vision.ground_config import (default_config_path, load_ground_config,
                                         read_params_file)

# Camera looking along world +x: optical x = -y_w, optical y = -z_w, optical z = +x_w.
R_FWD = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
K = np.array([[500.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
D = np.array([-0.12, 0.08, 0.0004, -0.0003, -0.02])


def params(**override):
    p = {'width': 640, 'height': 480, 'K': K.ravel().tolist(), 'D': D.tolist(),
         'R': R_FWD.ravel().tolist(), 't': [0.2, 0.1, 1.0], 'frame_id': 'cam_optical'}
    p.update(override)
    return p


def test_projection_matches_hand_computed_eq15_16():
    """X_w = (5, -1, 0.5): x_c = R X_w + t = (1 + 0.2, -0.5 + 0.1, 5 + 1) = (1.2, -0.4, 6),
    so u = 320 + 500 * 1.2 / 6 = 420 and v = 240 + 400 * (-0.4 / 6) = 213.333..."""
    cam = Camera('c', 640, 480, K, np.zeros(5), R_FWD, np.array([0.2, 0.1, 1.0]))
    X = np.array([[5.0, -1.0, 0.5]])
    np.testing.assert_allclose(cam.to_camera(X), [[1.2, -0.4, 6.0]], atol=1e-15)
    np.testing.assert_allclose(cam.project(X), [[420.0, 240.0 - 400 * 0.4 / 6]], atol=1e-12)
    h = cam.P @ np.array([5.0, -1.0, 0.5, 1.0])           # eq 15 in homogeneous form
    np.testing.assert_allclose(h[:2] / h[2], cam.project(X)[0], atol=1e-12)
    np.testing.assert_allclose(cam.center, [-1.0, 0.2, 0.1], atol=1e-15)


def test_distorted_projection_matches_opencv_and_round_trips():
    cam = Camera.from_params('c', params())
    rng = np.random.default_rng(3)
    X = rng.uniform([4, -2.5, -2], [9, 2.5, 2], (200, 3))   # in front, filling the image
    px = cam.project(X)
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, cam.D)
    np.testing.assert_allclose(px, ref.reshape(-1, 2), atol=1e-9)
    Xc = cam.to_camera(X)
    ideal = Xc[:, :2] / Xc[:, 2:]
    np.testing.assert_allclose(cam.normalize(px), ideal, atol=1e-9)
    np.testing.assert_allclose(cam.undistort(px), ideal @ K[:2, :2].T + K[:2, 2], atol=1e-6)
    assert np.abs(px - (ideal @ K[:2, :2].T + K[:2, 2])).max() > 5   # distortion is not nil


def test_points_behind_the_camera_are_nan():
    cam = Camera.from_params('c', params())
    px = cam.project(np.array([[-5.0, 0.0, 0.0], [5.0, 0.0, 0.0]]))
    assert np.isnan(px[0]).all() and np.isfinite(px[1]).all()


def test_look_at_points_the_optical_axis_at_the_target():
    eye, target = np.array([6.0, 1.0, 3.5]), np.array([0.0, 0.0, 1.0])
    R, t = look_at(eye, target)
    cam = Camera('c', 640, 480, K, np.zeros(5), R, t)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(cam.center, eye, atol=1e-12)
    np.testing.assert_allclose(cam.project(target[None])[0], K[:2, 2], atol=1e-9)
    above = cam.project((target + [0, 0, 1.0])[None])[0]
    assert above[1] < K[1, 2]                     # world up is image up (optical y down)


def test_camera_info_fields_map_one_to_one():
    cam = Camera.from_params('c', params())
    f = cam.camera_info_fields()
    assert (f['width'], f['height'], f['distortion_model']) == (640, 480, 'plumb_bob')
    assert f['k'] == K.ravel().tolist() and f['d'] == D.tolist()
    np.testing.assert_array_equal(np.reshape(f['p'], (3, 4))[:, :3], K)


@pytest.mark.parametrize('override, key', [
    ({'K': None}, 'K'),
    ({'K': [500.0, 0, 320, 0, 400, 240, 0, 0]}, 'K'),
    ({'K': [500.0, 0, 320, 0, 400, 240, 0, 0, 2]}, 'K'),
    ({'D': ['a', 0, 0, 0, 0]}, 'D'),
    ({'D': [0.1, 0.0, 0.0]}, 'D'),
    ({'R': (2 * R_FWD).ravel().tolist()}, 'R'),
    ({'R': (R_FWD * [[1], [1], [-1]]).ravel().tolist()}, 'R'),      # reflection, det -1
    ({'R': [1.0, 0.0, 0.0]}, 'R'),
    ({'t': 'zero'}, 't'),
    ({'width': 640.5}, 'width'),
])
def test_from_params_names_the_bad_parameter(override, key):
    p = params(**override)
    if override.get(key, 0) is None:
        del p[key]
    with pytest.raises(CalibrationError) as err:
        Camera.from_params('cam2', p, prefix='cameras.cam2.')
    msg = str(err.value)
    assert msg.startswith(f'cameras.cam2.{key}:') and '\n' not in msg


def test_shipped_config_loads():
    cfg = load_ground_config(read_params_file(default_config_path()))
    assert [c.name for c in cfg.cameras] == ['cam1', 'cam2', 'cam3']
    assert cfg.landmark_names == ['red', 'green', 'blue', 'yellow']
    assert cfg.layout.shape == (4, 3) and cfg.radius > 0
    centre = np.array([0.0, 0.0, 1.2])
    for cam in cfg.cameras:          # every camera sees the flight area centre, in frame
        u, v = cam.project(centre[None])[0]
        assert 0 < u < cam.width and 0 < v < cam.height
        assert cam.frame_id == f'{cam.name}_optical'


def test_every_config_key_is_commented():
    """Each `key:` line of the YAML has a comment on it or on the line above."""
    lines = default_config_path().read_text().splitlines()
    for i, line in enumerate(lines):
        m = re.match(r'\s*([\w.]+):', line)
        if m and m.group(1) not in ('ros__parameters',) and not line.startswith('/**'):
            assert '#' in line or lines[i - 1].strip().startswith('#'), f'line {i + 1}: {line}'


@pytest.mark.parametrize('key, value', [
    ('cameras.names', ['cam1']),
    ('cameras.names', 'cam1'),
    ('cameras.cam2.R', [1.0] * 9),
    ('cameras.cam3.K', None),
    ('landmarks.names', ['red', 'red']),
    ('landmarks.blue.position', [0.1, 0.2]),
    ('landmarks.green.hue', [50, 200]),
    ('landmarks.green.saturation', [200, 100]),
    ('landmarks.yellow.value', [0.5, 255]),
    ('landmarks.radius', -1.0),
])
def test_ground_config_names_the_bad_parameter(key, value):
    flat = read_params_file(default_config_path())
    if value is None:
        del flat[key]
    else:
        flat[key] = value
    with pytest.raises(CalibrationError) as err:
        load_ground_config(flat)
    assert str(err.value).startswith(f'{key}:') and '\n' not in str(err.value)


def test_hue_range_may_wrap_through_zero():
    flat = read_params_file(default_config_path())
    flat['landmarks.red.hue'] = [170, 10]
    cfg = load_ground_config(flat)
    assert cfg.hue[0].tolist() == [170, 10]


# One set of coefficients per OpenCV distortion model (k1 k2 p1 p2 [k3 [k4 k5 k6
# [s1 s2 s3 s4 [tau_x tau_y]]]]), each a lens that distorts the image edge by pixels.
MODELS = {
    0: [],
    4: [-0.11, 0.03, 0.0008, -0.0004],
    5: [-0.11, 0.03, 0.0008, -0.0004, -0.006],
    8: [0.15, -0.04, 0.0008, -0.0004, 0.002, 0.27, -0.05, 0.01],
    12: [0.15, -0.04, 0.0008, -0.0004, 0.002, 0.27, -0.05, 0.01, 0.002, -0.001, 0.0015, 0.0005],
    14: [0.15, -0.04, 0.0008, -0.0004, 0.002, 0.27, -0.05, 0.01, 0.002, -0.001, 0.0015, 0.0005,
         0.01, -0.015],
}


@pytest.mark.parametrize('n', sorted(MODELS))
def test_every_opencv_distortion_model_round_trips_against_opencv(n):
    """Camera from K and D alone: pixels as cv2.projectPoints gives them, and back to the
    true normalised coordinates (and to what cv2.undistortPoints gives)."""
    D = np.array(MODELS[n])
    R, t = look_at(np.array([0.3, -0.2, -1.0]), np.array([0.0, 0.0, 5.0]), up=np.array([0, -1.0, 0]))
    cam = Camera(K=K, D=D, R=R, t=t)
    rng = np.random.default_rng(n)
    X = rng.uniform([-2.5, -2.0, 4.0], [2.5, 2.0, 7.0], (300, 3))
    px = cam.project(X)
    ref, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, D if n else None)
    np.testing.assert_allclose(px, ref.reshape(-1, 2), atol=1e-9)
    Xc = cam.to_camera(X)
    ideal = Xc[:, :2] / Xc[:, 2:]
    np.testing.assert_allclose(cam.normalize(px), ideal, atol=1e-9)
    undistorted = undistort_points(px.reshape(-1, 1, 2), K, D)     # cv2, on pixels
    np.testing.assert_allclose(cam.normalize(px), undistorted.reshape(-1, 2), atol=1e-9)
    if n:
        assert np.abs(px - (ideal @ K[:2, :2].T + K[:2, 2])).max() > 2   # the lens does act
    info = cam.camera_info_fields()
    assert info['distortion_model'] == ('plumb_bob' if n <= 5 else 'rational_polynomial')
    assert info['d'] == (D.tolist() + [0.0] * (5 - n) if n <= 5 else D.tolist())


def test_camera_from_K_alone_is_the_pinhole_at_the_origin_with_skew():
    """x_c = X_w (R = I, t = 0) and u = fx x + s y + cx, v = fy y + cy (eq 15)."""
    Ks = K.copy()
    Ks[0, 1] = 3.0
    cam = Camera(K=Ks)
    X = np.array([[0.4, -0.3, 2.0], [-1.0, 0.5, 4.0]])
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    expected = np.column_stack([500 * x + 3 * y + 320, 400 * y + 240])
    np.testing.assert_allclose(cam.project(X), expected, atol=1e-12)
    np.testing.assert_allclose(cam.normalize(expected), np.column_stack([x, y]), atol=1e-12)
    distorted = Camera(K=Ks, D=MODELS[5])          # skew also honoured through the lens model
    np.testing.assert_allclose(distorted.normalize(distorted.project(X)), np.column_stack([x, y]),
                               atol=1e-9)
    assert cam.width is None and cam.camera_info_fields()['width'] == 0


@pytest.mark.parametrize('D', [[0.1], [0.1, 0.0, 0.0], [0.0] * 6, [0.0] * 9, [0.0] * 15])
def test_distortion_of_a_length_opencv_has_no_model_for_is_refused(D):
    with pytest.raises(CalibrationError) as err:
        Camera(K=K, D=D)
    msg = str(err.value)
    assert msg == (f"D: expected 0, 4, 5, 8, 12 or 14 distortion coefficients (OpenCV's models), "
                   f'got {len(D)}')
    with pytest.raises(CalibrationError, match=r'^cameras\.c\.D: expected 0, 4, 5'):
        Camera.from_params('c', params(D=D), prefix='cameras.c.')


@pytest.mark.parametrize('kwargs, key', [({}, 'K'), ({'K': np.eye(2)}, 'K'),
                                         ({'K': -K}, 'K'), ({'K': K, 't': [0.0, 1.0]}, 't'),
                                         ({'K': K, 'D': [np.nan] * 4}, 'D')])
def test_camera_fields_are_checked_in_one_line(kwargs, key):
    with pytest.raises(CalibrationError) as err:
        Camera(**kwargs)
    assert str(err.value).startswith(f'{key}:') and '\n' not in str(err.value)


@pytest.mark.parametrize('n', [0, 4, 8, 14])
def test_from_params_takes_every_opencv_model(n):
    cam = Camera.from_params('c', params(D=MODELS[n]))
    assert cam.D.tolist() == MODELS[n]
