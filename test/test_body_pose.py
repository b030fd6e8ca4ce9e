"""Vehicle pose from landmarks (eq 26 and the rigid SVD option) against exact poses."""
import numpy as np
import pytest

from uav_vs.vision.body_pose import quaternion_xyzw, solve_pose
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file
from uav_vs.vision.triangulation import triangulate

CONFIG = load_ground_config(read_params_file(default_config_path()))
LAYOUT = CONFIG.layout
# a second layout, not centred on base_link and not planar, so t is not the landmark mean
SKEWED = np.array([[0.35, 0.05, 0.02], [-0.1, 0.3, -0.04], [-0.28, -0.02, 0.06],
                   [0.05, -0.33, 0.0]])


def rot(yaw=0.0, pitch=0.0, roll=0.0):
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    Rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return Rz @ Ry @ Rx


def wrap(a):
    return np.angle(np.exp(1j * np.asarray(a)))


YAWS = [0.0, 0.3, -1.2, 2.9, np.pi, -np.pi + 1e-9, np.pi - 1e-9, -3.1]


@pytest.mark.parametrize('layout', [LAYOUT, SKEWED], ids=['config', 'skewed'])
@pytest.mark.parametrize('yaw', YAWS)
@pytest.mark.parametrize('method', ['yaw', 'rigid'])
def test_noise_free_landmarks_give_the_exact_pose(layout, yaw, method):
    t = np.array([1.3, -0.7, 1.45])
    R = rot(yaw)
    pose = solve_pose(layout, layout @ R.T + t, method)
    assert pose.ok and pose.reason == '' and pose.n_used == 4 and pose.method == method
    assert abs(wrap(pose.yaw - yaw)) < 1e-12
    np.testing.assert_allclose(pose.position, t, atol=1e-12)
    np.testing.assert_allclose(pose.R, R, atol=1e-12)
    assert pose.residual_rms < 1e-12 and np.all(pose.residuals < 1e-12)


@pytest.mark.parametrize('drop', [[0, 1], [0, 2], [1, 3], [2, 3]])
def test_two_landmarks_are_enough(drop):
    t, yaw = np.array([-0.4, 0.9, 0.8]), -2.4
    world = SKEWED @ rot(yaw).T + t
    world[drop] = np.nan
    pose = solve_pose(SKEWED, world)
    assert pose.ok and pose.n_used == 2
    assert abs(wrap(pose.yaw - yaw)) < 1e-12
    np.testing.assert_allclose(pose.position, t, atol=1e-12)
    assert np.isnan(pose.residuals[drop]).all()


@pytest.mark.parametrize('n_seen', [0, 1])
def test_fewer_than_two_landmarks_give_no_pose(n_seen):
    world = LAYOUT + [0.0, 0.0, 1.0]
    world[n_seen:] = np.nan
    pose = solve_pose(LAYOUT, world)
    assert not pose.ok and pose.n_used == n_seen
    assert 'need >= 2' in pose.reason
    assert np.isnan(pose.position).all() and np.isnan(pose.yaw)


def test_landmarks_stacked_vertically_leave_yaw_undetermined():
    layout = np.array([[0.1, 0.2, 0.0], [0.1, 0.2, 0.3]])
    pose = solve_pose(layout, layout + 1.0)
    assert not pose.ok and 'yaw is undetermined' in pose.reason


def test_rigid_alignment_recovers_pitch_and_roll():
    rng = np.random.default_rng(0)
    for _ in range(50):
        yaw, pitch, roll = rng.uniform(-np.pi, np.pi), *rng.uniform(-0.5, 0.5, 2)
        R, t = rot(yaw, pitch, roll), rng.uniform(-2, 2, 3)
        world = SKEWED @ R.T + t
        rigid = solve_pose(SKEWED, world, 'rigid')
        np.testing.assert_allclose(rigid.R, R, atol=1e-12)
        np.testing.assert_allclose(rigid.position, t, atol=1e-12)
        assert abs(wrap(rigid.yaw - yaw)) < 1e-12
        yaw_only = solve_pose(SKEWED, world, 'yaw')       # eq 26 assumes level flight
        assert yaw_only.residual_rms > 1e-3


def test_rigid_with_two_landmarks_falls_back_to_eq26():
    world = LAYOUT @ rot(0.7).T + [0.2, 0.1, 1.0]
    world[2:] = np.nan
    pose = solve_pose(LAYOUT, world, 'rigid')
    assert pose.ok and 'eq 26' in pose.reason and abs(pose.yaw - 0.7) < 1e-12
    assert pose.method == 'yaw'


def test_quaternion_matches_rotation():
    rng = np.random.default_rng(1)
    for _ in range(100):
        R = rot(*rng.uniform(-np.pi, np.pi, 3))
        x, y, z, w = quaternion_xyzw(R)
        Rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                       [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                       [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(Rq, R, atol=1e-12)
        assert w >= 0


def test_noisy_landmarks_stay_inside_derived_bounds():
    """Isotropic Gaussian noise sigma on each of n landmark positions (about what
    triangulation gives with 0.5 px, see test_triangulation). Linearising eq 26 about the
    truth, with the layout centred (sum x_h = sum y_h = 0): t is the mean of
    (x_w - R x_h), so each position axis has std sigma / sqrt(n); the yaw is the
    least-squares rotation of the tangential components, std sigma / sqrt(sum r_i^2) with
    r_i = |(x_h, y_h)|. Over 2000 trials each RMS is within 10 % of that (the sampling
    std of an RMS over 2000 samples is ~1.6 %)."""
    sigma, trials = 0.005, 2000
    rng = np.random.default_rng(2)
    n = len(LAYOUT)
    r2 = (LAYOUT[:, :2] ** 2).sum()
    err_t, err_yaw = [], []
    for _ in range(trials):
        yaw, t = rng.uniform(-np.pi, np.pi), rng.uniform(-2, 2, 3)
        world = LAYOUT @ rot(yaw).T + t + rng.normal(0, sigma, (n, 3))
        pose = solve_pose(LAYOUT, world)
        err_t.append(pose.position - t)
        err_yaw.append(wrap(pose.yaw - yaw))
    rms_axis = np.sqrt(np.mean(np.square(err_t), axis=0))
    np.testing.assert_allclose(rms_axis, sigma / np.sqrt(n), rtol=0.1)
    assert abs(np.sqrt(np.mean(np.square(err_yaw))) / (sigma / np.sqrt(r2)) - 1) < 0.1


def _pixels(pose: np.ndarray) -> np.ndarray:
    """(n_cams, n_landmarks, 2) true pixels of the layout at pose (x, y, z, yaw), level."""
    world = LAYOUT @ rot(pose[3]).T + pose[:3]
    return np.stack([c.project(world) for c in CONFIG.cameras])


def _poses_from_pixels(pixels: np.ndarray) -> np.ndarray:
    """(T, 4) x, y, z, yaw from (n_cams, T * n_landmarks, 2): eq 24-25 then eq 26."""
    points = triangulate(CONFIG.cameras, pixels, max_reproj_px=np.inf).points
    poses = [solve_pose(LAYOUT, w) for w in points.reshape(-1, len(LAYOUT), 3)]
    return np.array([[*pose.position, pose.yaw] for pose in poses])


def _stack(batch: np.ndarray) -> np.ndarray:
    """(T, n_cams, n, 2) pixel sets -> (n_cams, T * n, 2), one triangulate call."""
    return np.concatenate(list(batch), axis=1)


def _pose_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    error = estimate - truth
    error[..., 3] = wrap(error[..., 3])
    return error


@pytest.mark.parametrize('pose', [[0.0, 0.0, 1.2, 0.4], [1.2, -0.8, 1.6, -2.0],
                                  [-1.0, 1.1, 0.8, 2.8]], ids=['centre', 'east', 'low-west'])
def test_pixel_noise_through_triangulation_and_eq26_stays_inside_derived_bounds(pose):
    """The configured landmarks, level at `pose`, projected through the three configured
    cameras (distortion included), 0.5 px Gaussian noise on every centroid, triangulated
    (eq 24-25) and solved for x, y, z, yaw (eq 26), 400 trials.

    Bound: to first order the pose error is J n, with J (4 x 24) the Jacobian of
    pixels -> pose (central differences through triangulate + solve_pose) and n the pixel
    noise, so each of x, y, z, yaw has std s = 0.5 px * sqrt(diag(J J^T)): ~2-2.5 mm per
    axis and ~0.43 deg of yaw at these poses. Asserted: J G = I (G: Jacobian of the
    projection, pose -> pixels: the pipeline inverts the camera model); s is no smaller
    than the Cramer-Rao bound 0.5 px * sqrt(diag((G^T G)^-1)) of any unbiased estimator
    from these pixels (Gauss-Markov, since J G = I) and at most 25 % above it; the
    empirical RMS of each component is in [0.85, 1.15] s (its sampling std over 400
    trials is ~3.5 %), and no error exceeds 5 s."""
    pose, sigma, trials, h = np.array(pose), 0.5, 400, 1e-3
    truth_px = _pixels(pose)
    m = truth_px.size
    steps = h * np.eye(m).reshape(m, *truth_px.shape)
    ends = _poses_from_pixels(_stack(np.concatenate([truth_px + steps, truth_px - steps])))
    J = (_pose_error(ends[:m], ends[m:]) / (2 * h)).T
    G = np.empty((m, 4))
    for a in range(4):
        d = np.zeros(4)
        d[a] = 1e-6
        G[:, a] = ((_pixels(pose + d) - _pixels(pose - d)) / 2e-6).ravel()
    np.testing.assert_allclose(J @ G, np.eye(4), atol=1e-6)
    predicted = sigma * np.sqrt(np.diag(J @ J.T))
    cramer_rao = sigma * np.sqrt(np.diag(np.linalg.inv(G.T @ G)))
    assert np.all(predicted >= 0.999 * cramer_rao) and np.all(predicted <= 1.25 * cramer_rao)
    assert np.all(predicted[:3] < 0.003) and predicted[3] < np.radians(0.5)

    rng = np.random.default_rng(7)
    noisy = truth_px + rng.normal(0, sigma, (trials, *truth_px.shape))
    error = _pose_error(_poses_from_pixels(_stack(noisy)), pose)
    rms = np.sqrt(np.mean(error ** 2, axis=0))
    assert np.all((0.85 * predicted <= rms) & (rms <= 1.15 * predicted)), rms / predicted
    assert np.all(np.abs(error) <= 5 * predicted)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match='layout and world_points'):
        solve_pose(LAYOUT, LAYOUT[:3])
    with pytest.raises(ValueError, match='method'):
        solve_pose(LAYOUT, LAYOUT, 'affine')
