"""Robust homography (section 2.3, Algorithm 1, eq 13-14) against exact synthetic truth."""
import math

import cv2
import numpy as np
import pytest

from uav_vs.vision.homography import (DEFAULT_METHOD, METHODS, _Normalised, _weighted_eq14,
                                      adaptive_trials, estimate_homography, refine_robust,
                                      solve_dlt, solve_inhomogeneous, transfer_error)

H_TRUE = np.array([[0.9, -0.2, 40.0],
                   [0.15, 1.1, -25.0],
                   [2e-4, -1e-4, 1.0]])
CORNERS = np.array([[0, 0], [640, 0], [640, 480], [0, 480]], float)


def project(H, pts):
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


def corner_error(H):
    return np.linalg.norm(project(H, CORNERS) - project(H_TRUE, CORNERS), axis=1).mean()


def matches(n=300, outlier_frac=0.4, noise=0.5, seed=0):
    """n matches over a 640x480 image: inliers follow H_TRUE plus noise, outliers are uniform."""
    rng = np.random.default_rng(seed)
    src = rng.uniform([0, 0], [640, 480], (n, 2))
    dst = project(H_TRUE, src) + rng.normal(0, noise, (n, 2))
    bad = rng.random(n) < outlier_frac
    dst[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    return src, dst, ~bad


def test_adaptive_trials_matches_hartley_zisserman_table():
    # H&Z 2nd ed., Table 4.3 (p = 0.99, s = 4) for eps = 5 .. 50 %.
    table = {0.05: 3, 0.10: 5, 0.20: 9, 0.25: 13, 0.30: 17, 0.40: 34, 0.50: 72}
    assert {e: adaptive_trials(0.99, e) for e in table} == table
    assert adaptive_trials(0.995, 0.6) == math.ceil(math.log(0.005) / math.log(1 - 0.4 ** 4))
    assert adaptive_trials(0.99, 0.0) == 1
    n = [adaptive_trials(0.995, e) for e in np.linspace(0.0, 0.9, 19)]
    assert all(a < b for a, b in zip(n, n[1:]))             # more outliers, more trials
    with pytest.raises(ValueError, match='confidence'):
        adaptive_trials(1.0, 0.5)


def test_inhomogeneous_and_dlt_agree_on_exact_data():
    src = np.array([[10, 20], [600, 40], [580, 450], [30, 470], [320, 240], [100, 300.]])
    dst = project(H_TRUE, src)
    for k in (4, 6):                  # minimal (Gaussian elimination), over-determined (pinv)
        Hi, Hd = solve_inhomogeneous(src[:k], dst[:k]), solve_dlt(src[:k], dst[:k])
        np.testing.assert_allclose(Hi, H_TRUE, rtol=0, atol=1e-9 * np.abs(H_TRUE).max())
        np.testing.assert_allclose(Hd, Hi, rtol=0, atol=1e-9 * np.abs(H_TRUE).max())
    assert transfer_error(H_TRUE, src, dst).max() < 1e-9


def test_transfer_error_is_symmetric():
    src = np.array([[100.0, 100.0]])
    dst = project(H_TRUE, src) + [3.0, 4.0]                 # 5 px off in the second image
    d_fwd = 5.0
    d_bwd = np.linalg.norm(project(np.linalg.inv(H_TRUE), dst) - src)
    assert transfer_error(H_TRUE, src, dst)[0] == pytest.approx(math.hypot(d_fwd, d_bwd))


@pytest.mark.parametrize('method', METHODS)
@pytest.mark.parametrize('outlier_frac', [0.3, 0.5])
def test_recovers_exact_homography_through_outliers(method, outlier_frac):
    src, dst, good = matches(outlier_frac=outlier_frac)
    r = estimate_homography(src, dst, method, rng=1)
    assert r.ok, r.reason
    assert abs(r.H[2, 2] - 1) < 1e-12
    assert corner_error(r.H) < 1.0                          # px, image corners, 0.5 px noise
    # Inliers: at most a couple of outliers that fell within the threshold by chance,
    # and nearly all true ones found.
    assert (r.inliers & ~good).sum() <= 2
    assert (r.inliers & good).sum() >= 0.95 * good.sum()
    if method in ('ransac', 'lmeds'):
        assert 0.5 < r.rms_px < 1.5                        # symmetric error of N(0, 0.5) noise


def test_trial_count_follows_the_formula_and_stops_early_on_clean_data():
    src, dst, _ = matches(outlier_frac=0.0, noise=0.0)
    clean = estimate_homography(src, dst, 'ransac', rng=0)
    assert clean.ok and clean.trials <= 16                  # first batch, N = 1 at eps = 0
    src, dst, good = matches(n=400, outlier_frac=0.6, noise=0.0, seed=3)
    r = estimate_homography(src, dst, 'ransac', rng=0, confidence=0.995, max_trials=5000)
    assert r.ok, r.reason
    needed = adaptive_trials(0.995, 1 - r.inliers.sum() / len(src))
    assert needed > 64                                      # really adaptive, not one batch
    assert needed <= r.trials < needed + 64                 # stops once N trials are drawn
    assert (r.inliers == good).all()


def test_refinement_converges_to_the_truth_from_any_start():
    src, dst, _ = matches(outlier_frac=0.0, noise=0.0)
    start = H_TRUE @ np.array([[1.01, 0.02, 3.0], [-0.01, 0.99, -2.0], [1e-5, 2e-5, 1.0]])
    assert corner_error(start) > 5.0
    H = refine_robust(start, src, dst, 3.0, tol_px=1e-9)
    assert corner_error(H) < 1e-6                           # exact data: the exact H
    src, dst, _ = matches(outlier_frac=0.4, noise=0.5, seed=2)
    a = refine_robust(start, src, dst, 3.0)
    b = refine_robust(H_TRUE, src, dst, 3.0)
    assert corner_error(a) < 0.5                            # 40 % outliers take no hold
    np.testing.assert_allclose(project(a, CORNERS), project(b, CORNERS), atol=0.02)


def test_weighted_fit_is_eq14_on_the_weighted_matches():
    # Eq 14 (h33 = 1) on the matches with weight 1, solved by SVD least squares, is what
    # the weighted normal equations give; scaling the weights changes nothing.
    src, dst, good = matches(n=60, outlier_frac=0.3, noise=0.5, seed=4)
    data = _Normalised(src, dst)
    rows = np.repeat(good, 2)
    h = np.linalg.lstsq(data.A[rows, :8], -data.A[rows, 8], rcond=None)[0]
    for scale in (1.0, 3.0):
        Hn = _weighted_eq14(data.A, scale * good)
        np.testing.assert_allclose(Hn.ravel(), np.append(h, 1.0), rtol=0, atol=1e-9)
    # On exact data every positive weighting gives the exact H.
    dst = project(H_TRUE, src)
    data = _Normalised(src, dst)
    H = data.to_input(_weighted_eq14(data.A, np.random.default_rng(0).uniform(0.1, 2, 60)))
    np.testing.assert_allclose(project(H, CORNERS), project(H_TRUE, CORNERS), atol=1e-6)


def test_refinement_gives_outliers_no_hold():
    # Starting from the truth, the Cauchy-weighted refit stays where the true inliers put
    # it: within the noise of their own least-squares fit, far from the fit on all matches.
    src, dst, good = matches(n=400, outlier_frac=0.4, noise=0.5, seed=5)
    H = refine_robust(H_TRUE, src, dst, 3.0)
    ls_inliers = solve_inhomogeneous(src[good], dst[good])
    assert corner_error(H) < 0.5
    assert np.abs(project(H, CORNERS) - project(ls_inliers, CORNERS)).max() < 0.5
    assert corner_error(solve_inhomogeneous(src, dst)) > 20.0


def test_estimate_does_not_depend_on_the_sample_that_won():
    # The refinement converges to the M-estimate of all matches: another order of the
    # same matches and another seed give the same H, though RANSAC draws other samples.
    src, dst, _ = matches(n=300, outlier_frac=0.4, noise=1.0, seed=6)
    ref = estimate_homography(src, dst, 'ransac', rng=0)
    for k in range(1, 6):
        p = np.random.default_rng(k).permutation(len(src))
        r = estimate_homography(src[p], dst[p], 'ransac', rng=k)
        assert r.ok and (r.inliers == ref.inliers[p]).all()
        assert np.abs(project(r.H, CORNERS) - project(ref.H, CORNERS)).max() < 0.01


def test_without_refinement_is_algorithm_1():
    src, dst, good = matches(outlier_frac=0.4)
    r = estimate_homography(src, dst, 'ransac', rng=0, refine=False)
    assert r.ok and corner_error(r.H) < 1.0
    assert (r.inliers & ~good).sum() <= 2 and (r.inliers & good).sum() >= 0.95 * good.sum()


def test_too_few_points_is_a_failure():
    src, dst, _ = matches(n=3, outlier_frac=0.0)
    for method in METHODS:
        r = estimate_homography(src, dst, method)
        assert not r.ok and r.H is None and 'fewer than' in r.reason


def test_collinear_points_are_a_failure():
    t = np.linspace(0, 1, 50)[:, None]
    src = np.hstack([40 + 500 * t, 30 + 300 * t])
    dst = project(H_TRUE, src)
    for method in METHODS:
        r = estimate_homography(src, dst, method, rng=0)
        assert not r.ok and r.H is None and 'collinear' in r.reason, (method, r.reason)


def test_all_outliers_is_a_failure():
    rng = np.random.default_rng(5)
    src, dst = rng.uniform(0, 640, (200, 2)), rng.uniform(0, 640, (200, 2))
    for method in METHODS:
        r = estimate_homography(src, dst, method, rng=0)
        assert not r.ok and r.H is None and 'fewer than' in r.reason, (method, r.reason)


def test_mirror_homography_is_a_failure():
    src, dst, _ = matches(outlier_frac=0.0)
    dst[:, 0] = 640 - dst[:, 0]                             # seen from behind: orientation flips
    for method in METHODS:
        r = estimate_homography(src, dst, method, rng=0)
        assert not r.ok and r.H is None, (method, r.reason)


def test_bad_input_raises_one_line_errors():
    src, dst, _ = matches(n=10)
    with pytest.raises(ValueError, match='unknown homography method'):
        estimate_homography(src, dst, 'magic')
    with pytest.raises(ValueError, match='matching'):
        estimate_homography(src, dst[:5])
    dst[0, 0] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        estimate_homography(src, dst)


def test_plane_coordinates_in_metres():
    # A 0.2 m square tag seen by a camera: src on the tag in metres, dst in pixels.
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    c, s = math.cos(0.4), math.sin(0.4)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    t = np.array([-0.05, 0.02, 0.9])
    H_tag = K @ np.c_[R[:, :2], t]
    H_tag /= H_tag[2, 2]
    rng = np.random.default_rng(7)
    src = rng.uniform(0.0, 0.2, (120, 2))
    dst = project(H_tag, src) + rng.normal(0, 0.3, (120, 2))
    dst[:30] = rng.uniform([0, 0], [640, 480], (30, 2))    # outliers
    corners_m = np.array([[0, 0], [0.2, 0], [0.2, 0.2], [0, 0.2]])
    for method in ('ransac', 'lmeds', DEFAULT_METHOD):
        r = estimate_homography(src, dst, method, rng=0)
        assert r.ok, (method, r.reason)
        err = np.linalg.norm(project(r.H, corners_m) - project(H_tag, corners_m), axis=1)
        assert err.max() < 1.0, method                     # px, 0.3 px noise
        assert r.inliers[30:].mean() > 0.95 and r.inliers[:30].sum() <= 1


def test_plane_coordinates_in_metres_on_both_sides():
    # Plane to plane in metres: a 0.2 m tag to its perspective image 1 m away.
    Z = np.array([[0.9, -0.2, 0.04], [0.15, 1.1, -0.02], [0.8, -0.5, 1.0]])
    rng = np.random.default_rng(8)
    src = rng.uniform(0.0, 0.2, (100, 2))
    dst = project(Z, src) + rng.normal(0, 2e-4, (100, 2))
    corners_m = np.array([[0, 0], [0.2, 0], [0.2, 0.2], [0, 0.2]])
    for method in ('ransac', DEFAULT_METHOD):
        r = estimate_homography(src, dst, method, rng=0, threshold_px=2e-3)
        assert r.ok, (method, r.reason)
        assert np.abs(project(r.H, corners_m) - project(Z, corners_m)).max() < 1e-3, method


def test_mirror_homography_is_accepted_when_asked():
    # Corners listed the other way round: a valid map that reverses orientation.
    M = np.diag([-1.0, 1.0, 1.0]) @ H_TRUE
    M[0, 2] += 640.0 * M[2, 2]                              # x' -> 640 - x'
    M /= M[2, 2]
    src, _, _ = matches(outlier_frac=0.0)
    rng = np.random.default_rng(9)
    dst = project(M, src) + rng.normal(0, 0.5, src.shape)
    bad = rng.random(len(src)) < 0.3
    dst[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    for method in ('ransac', 'lmeds'):
        assert not estimate_homography(src, dst, method, rng=0).ok       # refused by default
        r = estimate_homography(src, dst, method, rng=0, mirror=True)
        assert r.ok, (method, r.reason)
        err = np.linalg.norm(project(r.H, CORNERS) - project(M, CORNERS), axis=1).mean()
        assert err < 1.0 and np.linalg.det(r.H) < 0
        assert (r.inliers & bad).sum() <= 2 and r.inliers[~bad].mean() > 0.95



def test_default_is_opencv_ransac_with_the_project_checks():
    """The default estimator is cv2.findHomography(RANSAC) itself, plus the failure checks."""
    src, dst, _ = matches(outlier_frac=0.3)
    r = estimate_homography(src, dst)
    H, mask = cv2.findHomography(src, dst, cv2.RANSAC, 3.0, maxIters=2000, confidence=0.995)
    assert DEFAULT_METHOD == 'opencv_ransac' and r.ok
    np.testing.assert_allclose(r.H, H / H[2, 2], rtol=1e-9, atol=1e-12)
    assert (r.inliers == mask.ravel().astype(bool)).all()
