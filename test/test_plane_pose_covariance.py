"""The onboard pose's covariance (uav_vs.vision.plane_pose_covariance) against its own
definition by finite differences, Monte Carlo of the refined fit, and the simulator's
truth over a rendered flight."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uav_vs.sim.onboard_scene import OnboardScene, Trajectory, fly
from uav_vs.vision.camera import look_at
from uav_vs.vision.plane_geometry import linearise, refine_plane_pose
from uav_vs.vision.plane_pose import PlanePoseEstimator, body_pose
from uav_vs.vision.plane_pose_covariance import fit_covariance

from test_plane_pose import cfg, flat_params, jpeg_grey  # noqa: F401 (fixtures)

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
MOUNT = np.eye(4)                      # optical frame in base_link: down, 10 cm under
MOUNT[:3, :3] = Rotation.from_euler('x', 180, degrees=True).as_matrix()
MOUNT[:3, 3] = [0.05, 0.0, -0.10]


def scene_points(R: np.ndarray, t: np.ndarray, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n plane points (z = 0) the camera sees and their ideal pixels."""
    px = rng.uniform([20, 20], [620, 460], (n, 2))
    rays = np.linalg.solve(K, np.column_stack([px, np.ones(n)]).T).T @ R   # world directions
    centre = -R.T @ t
    xyz = centre - rays * (centre[2] / rays[:, 2])[:, None]
    xyz[:, 2] = 0.0
    return xyz, px


def body_error(R_true, p_true, R, p) -> np.ndarray:
    """(position error, world rotation vector R R_true^T)."""
    return np.r_[p - p_true, Rotation.from_matrix(R @ R_true.T).as_rotvec()]


def test_the_body_pose_jacobian_is_the_derivative_of_body_pose():
    """With a mounted camera, no pixel noise (sigma at its 1 px floor): the covariance is
    (J^T J)^-1 carried through the finite-difference derivative of body_pose (central,
    1e-6) of the world-to-camera perturbation."""
    R, t = look_at(np.array([1.0, -2.0, 3.0]), np.array([1.5, -1.0, 0.0]))
    rng = np.random.default_rng(0)
    xyz, px = scene_points(R, t, 50, rng)
    R_wb, p_wb = body_pose(R, t, MOUNT)
    cov, _ = fit_covariance(K, R, t, xyz, px, p_wb, floor_px=1.0)
    _, J = linearise(K, R, t, xyz, px)
    C = np.linalg.inv(J.T @ J)
    eps = 1e-6
    numeric = np.zeros((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        plus = body_pose(Rotation.from_rotvec(d[:3]).as_matrix() @ R, t + d[3:], MOUNT)
        minus = body_pose(Rotation.from_rotvec(-d[:3]).as_matrix() @ R, t - d[3:], MOUNT)
        numeric[:, k] = (body_error(R_wb, p_wb, *plus) - body_error(R_wb, p_wb, *minus)) / (2 * eps)
    expected = numeric @ C @ numeric.T
    assert np.allclose(cov, expected, rtol=1e-5, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize('eye, target', [((0.0, 0.0, 1.5), (0.0, 0.0, 0.0)),
                                         ((1.0, -2.0, 3.0), (1.5, -1.0, 0.0))])
def test_the_fit_covariance_matches_monte_carlo(eye, target):
    """0.3 px of noise on 60 inliers, 1500 refits from the truth: every predicted standard
    deviation of the body pose within 10 % of the trials' and every correlation within
    0.1; the pixel sigma from the residuals within 5 % of the noise."""
    R, t = look_at(np.array(eye), np.array(target))
    rng = np.random.default_rng(1)
    xyz, px = scene_points(R, t, 60, rng)
    R_wb, p_wb = body_pose(R, t, MOUNT)
    errors, sigmas = [], []
    for _ in range(1500):
        noisy = px + rng.normal(0.0, 0.3, px.shape)
        fit = refine_plane_pose(K, xyz, noisy, R, t, method='lm')
        errors.append(body_error(R_wb, p_wb, *body_pose(fit.R, fit.t, MOUNT)))
        sigmas.append(fit_covariance(K, fit.R, fit.t, xyz, noisy, p_wb, 0.01)[1])
    cov, _ = fit_covariance(K, R, t, xyz, px, p_wb, floor_px=0.3)
    trials = np.cov(np.array(errors).T)
    sd, sd_trials = np.sqrt(np.diag(cov)), np.sqrt(np.diag(trials))
    assert np.all(np.abs(sd / sd_trials - 1) < 0.10), (sd, sd_trials)
    corr, corr_trials = cov / np.outer(sd, sd), trials / np.outer(sd_trials, sd_trials)
    assert np.abs(corr - corr_trials).max() < 0.1
    assert abs(np.mean(sigmas) / 0.3 - 1) < 0.05


@pytest.fixture(scope='module')
def flight_poses(cfg):  # noqa: F811 (the fixture imported above)
    """The sample bag's flight (1 m hover, climb to 3 m, move 3.5 m and turn, descend)
    through the estimator: (its results, the drift covariance after each, the true
    base_link R, p of each frame, the result and drift of a second estimator asked for no
    covariance)."""
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=0)
    frames = [(jpeg_grey(img), R, p) for _, img, R, p in fly(scene, Trajectory(), 15.0)]
    exact_start = replace(cfg.params, init_position_sigma=1e-4, init_angle_sigma=1e-5)
    est, bare = (PlanePoseEstimator(cfg.camera, exact_start, cfg.camera_to_body)
                 for _ in range(2))
    assert est.initialise(frames[0][0], cfg.initial_homography).ok
    assert bare.initialise(frames[0][0], cfg.initial_homography).ok
    return [(est.update(gray), est.drift_covariance, R, p,
             bare.update(gray, covariance=False), bare.drift_covariance)
            for gray, R, p in frames[1:]]


def test_over_a_flight_the_drift_grows_with_each_keyframe_and_the_covariance_bounds_the_error(
        flight_poses):
    """Every pose has a covariance (symmetric, positive definite); the drift part grows
    at every re-anchor and only then (a random walk); the position errors against the
    simulator's truth, divided by their predicted standard deviation, have an RMS
    between 0.1 and 1 per axis: the drift model is a bound (1 if it were exact; the start
    is exact here, its sigmas set near zero)."""
    assert all(r.ok for r, *_ in flight_poses)
    for r, *_ in flight_poses:
        assert np.allclose(r.covariance, r.covariance.T)
        assert np.linalg.eigvalsh(r.covariance).min() > 0
    drift = [np.trace(d[:3, :3]) for _, d, *_ in flight_poses]
    reanchored = [r.stats['reanchored'] for r, *_ in flight_poses]
    assert sum(reanchored) >= 5
    for a, b, grew in zip(drift, drift[1:], reanchored[1:]):
        assert (b > a) if grew else (b == a), (a, b, grew)
    z = np.array([(r.position - p) / np.sqrt(np.diag(r.covariance)[:3])
                  for r, _, _, p, *_ in flight_poses])
    rms = np.sqrt(np.mean(z ** 2, axis=0))
    print(f'position sd from {np.sqrt(drift[0] / 3):.4f} m (drift) to '
          f'{np.sqrt(drift[-1] / 3):.4f} m; error / sd RMS per axis {rms.round(2)}')
    assert np.all((rms > 0.1) & (rms < 1.0)), rms


def test_without_a_covariance_asked_the_poses_and_the_drift_are_the_same(flight_poses):
    """An estimator asked for no covariance (no one subscribes to onboard/pose_cov) gives
    the same poses without one, and its drift grows as the other's: the fit's covariance is
    still solved on the frames that re-anchor."""
    for r, drift, _, _, bare, bare_drift in flight_poses:
        assert bare.ok and bare.covariance is None
        assert np.array_equal(bare.position, r.position)
        assert np.array_equal(bare_drift, drift)
    assert sum(bare.stats['reanchored'] for *_, bare, _ in flight_poses) >= 5
