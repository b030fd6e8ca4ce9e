"""Robust homography on real images with true homographies (VGG Oxford graf, boat,
and real images warped by known homographies).

Metric (data README): mean transfer error of img1's four corners, estimated H vs the
true H1toNp. Matches are the baseline's: SIFT, exact nearest neighbours, ratio 0.75;
only the estimator differs: the project's default (cv2 RANSAC) and Algorithm 1.
"""
from functools import lru_cache

import cv2
import numpy as np
import pytest

from uav_vs.vision.features import detect_and_describe, match
from uav_vs.vision.homography import DEFAULT_METHOD, estimate_homography

ESTIMATORS = [DEFAULT_METHOD, 'ransac']

# OpenCV 5.0 baseline from the data README (SIFT, ratio 0.75, findHomography RANSAC 3 px);
# None: the baseline reports failure and so must we.
BASELINE = {'graf': [0.90, 4.89, 2.36, None, None],
            'boat': [0.29, 0.22, 1.08, 1.62, 9.76]}
CASES = [(seq, n) for seq in BASELINE for n in range(2, 7)]


@lru_cache(maxsize=None)
def features(folder: str, name: str):
    img = cv2.imread(folder + '/' + name, cv2.IMREAD_GRAYSCALE)
    assert img is not None, f'cannot read {folder}/{name}'
    return img.shape, *detect_and_describe(img, 'sift')


def corners(shape):
    h, w = shape
    return np.array([[0, 0], [w, 0], [w, h], [0, h]], float)


def project(H, pts):
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


@pytest.mark.parametrize('method', ESTIMATORS)
@pytest.mark.parametrize('seq,n', CASES)
def test_corner_error_no_worse_than_opencv(shared_data, seq, n, method):
    folder = str(shared_data / 'oxford' / seq)
    ext = 'ppm' if seq == 'graf' else 'pgm'
    shape, xy1, d1 = features(folder, f'img1.{ext}')
    _, xyn, dn = features(folder, f'img{n}.{ext}')
    i1, i2 = match(d1, dn, 'sift', 0.75, matcher=cv2.BFMatcher(cv2.NORM_L2))
    r = estimate_homography(xy1[i1], xyn[i2], method, rng=0)
    baseline = BASELINE[seq][n - 2]
    if baseline is None:
        assert not r.ok and r.H is None, f'{seq} 1->{n} must fail, got {r.inliers.sum()} inliers'
        return
    assert r.ok, r.reason
    H_true = np.loadtxt(f'{folder}/H1to{n}p')
    c = corners(shape)
    err = np.linalg.norm(project(r.H, c) - project(H_true, c), axis=1).mean()
    # The README gives the baseline cut to 0.01 px (OpenCV RANSAC itself measures 2.367 on
    # graf 1->4): no worse means below the next hundredth.
    assert err < baseline + 0.01, f'{seq} 1->{n}: {err:.3f} px vs baseline {baseline}'


WARPED = ['opencv/aero1.jpg', 'opencv/box_in_scene.png', 'oxford/boat/img1.pgm']


@pytest.mark.parametrize('method', ESTIMATORS)
@pytest.mark.parametrize('name', WARPED)
@pytest.mark.parametrize('seed', [0, 1])
def test_known_warp_of_a_real_image(shared_data, name, seed, method):
    # A random homography (any rotation, scale 0.6-1.2, corners moved by up to 15 %)
    # applied to a real image with sensor noise: the truth is the H that warped it.
    img = cv2.imread(str(shared_data / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f'cannot read {name}'
    rng = np.random.default_rng(seed)
    c = corners(img.shape)
    a, s = rng.uniform(-np.pi, np.pi), rng.uniform(0.6, 1.2)
    R = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    q = (c - c[2] / 2 + rng.uniform(-0.15, 0.15, (4, 2)) * c[2]) @ R.T
    q -= q.min(0)
    H_true = cv2.getPerspectiveTransform(c.astype(np.float32), q.astype(np.float32))
    warped = cv2.warpPerspective(img, H_true, tuple(int(v) + 1 for v in q.max(0)))
    warped = np.clip(warped + rng.normal(0, 2, warped.shape), 0, 255).astype(np.uint8)
    xy1, d1 = detect_and_describe(img, 'sift', 1000)
    xy2, d2 = detect_and_describe(warped, 'sift', 1000)
    i1, i2 = match(d1, d2, 'sift', 0.75, matcher=cv2.BFMatcher(cv2.NORM_L2))
    r = estimate_homography(xy1[i1], xy2[i2], method, rng=0)
    assert r.ok, r.reason
    err = np.linalg.norm(project(r.H, c) - project(H_true, c), axis=1).mean()
    assert err < 1.5, f'{name}, seed {seed}: {err:.3f} px'   # SIFT keypoints: ~0.5 px
    truth = np.linalg.norm(project(H_true, xy1[i1]) - xy2[i2], axis=1) < 2.0
    assert (r.inliers & ~truth).sum() <= 0.02 * len(i1)     # no gross outlier kept
