"""Robust homography estimators and feature matchers side by side (suite 'onboard').

- onboard/homography_<method>: every estimator on the same real SIFT matches (ratio
  0.75, exact nearest neighbours, as the data README's baseline): Oxford graf/boat
  1->2..1->6 (corner transfer error against the true H, 'fail' where the estimate is
  reported as a failure) and OpenCV's box -> box_in_scene (no true H: inliers and
  their symmetric transfer RMS). As every estimator is randomised (cv2's by a fixed
  seed over the match order), also the median error over ORDERS orders of the same
  matches. Time per call next to cv2 RANSAC on the same matches, the two called in
  turn; the ratio per pair.
- onboard/homography_synthetic_<method>: the same on 100 random homographies applied
  to real images (aero1, aero3, box_in_scene, graf and boat img1; SIFT matches to the
  warped copy, corner error against the known H): median, 90th percentile, worst and
  mean corner error beside cv2 RANSAC's, failures, the pairs where the estimator is
  worse (better) than cv2 RANSAC by more than WORSE_PX, and the mean of the difference.
- onboard/features_<kind>: detection + description of two 640x480 frames and FLANN
  ratio-test matching between them (aero1.jpg and a rotated, scaled copy).
"""
import time
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from bench.common import report, timeit
from uav_vs.datasets import shared_data_dir
from uav_vs.vision.features import detect_and_describe, make_matcher, match
from uav_vs.vision.homography import METHODS, HomographyResult, estimate_homography

SUITE = 'onboard'
ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'
SYNTHETIC = ('opencv/aero1.jpg', 'opencv/aero3.jpg', 'opencv/box_in_scene.png',
             'oxford/graf/img1.ppm', 'oxford/boat/img1.pgm')
WARPS = 100                    # synthetic pairs, 20 per image
WORSE_PX = 0.01                # corner error more than this above cv2 RANSAC's is worse
ORDERS = 10                    # match orders (and seeds) per real pair for the error spread
Pair = tuple[str, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]


def _project(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


def _corners(gray: np.ndarray) -> np.ndarray:
    h, w = gray.shape
    return np.array([[0, 0], [w, 0], [w, h], [0, h]], float)


def _sift_matches(f1: tuple, f2: tuple) -> tuple[np.ndarray, np.ndarray]:
    i1, i2 = match(f1[1], f2[1], 'sift', 0.75, matcher=cv2.BFMatcher(cv2.NORM_L2))
    return f1[0][i1], f2[0][i2]


@lru_cache(maxsize=None)
def real_pairs() -> list[Pair]:
    """(pair name, src, dst, true H or None, src image corners): Oxford 1->2..6, box."""
    root = shared_data_dir()
    if root is None:
        return []
    pairs = []
    for seq, ext in (('graf', 'ppm'), ('boat', 'pgm')):
        imgs = [cv2.imread(str(root / 'oxford' / seq / f'img{k}.{ext}'), cv2.IMREAD_GRAYSCALE)
                for k in range(1, 7)]
        feats = [detect_and_describe(img, 'sift') for img in imgs]
        for k in range(2, 7):
            H = np.loadtxt(root / 'oxford' / seq / f'H1to{k}p')
            pairs.append((f'{seq}1-{k}', *_sift_matches(feats[0], feats[k - 1]), H,
                          _corners(imgs[0])))
    box, scene = (cv2.imread(str(root / 'opencv' / f), cv2.IMREAD_GRAYSCALE)
                  for f in ('box.png', 'box_in_scene.png'))
    pairs.append(('box', *_sift_matches(detect_and_describe(box, 'sift'),
                                        detect_and_describe(scene, 'sift')), None, _corners(box)))
    return pairs


def random_homography(rng: np.random.Generator, w: int, h: int
                      ) -> tuple[np.ndarray, tuple[int, int]]:
    """A random H of a w x h image (any rotation, scale 0.6-1.2, corners moved by up to
    15 % of the size) and the size of the canvas holding the warped image."""
    c = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    a, s = rng.uniform(-np.pi, np.pi), rng.uniform(0.6, 1.2)
    R = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    q = (c - [w / 2, h / 2] + rng.uniform(-0.15, 0.15, (4, 2)) * [w, h]) @ R.T
    q -= q.min(0)
    H = cv2.getPerspectiveTransform(c.astype(np.float32), q.astype(np.float32))
    return H, (int(q[:, 0].max()) + 1, int(q[:, 1].max()) + 1)


@lru_cache(maxsize=None)
def synthetic_pairs(count: int = WARPS, seed: int = 2) -> list[Pair]:
    """Real images under random homographies, with sensor noise; SIFT matches."""
    root = shared_data_dir()
    if root is None:
        return []
    rng = np.random.default_rng(seed)
    imgs = [cv2.imread(str(root / f), cv2.IMREAD_GRAYSCALE) for f in SYNTHETIC]
    feats = [detect_and_describe(img, 'sift', 1000) for img in imgs]
    pairs = []
    for k in range(count):
        j = k % len(imgs)
        H, size = random_homography(rng, imgs[j].shape[1], imgs[j].shape[0])
        warped = cv2.warpPerspective(imgs[j], H, size)
        warped = np.clip(warped + rng.normal(0, 2, warped.shape), 0, 255).astype(np.uint8)
        pairs.append((f'{Path(SYNTHETIC[j].replace("/img1", "")).stem}-{k}',
                      *_sift_matches(feats[j], detect_and_describe(warped, 'sift', 1000)),
                      H, _corners(imgs[j])))
    return pairs


def accuracy(r: HomographyResult, H_true: np.ndarray | None, corners: np.ndarray) -> float | str:
    """Corner error, px, against the true H; without one, 'inliers/RMS px'."""
    if not r.ok:
        return 'fail'
    if H_true is None:
        return f'{int(r.inliers.sum())}/{r.rms_px:.2f}'
    return round(float(np.linalg.norm(_project(r.H, corners) - _project(H_true, corners),
                                      axis=1).mean()), 3)


def _timed(method: str, src: np.ndarray, dst: np.ndarray) -> tuple[HomographyResult, float]:
    """The estimate and its time, ms."""
    t0 = time.perf_counter()
    r = estimate_homography(src, dst, method, rng=0)
    return r, (time.perf_counter() - t0) * 1e3


def run_pairs(method: str, pairs: list[Pair], repeat: int
              ) -> tuple[list, np.ndarray, np.ndarray]:
    """Accuracy per pair and times (pairs, repeat) of method and cv2 RANSAC, called in turn."""
    acc, ms, ref = [], np.empty((len(pairs), repeat)), np.empty((len(pairs), repeat))
    for i, (_, src, dst, H_true, corners) in enumerate(pairs):
        for k in range(repeat):
            r, ms[i, k] = _timed(method, src, dst)
            rr, ref[i, k] = _timed('opencv_ransac', src, dst)
        acc.append((accuracy(r, H_true, corners), accuracy(rr, H_true, corners)))
    return acc, ms, ref


def over_orders(method: str, pair: Pair, orders: int = ORDERS) -> float | str:
    """Median corner error over `orders` random orders of the same matches (order k and
    rng=k): one order is one draw of a randomised estimator, cv2's fixed seed included."""
    _, src, dst, H_true, corners = pair
    err = []
    for k in range(orders):
        p = np.random.default_rng(k).permutation(len(src))
        a = accuracy(estimate_homography(src[p], dst[p], method, rng=k), H_true, corners)
        err.append(np.inf if a == 'fail' else a)
    med = float(np.median(err))
    return round(med, 3) if np.isfinite(med) else 'fail'


def real_case(method: str, pairs: list[Pair], repeat: int) -> tuple:
    """Case on the real pairs: accuracy, cv2 RANSAC's, over match orders too, and the time
    ratio per pair."""
    acc, ms, ref = run_pairs(method, pairs, repeat)
    truth = [pair for pair in pairs if pair[3] is not None]
    names = [name for name, *_ in pairs]
    ratio = np.median(ms, 1) / np.median(ref, 1)
    return (f'{SUITE}/homography_{method}', ms.ravel(), ref.ravel(), {
        'pairs': len(pairs),
        'accuracy': {n: a for n, (a, _) in zip(names, acc)},
        'cv2_ransac': {n: b for n, (_, b) in zip(names, acc)},
        f'median_of_{ORDERS}_orders': {p[0]: over_orders(method, p) for p in truth},
        f'cv2_ransac_median_of_{ORDERS}_orders': {p[0]: over_orders('opencv_ransac', p)
                                                  for p in truth},
        'time_vs_cv2_ransac': {n: round(float(x), 2) for n, x in zip(names, ratio)}})


def _spread(err: np.ndarray) -> list[float]:
    """Median, 90th percentile, worst and mean of the finite corner errors."""
    e = err[np.isfinite(err)]
    if not len(e):
        return []
    return [round(float(x), 3) for x in (*np.percentile(e, [50, 90, 100]), e.mean())]


def synthetic_case(method: str, pairs: list[Pair]) -> tuple:
    """Case on the synthetic pairs: corner error spread, failures, pairs worse than cv2 RANSAC."""
    acc, ms, ref = run_pairs(method, pairs, 1)
    err = np.array([np.inf if a == 'fail' else a for a, _ in acc])
    ref_err = np.array([np.inf if b == 'fail' else b for _, b in acc])
    ok, both = np.isfinite(err), np.isfinite(err) & np.isfinite(ref_err)
    return (f'{SUITE}/homography_synthetic_{method}', ms.ravel(), ref.ravel(), {
        'pairs': len(pairs), 'failures': int((~ok).sum()),
        'cv2_ransac_failures': int((~np.isfinite(ref_err)).sum()),
        'corner_err_px_median_p90_max_mean': _spread(err),
        'cv2_ransac_median_p90_max_mean': _spread(ref_err),
        'worse_than_cv2_ransac': int((err > ref_err + WORSE_PX).sum()),
        'better_than_cv2_ransac': int((err < ref_err - WORSE_PX).sum()),
        'worst_excess_px': round(float((err - ref_err)[both].max()), 3) if both.any() else None,
        'mean_excess_px': round(float((err - ref_err)[both].mean()), 4) if both.any() else None,
        'time_vs_cv2_ransac_median': round(float(np.median(ms.ravel() / ref.ravel())), 2)})


def homography_cases(repeat: int = 5) -> list[tuple[str, np.ndarray, np.ndarray, dict]]:
    """(case, per-call times, cv2 RANSAC times, fields) per estimator and data set."""
    real, synthetic = real_pairs(), synthetic_pairs()
    cases = []
    for method in METHODS:
        cases.append(real_case(method, real, repeat))
        cases.append(synthetic_case(method, synthetic))
    return cases


def feature_cases() -> list[tuple[str, callable, dict]]:
    """SIFT vs ORB: describe two 640x480 frames and match them (ratio 0.75)."""
    img = cv2.imread(str(ASSETS / 'aero1.jpg'), cv2.IMREAD_GRAYSCALE)
    img = cv2.resize(img, (640, 480))
    A = cv2.getRotationMatrix2D((320, 240), 15, 0.9)
    other = cv2.warpAffine(img, A, (640, 480))
    cases = []
    for kind in ('sift', 'orb'):
        matcher = make_matcher(kind)

        def run(kind=kind, matcher=matcher):
            xy1, d1 = detect_and_describe(img, kind, 2000)
            xy2, d2 = detect_and_describe(other, kind, 2000)
            return xy1, xy2, match(d1, d2, kind, 0.75, matcher=matcher)
        xy1, xy2, (i1, i2) = run()
        err = np.linalg.norm(xy1[i1] @ A[:, :2].T + A[:, 2] - xy2[i2], axis=1)
        cases.append((f'{SUITE}/features_{kind}', run,
                      {'matches': int(len(i1)), 'correct_3px': round(float(np.mean(err < 3)), 3)}))
    return cases


def main() -> None:
    for case, ms, ref_ms, fields in homography_cases():
        report(SUITE, case, ms, ref_ms=ref_ms,
               reference='cv2 RANSAC on the same matches, called in turn', **fields)
    for case, fn, fields in feature_cases():
        report(SUITE, case, timeit(fn, repeat=10, warmup=1), **fields)


if __name__ == '__main__':
    main()
