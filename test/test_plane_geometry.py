"""Eq 27 plane geometry: pose refinement against analytic truth and cv2.solvePnP."""
import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uav_vs.vision.camera import look_at
from uav_vs.vision.plane_geometry import (REFINERS, plane_homography,
                                          pose_from_plane_homography, refine_plane_pose)

K = np.array([[520.0, 0.0, 322.0], [0.0, 515.0, 241.0], [0.0, 0.0, 1.0]])


def scene(seed: int, n: int = 40, noise_px: float = 0.0):
    """A camera 2-20 m above the plane looking down up to 40 deg off the vertical, n plane
    points it sees inside a 640x480 image, their exact pixels plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    eye = np.r_[rng.uniform(-5, 5, 2), rng.uniform(2, 20)]
    off = np.tan(np.radians(rng.uniform(0, 40))) * eye[2]
    a = rng.uniform(0, 2 * np.pi)
    R, t = look_at(eye, eye + [off * np.cos(a), off * np.sin(a), -eye[2]])
    roll = Rotation.from_euler('z', rng.uniform(-np.pi, np.pi)).as_matrix()
    R, t = roll @ R, roll @ t
    H_inv = np.linalg.inv(plane_homography(K, R, t))
    px = rng.uniform([20, 20], [620, 460], (n, 2))
    q = np.c_[px, np.ones(n)] @ H_inv.T
    xy = q[:, :2] / q[:, 2:]
    return R, t, xy, px + rng.normal(0, noise_px, px.shape) if noise_px else px


def reprojection_rms(R, t, xy, px) -> float:
    q = np.c_[xy, np.ones(len(xy))] @ plane_homography(K, R, t).T
    return float(np.sqrt(np.mean(np.sum((q[:, :2] / q[:, 2:] - px) ** 2, axis=1))))


def angle_deg(Ra, Rb) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(Ra.T @ Rb).as_rotvec())))


@pytest.mark.parametrize('method', REFINERS)
@pytest.mark.parametrize('seed', range(20))
def test_exact_correspondences_give_the_true_pose_from_a_wrong_start(seed, method):
    """From 5 deg and 10 % of the distance away, the pose comes back to 1e-9 (lm); cv2's
    LM stops by its own criteria, some 1e-6 deg from it whatever the iteration cap."""
    R, t, xy, px = scene(seed)
    rng = np.random.default_rng(100 + seed)
    w = rng.normal(size=3)
    R0 = Rotation.from_rotvec(np.radians(5) * w / np.linalg.norm(w)).as_matrix() @ R
    t0 = t + 0.1 * np.linalg.norm(t) * rng.normal(size=3) / np.sqrt(3)
    fit = refine_plane_pose(K, xy, px, R0, t0, method=method)
    tol = 1.0 if method == 'lm' else 100.0
    assert angle_deg(R, fit.R) < 1e-7 * tol
    np.testing.assert_allclose(fit.t, t, atol=1e-9 * tol * np.linalg.norm(t))
    assert fit.rms_px < 1e-8 * tol ** 2
    assert fit.iterations >= 2 if method == 'lm' else fit.iterations is None


@pytest.mark.parametrize('method', REFINERS)
@pytest.mark.parametrize('seed', range(20))
def test_noisy_correspondences_agree_with_opencv_solvepnp(seed, method):
    """With 0.7 px noise: the same least-squares optimum as cv2.solvePnP (ITERATIVE) to
    1e-6, a reprojection RMS near the noise's expected sigma sqrt((2N - 6) / N), and a
    better fit than the closed-form pose of the DLT homography (section 4.1)."""
    sigma, n = 0.7, 60
    R, t, xy, px = scene(seed, n, sigma)
    fit = refine_plane_pose(K, xy, px, method=method)   # started from the homography
    xyz = np.c_[xy, np.zeros(n)]
    ok, rvec, tvec = cv2.solvePnP(xyz, px, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    R_cv, t_cv = cv2.Rodrigues(rvec)[0], tvec.ravel()
    assert angle_deg(R_cv, fit.R) < 1e-4
    np.testing.assert_allclose(fit.t, t_cv, atol=1e-6 * np.linalg.norm(t))
    assert fit.rms_px <= reprojection_rms(R_cv, t_cv, xy, px) + 1e-9
    assert abs(fit.rms_px - sigma * np.sqrt((2 * n - 6) / n)) < 0.25 * sigma
    H, _ = cv2.findHomography(xy, px, 0)
    assert fit.rms_px < reprojection_rms(*pose_from_plane_homography(K, H), xy, px)
    # ... and the pose error is what that noise allows: under a degree, under 2 % of range.
    assert angle_deg(R, fit.R) < 1.0
    assert np.linalg.norm(-fit.R.T @ fit.t + R.T @ t) < 0.02 * np.linalg.norm(t)


def test_skewed_intrinsics_and_3d_plane_points():
    """A skewed K and (N,3) points with Z = 0 give the true pose too (lm); cv2's model
    has no skew, so the opencv refinement refuses such a K rather than miss by ~0.4 deg."""
    Ks = K.copy()
    Ks[0, 1] = 4.0
    R, t, xy, _ = scene(3)
    q = np.c_[xy, np.ones(len(xy))] @ plane_homography(Ks, R, t).T
    xyz, px = np.c_[xy, np.zeros(len(xy))], q[:, :2] / q[:, 2:]
    fit = refine_plane_pose(Ks, xyz, px, method='lm')
    assert angle_deg(R, fit.R) < 1e-7 and fit.rms_px < 1e-8
    with pytest.raises(ValueError, match='ignores the skew of K'):
        refine_plane_pose(Ks, xyz, px, method='opencv')


@pytest.mark.parametrize('args, words', [
    ((np.zeros((3, 2)), np.zeros((3, 2))), 'at least 4'),
    ((np.zeros((5, 2)), np.zeros((4, 2))), 'expected (N,2)'),
    ((np.c_[np.ones((5, 2)), np.ones(5)], np.zeros((5, 2))), 'Z = 0'),
    ((np.full((5, 2), np.nan), np.zeros((5, 2))), 'NaN'),
    ((np.c_[np.arange(5.0), np.arange(5.0)], np.c_[np.arange(5.0), np.arange(5.0)]), 'degenerate'),
])
def test_bad_input_is_one_clear_line(args, words):
    with pytest.raises(ValueError) as err:
        refine_plane_pose(K, *args)
    assert words in str(err.value) and '\n' not in str(err.value)


def test_an_unknown_method_is_one_clear_line():
    _, _, xy, px = scene(0)
    with pytest.raises(ValueError, match="method: expected one of lm, opencv, got 'gn'"):
        refine_plane_pose(K, xy, px, method='gn')


def test_a_start_needs_both_rotation_and_translation():
    _, t, xy, px = scene(0)
    with pytest.raises(ValueError, match='both R and t'):
        refine_plane_pose(K, xy, px, t=t)
