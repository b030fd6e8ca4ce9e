"""Robust homography estimators and feature matchers side by side (suite 'onboard').

- onboard/homography_<method>: every estimator on the same Oxford graf/boat SIFT
  matches (ratio 0.75, exact nearest neighbours, as the data README's baseline): time
  per call, next to cv2 RANSAC timed in turn with it in the same process, and the
  corner transfer error against the true H for each pair 1->2..1->6 ('fail' where the
  estimate is reported as a failure).
- onboard/features_<kind>: detection + description of two 640x480 frames and FLANN
  ratio-test matching between them (aero1.jpg and a rotated, scaled copy).
"""
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from bench.common import report, timeit
from uav_vs.datasets import shared_data_dir
from uav_vs.vision.features import detect_and_describe, make_matcher, match
from uav_vs.vision.homography import METHODS, estimate_homography

SUITE = 'onboard'
ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'


def _project(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


@lru_cache(maxsize=None)
def oxford_matches() -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(pair name, src, dst, true H, img1 corners) for graf and boat 1->2..1->6."""
    root = shared_data_dir()
    if root is None:
        return []
    pairs = []
    bf = cv2.BFMatcher(cv2.NORM_L2)
    for seq, ext in (('graf', 'ppm'), ('boat', 'pgm')):
        imgs = [cv2.imread(str(root / 'oxford' / seq / f'img{k}.{ext}'), cv2.IMREAD_GRAYSCALE)
                for k in range(1, 7)]
        feats = [detect_and_describe(img, 'sift') for img in imgs]
        h, w = imgs[0].shape
        corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
        for k in range(2, 7):
            i1, i2 = match(feats[0][1], feats[k - 1][1], 'sift', 0.75, matcher=bf)
            H = np.loadtxt(root / 'oxford' / seq / f'H1to{k}p')
            pairs.append((f'{seq}1-{k}', feats[0][0][i1], feats[k - 1][0][i2], H, corners))
    return pairs


def homography_cases() -> list[tuple[str, callable, dict]]:
    """(case, fn timing one pass over all pairs, accuracy fields) per estimator."""
    cases = []
    pairs = oxford_matches()
    for method in METHODS:
        errors = {}
        for name, src, dst, H_true, c in pairs:
            r = estimate_homography(src, dst, method, rng=0)
            errors[name] = (round(float(np.linalg.norm(_project(r.H, c) - _project(H_true, c),
                                                       axis=1).mean()), 3) if r.ok else 'fail')

        def one_pass(method=method):
            for _, src, dst, _, _ in pairs:
                estimate_homography(src, dst, method, rng=0)
        cases.append((f'{SUITE}/homography_{method}', one_pass,
                      {'pairs': len(pairs), 'corner_err_px': errors}))
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


def interleaved(fn: callable, ref: callable, repeat: int) -> tuple[np.ndarray, np.ndarray]:
    """Durations (ms) of fn and ref called in turn, so both see the same machine load."""
    fn()
    ref()
    times = np.array([[timeit(f, repeat=1, warmup=0)[0] for f in (fn, ref)]
                      for _ in range(repeat)])
    return times[:, 0], times[:, 1]


def main() -> None:
    cases = homography_cases()
    reference = next(fn for case, fn, _ in cases if case.endswith('_opencv_ransac'))
    for case, fn, fields in cases:
        ms, ref_ms = interleaved(fn, reference, repeat=7)
        report(SUITE, case, ms / fields['pairs'], ref_ms=ref_ms / fields['pairs'],
               reference='cv2 RANSAC per call, mean over the Oxford pairs', **fields)
    for case, fn, fields in feature_cases():
        report(SUITE, case, timeit(fn, repeat=10, warmup=1), **fields)


if __name__ == '__main__':
    main()
