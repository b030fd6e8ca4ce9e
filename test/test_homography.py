"""Robust homography (section 2.3, Algorithm 1, eq 13-14) against exact synthetic truth."""
import math

import numpy as np
import pytest

from uav_vs.vision.homography import (METHODS, _linearise, adaptive_trials,
                                      estimate_homography, refine_robust, solve_dlt,
                                      solve_inhomogeneous, transfer_error)

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
    clean = estimate_homography(src, dst, rng=0)
    assert clean.ok and clean.trials <= 8                   # first batch, N = 1 at eps = 0
    src, dst, good = matches(n=400, outlier_frac=0.6, noise=0.0, seed=3)
    r = estimate_homography(src, dst, rng=0, confidence=0.995, max_trials=5000)
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


def test_linearisation_matches_finite_differences():
    Hn = np.array([[0.9, -0.2, 0.1], [0.15, 1.1, -0.05], [0.2, -0.3, 1.0]])
    rng = np.random.default_rng(6)
    src, dst = rng.normal(0, 1, (6, 2)), rng.normal(0, 1, (6, 2))
    ks, kd = 0.01, 0.02                             # normalisation scales, px -> normalised
    r, J, z = _linearise(Hn, src, dst, ks, kd)
    q = np.c_[src, np.ones(6)] @ Hn.T
    p = np.c_[dst, np.ones(6)] @ np.linalg.inv(Hn).T
    np.testing.assert_allclose(r, np.c_[(dst - q[:, :2] / q[:, 2:]) / kd,
                                        (src - p[:, :2] / p[:, 2:]) / ks], atol=1e-12)
    for k in range(8):
        step = np.zeros(9)
        step[k] = 1e-7
        r_k = _linearise(Hn + step.reshape(3, 3), src, dst, ks, kd)[0]
        np.testing.assert_allclose((r_k - r) / 1e-7, J[:, :, k], rtol=1e-5, atol=1e-3)
    for x, z_i in zip(src, z):                      # 8 / (4 + |J|^2 + |J^-1|^2), J in px
        w = Hn[2] @ [*x, 1]
        u = Hn[:2] @ [*x, 1] / w
        Jpx = (Hn[:2, :2] - np.outer(u, Hn[2, :2])) / w * ks / kd
        expected = 8 / (4 + (Jpx ** 2).sum() + (np.linalg.inv(Jpx) ** 2).sum())
        assert z_i == pytest.approx(expected, rel=1e-12)


def test_refinement_treats_both_images_alike():
    # Swapping the images must give the inverse H: the cost is symmetric in them.
    Z = np.array([[0.45, -0.12, 300.0], [0.1, 0.5, 150.0], [1e-4, -2e-4, 1.0]])
    rng = np.random.default_rng(4)
    src = rng.uniform([0, 0], [640, 480], (300, 2))
    dst = project(Z, src) + rng.normal(0, 0.3, (300, 2))
    dst[:60] = rng.uniform([250, 120], [560, 400], (60, 2))   # outliers
    fwd = refine_robust(Z, src, dst, 3.0, tol_px=1e-6)
    bwd = np.linalg.inv(refine_robust(np.linalg.inv(Z), dst, src, 3.0, tol_px=1e-6))
    np.testing.assert_allclose(project(fwd, CORNERS), project(bwd, CORNERS), atol=1e-3)


def test_without_refinement_is_algorithm_1():
    src, dst, good = matches(outlier_frac=0.4)
    r = estimate_homography(src, dst, rng=0, refine=False)
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
