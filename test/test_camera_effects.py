"""Camera effects of the simulated world, each against an analytic truth."""
import cv2
import numpy as np
import pytest

from uav_vs.sim.camera_effects import (CameraEffects, EffectsConfig, Exposure, FrameDrops,
                                       GaussianNoise, LensDistortion, Latency, jpeg_roundtrip,
                                       motion_blur, motion_kernel)
from conftest import REPO
from uav_vs.sim.ground_scene import rot_z
from uav_vs.sim.onboard_scene import OnboardScene, ground_texture
from uav_vs.sim.world import ground_image_velocity, point_image_velocity
from uav_vs.vision.camera import Camera, look_at
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config

K = np.array([[520.0, 0.0, 322.0], [0.0, 515.0, 236.0], [0.0, 0.0, 1.0]])
D = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.012])     # strong barrel, plumb bob


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0 ** 2 / mse)


@pytest.mark.parametrize('sigma', [1.0, 2.0, 5.0])
def test_noise_has_the_stated_sigma_on_a_flat_image(sigma):
    noise = GaussianNoise(sigma, (480, 640), np.random.default_rng(3))
    flat = np.full((480, 640, 3), 128, np.uint8)
    a, b = noise(flat).astype(np.float64), noise(flat).astype(np.float64)
    # integer noise: round(N(0, sigma^2)) has variance sigma^2 + 1/12
    assert a.std() == pytest.approx(np.sqrt(sigma ** 2 + 1 / 12), rel=0.02)
    assert abs(a.mean() - 128) < 0.05
    assert np.mean(a != b) > 0.5                  # a new draw every frame


def test_jpeg_of_a_flat_image_is_flat_and_of_a_photo_is_within_quality_bounds():
    # A flat block is its DC coefficient 8 (x - 128) alone, quantised by the scaled
    # luminance step (16 x 5000 / q %): the image stays flat, within half a step / 8.
    flat = np.full((64, 64, 3), 77, np.uint8)
    for q in (10, 30):
        out = jpeg_roundtrip(flat, q).astype(int)
        assert np.ptp(out) == 0
        assert abs(out[0, 0, 0] - 77) <= 16 * 50 / q / 16 + 1
    photo = ground_texture()[:480, :640]
    scores = {q: psnr(photo, jpeg_roundtrip(photo, q)) for q in (10, 50, 95)}
    assert 22 < scores[10] < scores[50] < scores[95]
    assert scores[50] < 40 and scores[95] > 35


def test_jpeg_at_one_quality_is_idempotent_in_size():
    photo = ground_texture()[:480, :640]
    for q in (20, 75):
        once = cv2.imencode('.jpg', photo, [cv2.IMWRITE_JPEG_QUALITY, q])[1].size
        again = cv2.imencode('.jpg', jpeg_roundtrip(photo, q), [cv2.IMWRITE_JPEG_QUALITY, q])[1]
        assert abs(again.size - once) < 0.03 * once
        assert psnr(jpeg_roundtrip(photo, q), jpeg_roundtrip(jpeg_roundtrip(photo, q), q)) > 38


@pytest.mark.parametrize('velocity, exposure', [((1200.0, 500.0), 0.01), ((0.0, -800.0), 0.02),
                                                ((-300.0, 300.0), 0.03)])
def test_motion_blur_of_a_point_is_a_centred_line_of_the_motion(velocity, exposure):
    img = np.zeros((101, 101), np.float32)
    img[50, 50] = 1.0
    out = motion_blur(img, np.array(velocity), exposure)
    d = np.array(velocity) * exposure
    length = np.hypot(*d)
    assert out.sum() == pytest.approx(1.0, abs=1e-5)
    v, u = np.nonzero(out > 1e-7)
    w = out[v, u]
    xy = np.column_stack([u, v]) - 50.0
    assert np.allclose(w @ xy, 0.0, atol=1e-3)                  # centred on the point
    along = xy @ (d / length)
    across = xy @ (np.array([-d[1], d[0]]) / length)
    # a uniform segment of length L: variance L^2 / 12 along, none across; the bilinear
    # splat adds up to 1/6 px^2 in each direction
    assert w @ along ** 2 == pytest.approx(length ** 2 / 12 + 1 / 12, abs=0.1)
    assert w @ across ** 2 < 0.3
    assert along.max() - along.min() == pytest.approx(length, abs=2.0)


def test_motion_blur_below_a_tenth_of_a_pixel_leaves_the_image():
    img = np.random.default_rng(0).integers(0, 255, (20, 20, 3), np.uint8)
    assert motion_blur(img, np.array([5.0, 0.0]), 0.01) is img
    assert motion_kernel(np.zeros(2)).shape == (3, 3)


def spot(shape: tuple[int, int], centre: np.ndarray, sigma: float = 1.2) -> np.ndarray:
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    return np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma ** 2)
                  ).astype(np.float32)


def centroid(img: np.ndarray, near: np.ndarray, r: int = 8) -> np.ndarray:
    x0, y0 = np.round(near).astype(int) - r
    patch = img[y0:y0 + 2 * r + 1, x0:x0 + 2 * r + 1].astype(np.float64)
    v, u = np.mgrid[0:patch.shape[0], 0:patch.shape[1]]
    return np.array([(patch * u).sum(), (patch * v).sum()]) / patch.sum() + [x0, y0]


@pytest.mark.parametrize('ideal', [(322.0, 236.0), (120.3, 80.7), (560.6, 410.2), (80.0, 300.5)])
def test_lens_distortion_puts_a_point_where_project_points_does(ideal):
    camera = Camera('c', 640, 480, K, D)
    ideal = np.array(ideal)
    distorted = LensDistortion(camera)(spot((480, 640), ideal))
    ray = np.append(np.linalg.solve(K, np.append(ideal, 1.0))[:2], 1.0)
    expected = cv2.projectPoints(ray[None], np.zeros(3), np.zeros(3), K, D)[0].reshape(2)
    found = centroid(distorted, expected)
    assert np.linalg.norm(found - expected) < 0.05
    # the vision nodes' undistortion with the same K, D returns the ideal point
    assert np.linalg.norm(camera.undistort(found[None])[0] - ideal) < 0.05


def test_no_distortion_is_the_identity():
    img = np.random.default_rng(1).integers(0, 255, (48, 64, 3), np.uint8)
    camera = Camera('c', 64, 48, np.array([[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]]))
    assert np.array_equal(LensDistortion(camera)(img), img)


def test_exposure_is_gain_and_offset_clipped():
    exposure = Exposure(0.1, 5.0, 2.0, np.random.default_rng(4))
    flat = np.array([[0, 100, 250]], np.uint8)
    out = exposure(flat).astype(float)
    expected = np.clip(np.rint(flat * exposure.gain + exposure.offset), 0, 255)
    assert np.array_equal(out, expected)
    exposure.drift.state = np.array([0.5, 0.0])
    assert exposure(flat)[0, 2] == 255 and exposure(flat)[0, 0] == 0


@pytest.mark.parametrize('p', [0.0, 0.05, 0.3, 1.0])
def test_dropped_frame_rate_within_a_binomial_bound(p):
    drops = FrameDrops(p, np.random.default_rng(7))
    n = 20000
    count = sum(drops.dropped() for _ in range(n))
    assert abs(count - n * p) <= 4 * np.sqrt(n * p * (1 - p))


def test_latency_offsets_within_bounds_and_publications_in_order():
    latency, jitter = 0.03, 0.01
    lat = Latency(latency, jitter, np.random.default_rng(8))
    captures = np.arange(3000) / 30.0
    offsets = np.array([lat.offset(t) for t in captures])
    assert np.all((offsets >= latency - jitter) & (offsets <= latency + jitter))
    assert offsets.mean() == pytest.approx(latency, abs=3 * jitter / np.sqrt(3 * len(offsets)))
    assert offsets.std() == pytest.approx(2 * jitter / np.sqrt(12), rel=0.05)
    assert np.all(np.diff(captures + offsets) > 0)


def test_latency_keeps_order_when_jitter_exceeds_the_frame_interval():
    lat = Latency(0.05, 0.04, np.random.default_rng(9))
    captures = np.arange(2000) * 0.005
    published = captures + np.array([lat.offset(t) for t in captures])
    assert np.all(np.diff(published) >= 0)
    assert np.all(published - captures >= 0.05 - 0.04)
    with pytest.raises(ValueError, match='jitter'):
        Latency(0.01, 0.02, np.random.default_rng(0))


def test_camera_effects_all_off_is_the_identity_and_drops_are_counted():
    img = np.random.default_rng(2).integers(0, 255, (48, 64, 3), np.uint8)
    off = CameraEffects(EffectsConfig(), (48, 64), np.random.SeedSequence(0))
    assert np.array_equal(off(img, np.array([500.0, 0.0]), 0.1), img)
    dropping = CameraEffects(EffectsConfig(drop_probability=1.0), (48, 64),
                             np.random.SeedSequence(0))
    assert dropping(img, np.zeros(2), 0.1) is None


def test_camera_effects_chain_is_blur_then_exposure_then_noise_then_jpeg():
    img = np.zeros((64, 64, 3), np.uint8)
    img[:, 32:] = 200
    config = EffectsConfig(noise_sigma=2.0, jpeg_quality=60, exposure_time=0.01,
                           gain_sigma=0.1, offset_sigma=3.0)
    fx = CameraEffects(config, (64, 64), np.random.SeedSequence(11))
    twin = CameraEffects(config, (64, 64), np.random.SeedSequence(11))
    out = fx(img, np.array([600.0, 0.0]), 0.1)
    twin.exposure.step(0.1)
    twin.drops.dropped()
    expected = jpeg_roundtrip(twin.noise(twin.exposure(motion_blur(img, np.array([600.0, 0.0]),
                                                                   0.01))), 60)
    assert np.array_equal(out, expected)


def test_point_image_velocity_is_the_derivative_of_the_pinhole_projection():
    R, t = look_at(np.array([4.0, -3.0, 2.0]), np.zeros(3))
    camera = Camera('c', 640, 480, K, R=R, t=t)
    p, v = np.array([0.3, 0.2, 1.1]), np.array([1.5, -0.7, 0.4])
    X, w = camera.to_camera(p[None])[0], R @ v
    # d/dt of (fx X / Z, fy Y / Z)
    expected = np.diag(K)[:2] * (w[:2] * X[2] - X[:2] * w[2]) / X[2] ** 2
    np.testing.assert_allclose(point_image_velocity(camera, p, v), expected, rtol=1e-3)


@pytest.mark.parametrize('yaw, velocity', [(0.0, (1.0, 0.0, 0.0)), (0.7, (0.3, -0.8, 0.0)),
                                           (-2.0, (0.0, 0.5, 0.2))])
def test_ground_image_velocity_of_the_onboard_camera(yaw, velocity):
    cfg = load_onboard_config(read_params_file(REPO / 'config' / 'onboard.yaml'))
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, np.zeros((8, 8, 3), np.uint8))
    R_wb, p_wb, v = rot_z(yaw), np.array([0.4, -0.2, 2.5]), np.array(velocity)
    R_wc = R_wb @ cfg.camera_to_body[:3, :3]
    centre = p_wb + R_wb @ cfg.camera_to_body[:3, 3]
    Z = -centre[2] / R_wc[2, 2]                      # depth of the ground on the optical axis
    w = -R_wc.T @ v                                  # the ground's velocity in the camera frame
    # d/dt of (fx X / Z, fy Y / Z) at X = Y = 0
    expected = np.diag(cfg.camera.K)[:2] * w[:2] / Z
    np.testing.assert_allclose(ground_image_velocity(scene, R_wb, p_wb, v), expected,
                               rtol=1e-3, atol=1e-6)
