"""Triangulation (eq 24-25) and OpenCV's DLT against exact projections of known points."""
from itertools import combinations

import numpy as np
import pytest

from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file
from uav_vs.vision.triangulation import triangulate

CAMERAS = load_ground_config(read_params_file(default_config_path())).cameras
PINHOLE = [Camera(c.name, c.width, c.height, c.K, np.zeros(5), c.R, c.t) for c in CAMERAS]
SUBSETS = [list(s) for s in combinations(range(3), 2)] + [[0, 1, 2]]
SIGMA = 0.5       # px
N = 500


def flight_area_points(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-1.8, -1.8, 0.5], [1.8, 1.8, 2.0], (n, 3))


def pixels(cameras, X):
    return np.stack([c.project(X) for c in cameras])


def first_order_covariance(cameras, X, sigma):
    """sigma^2 (J^T J)^-1 with J the (2 n_cams x 3) Jacobian of the pixel projections
    (central differences of Camera.project, distortion included) at each point."""
    h = 1e-6
    J = np.empty((len(X), 2 * len(cameras), 3))
    for a in range(3):
        dX = np.zeros(3)
        dX[a] = h
        J[:, :, a] = np.concatenate(
            [(c.project(X + dX) - c.project(X - dX)) / (2 * h) for c in cameras], axis=1)
    return sigma ** 2 * np.linalg.inv(np.einsum('nri,nrj->nij', J, J))


@pytest.mark.parametrize('method', ['lsq', 'opencv'])
@pytest.mark.parametrize('cams', [CAMERAS, PINHOLE], ids=['distorted', 'pinhole'])
@pytest.mark.parametrize('subset', SUBSETS, ids=lambda s: ''.join(map(str, s)))
def test_noise_free_projections_triangulate_back(method, cams, subset):
    cameras = [cams[i] for i in subset]
    X = flight_area_points(200, seed=1)
    tri = triangulate(cameras, pixels(cameras, X), method)
    assert np.abs(tri.points - X).max() < 1e-9
    assert np.all(tri.n_views == len(subset)) and tri.used.all() and tri.inlier.all()
    assert tri.reproj_px.max() < 1e-6


@pytest.mark.parametrize('subset', [[0, 1], [0, 1, 2]], ids=['2 cams', '3 cams'])
def test_pixel_noise_stays_inside_first_order_bounds(subset):
    """0.5 px Gaussian noise on every centroid. First-order propagation through the
    projection gives each point's covariance S = sigma^2 (J^T J)^-1 (J: Jacobian of the
    stacked pixel projections). Then e^T S^-1 e is ~chi^2(3), so over N = 500 points:
    the RMS 3D error is within 15 % of sqrt(mean trace S) (~9 mm with 2 cameras, ~7 mm
    with 3 here), the mean of e^T S^-1 e is in [2.5, 3.6] (3 expected, sampling std 0.11;
    eq 25 minimises an algebraic error, not the pixel error, so it may sit slightly above),
    and no point exceeds the chi^2(3) 1e-6 quantile (30.7). Both methods obey this and
    agree to within a fraction of the predicted sigma."""
    cameras = [CAMERAS[i] for i in subset]
    X = flight_area_points(N, seed=2)
    S = first_order_covariance(cameras, X, SIGMA)
    rng = np.random.default_rng(4)
    noisy = pixels(cameras, X) + rng.normal(0, SIGMA, (len(cameras), N, 2))
    predicted_rms = np.sqrt(np.trace(S, axis1=1, axis2=2).mean())
    points = {}
    for method in ('lsq', 'opencv'):
        tri = triangulate(cameras, noisy, method, max_reproj_px=np.inf)
        e = tri.points - X
        rms = np.sqrt((e ** 2).sum(axis=1).mean())
        maha = np.einsum('ni,nij,nj->n', e, np.linalg.inv(S), e)
        assert abs(rms / predicted_rms - 1) < 0.15, (method, rms, predicted_rms)
        assert 2.5 < maha.mean() < 3.6, (method, maha.mean())
        assert maha.max() < 30.7, (method, maha.max())
        points[method] = tri.points
    sigma_pt = np.sqrt(np.trace(S, axis1=1, axis2=2))
    gap = np.linalg.norm(points['lsq'] - points['opencv'], axis=1) / sigma_pt
    assert gap.max() < (0.05 if len(subset) == 2 else 1.0)


@pytest.mark.parametrize('method', ['lsq', 'opencv'])
def test_biased_camera_is_left_out(method):
    """A centroid pulled 6 px down in one camera (e.g. the bottom of the sphere hidden by
    the body) is dropped; the remaining two exact views give the point back."""
    X = flight_area_points(50, seed=5)
    px = pixels(CAMERAS, X)
    bad = np.arange(50) % 3
    px[bad, np.arange(50), 1] -= 6.0
    tri = triangulate(CAMERAS, px, method, max_reproj_px=2.0)
    assert np.abs(tri.points - X).max() < 1e-6
    assert not tri.used[bad, np.arange(50)].any() and np.all(tri.n_views == 2)
    assert tri.inlier.all()
    kept = triangulate(CAMERAS, px, method, max_reproj_px=np.inf)   # no retry: biased
    assert np.linalg.norm(kept.points - X, axis=1).min() > 0.01 and kept.used.all()


def test_unseen_landmarks_and_single_views():
    X = flight_area_points(4, seed=6)
    px = pixels(CAMERAS, X)
    px[0, 1] = np.nan                 # landmark 1: two views left
    px[1:, 2] = np.nan                # landmark 2: one view, cannot be triangulated
    px[:, 3] = np.nan                 # landmark 3: unseen
    tri = triangulate(CAMERAS, px)
    assert np.abs(tri.points[:2] - X[:2]).max() < 1e-9
    assert np.isnan(tri.points[2:]).all() and np.isnan(tri.reproj_px[2:]).all()
    assert tri.n_views.tolist() == [3, 2, 0, 0]
    assert tri.inlier.tolist() == [True, True, False, False]


def test_bad_input_is_named():
    with pytest.raises(ValueError, match='pixels'):
        triangulate(CAMERAS, np.zeros((2, 4, 2)))
    with pytest.raises(ValueError, match='method'):
        triangulate(CAMERAS, np.zeros((3, 4, 2)), method='svd')
