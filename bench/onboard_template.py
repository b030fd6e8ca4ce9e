"""Template alignment (section 2.1): L-K and ICIA next to cv2.findTransformECC.

onboard/template_<warp>_<algo>_<side>: a side x side template cut from the middle of
aero1.jpg is aligned with a copy of the photo moved by a known warp of that type
(2.3 px shift; affine and homography add a 3 deg rotation, 3 % zoom and a shear or
tilt; Lanczos resampling, Gaussian noise sigma 2 grey levels), starting from where the
template was cut, as a tracker does between frames. `algo` is `lk` (forward additive,
eq 1-5) or `icia` (inverse compositional, Baker & Matthews 2004); a call includes all
per-template work, and `align_only_ms` gives ICIA's time with that done once
beforehand. The reference is cv2.findTransformECC (ECC criterion, OpenCV's default
termination, no smoothing, as for L-K and ICIA) on the same pair from the same start.
Accuracy is the largest corner error of the template against the true warp, px. One
OpenCV thread.
"""
from pathlib import Path

import cv2
import numpy as np

from bench.common import report, summary, timeit
from uav_vs.vision.template_align import (WARPS, InverseCompositional, align_ic, align_lk,
                                          corner_error)

SUITE = 'onboard'
ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'
REFERENCE = 'cv2.findTransformECC'
SIDES = (100, 200)
ECC_MOTION = {'translation': cv2.MOTION_TRANSLATION, 'affine': cv2.MOTION_AFFINE,
              'homography': cv2.MOTION_HOMOGRAPHY}
ECC_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-3)


def translation(x: float, y: float) -> np.ndarray:
    return np.array([[1, 0, x], [0, 1, y], [0, 0, 1.0]])


def motion(warp: str, centre: tuple[float, float]) -> np.ndarray:
    """The known image motion of each warp type, about the template's centre."""
    c, s = 1.03 * np.cos(np.radians(3.0)), 1.03 * np.sin(np.radians(3.0))
    linear = {'translation': np.eye(3),
              'affine': np.array([[c, -s + 0.02, 0], [s, c, 0], [0, 0, 1.0]]),
              'homography': np.array([[c, -s, 0], [s, c, 0], [2e-4, -1.5e-4, 1.0]])}[warp]
    C = translation(*centre)
    return translation(2.3, -1.7) @ C @ linear @ np.linalg.inv(C)


def ecc(template: np.ndarray, image: np.ndarray, M0: np.ndarray, warp: str) -> np.ndarray:
    """cv2.findTransformECC from M0; the 3x3 warp it finds."""
    start = (M0 if warp == 'homography' else M0[:2]).astype(np.float32)
    _, W = cv2.findTransformECC(template, image, start, ECC_MOTION[warp], ECC_CRITERIA,
                                None, 1)
    return W if warp == 'homography' else np.vstack([W, [0, 0, 1]])


def template_cases(repeat: int = 20) -> list[dict]:
    """Every warp and template side, L-K and ICIA, with ECC as the reference."""
    photo = cv2.imread(str(ASSETS / 'aero1.jpg'), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    h, w = photo.shape
    rng = np.random.default_rng(0)
    rows = []
    for warp in WARPS:
        G = motion(warp, ((w - 1) / 2, (h - 1) / 2))
        image = cv2.warpPerspective(photo, G, (w, h), flags=cv2.INTER_LANCZOS4)
        image += rng.normal(0, 2.0, image.shape).astype(np.float32)
        for side in SIDES:
            x0, y0 = (w - side) // 2, (h - side) // 2
            template = photo[y0:y0 + side, x0:x0 + side]
            M0, truth = translation(x0, y0), G @ translation(x0, y0)
            ref_ms = timeit(lambda: ecc(template, image, M0, warp), repeat, 2)
            ref_err = corner_error(ecc(template, image, M0, warp), truth, template.shape)
            tracker = InverseCompositional(template, warp)
            align_only = summary(timeit(lambda: tracker.align(image, M0), repeat, 2))[0]
            for algo, fn in (('lk', align_lk), ('icia', align_ic)):
                r = fn(template, image, M0, warp)
                ms = timeit(lambda: fn(template, image, M0, warp), repeat, 2)
                extra = {'align_only_ms': round(align_only, 3)} if algo == 'icia' else {}
                rows.append(report(
                    SUITE, f'onboard/template_{warp}_{algo}_{side}', ms, REFERENCE, ref_ms,
                    corner_err_px=round(corner_error(r.M, truth, template.shape), 4),
                    ref_corner_err_px=round(ref_err, 4), iterations=r.iterations,
                    converged=r.converged, **extra))
    return rows


def main() -> None:
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        template_cases()
    finally:
        cv2.setNumThreads(threads)


if __name__ == '__main__':
    main()
