"""Feature toolbox (section 2, 2.2): corner robustness test, Hough lines, ratio-test matching."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from uav_vs.vision.features import detect_and_describe, hough_lines, match, robust_corners

ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'


def checkerboard_with_blob():
    """Exact corners of a 4x4 checkerboard at known places, plus a smooth blob (no corner)."""
    img = np.full((240, 320), 40, np.uint8)
    for i in range(4):
        for j in range(4):
            if (i + j) % 2 == 0:
                img[40 + 40 * i:80 + 40 * i, 60 + 40 * j:100 + 40 * j] = 220
    yy, xx = np.mgrid[:240, :320]
    blob = 120 * np.exp(-((xx - 260) ** 2 + (yy - 200) ** 2) / (2 * 12.0 ** 2))
    img = np.clip(img + blob, 0, 255).astype(np.uint8)
    inner = np.array([[60 + 40 * j, 40 + 40 * i] for i in range(1, 4) for j in range(1, 4)], float)
    return img, inner


# Round discs: blob-like, no corner; their detector responses move as the window grows.
DISCS = ((215, 35, 6), (270, 60, 9), (225, 115, 12), (290, 135, 5), (200, 190, 4),
         (255, 195, 7), (120, 195, 10), (50, 200, 5))


def polygon_with_discs():
    """A quadrilateral with exact vertices and round discs, area-sampled (drawn at 16x).

    Vertex v in pixel-edge coordinates is at v - 0.5 in OpenCV's pixel-centre ones.
    """
    s = 16
    big = np.full((240 * s, 320 * s), 40, np.uint8)
    verts = np.array([[40.25, 30.5], [130.75, 22.0], [150.5, 110.25], [60.0, 128.75]])
    cv2.fillPoly(big, [np.round(verts * s).astype(np.int32)], 220)
    for x, y, r in DISCS:
        cv2.circle(big, (x * s, y * s), r * s, 200, -1)
    return cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA), verts - 0.5


@pytest.mark.parametrize('use_harris, disc_responses', [(False, (20, 100)), (True, (3, 12))])
def test_regrown_window_keeps_the_true_vertices_and_drops_the_blobs(use_harris, disc_responses):
    img, true = polygon_with_discs()
    kept = robust_corners(img, use_harris=use_harris)
    d = np.linalg.norm(kept[:, None] - true[None], axis=2)
    # Exactly the four vertices, each to 0.35 px (cornerSubPix on slanted area-sampled
    # L-corners is biased by up to ~0.27 px here).
    assert len(kept) == 4 and (d.min(0) < 0.35).all(), kept
    # The detector and the eigenvalue test alone keep responses on the discs (28 for
    # Shi-Tomasi; 6 for Harris, whose det - k tr^2 penalises edges): the window test
    # is what drops them.
    unchecked = robust_corners(img, max_shift_px=np.inf, use_harris=use_harris)
    on_discs = np.linalg.norm(unchecked[:, None] - true[None], axis=2).min(1) > 5
    assert disc_responses[0] <= on_discs.sum() <= disc_responses[1], unchecked


def test_robust_corners_are_the_true_corners():
    img, inner = checkerboard_with_blob()
    pts = robust_corners(img, block_sizes=(3, 5, 7, 9), min_eigenvalue=0.01)
    # Every inner checkerboard corner is found, within half a pixel (pixel-edge convention).
    d = np.linalg.norm(pts[None] - inner[:, None] + 0.5, axis=2)
    assert (d.min(1) < 0.75).all()
    # and nothing is kept near the blob, whose Shi-Tomasi response has no stable peak
    assert not (np.linalg.norm(pts - [260, 200], axis=1) < 20).any()


def test_robustness_test_drops_corners_that_move_with_the_window():
    img, _ = checkerboard_with_blob()
    loose = robust_corners(img, max_shift_px=100.0, min_eigenvalue=0.0, quality=1e-4)
    strict = robust_corners(img, max_shift_px=0.5, min_eigenvalue=0.0, quality=1e-4)
    assert len(strict) < len(loose)                         # the window test removes some
    eig_strict = robust_corners(img, max_shift_px=100.0, min_eigenvalue=1e9, quality=1e-4)
    assert len(eig_strict) == 0                             # the eigenvalue threshold applies


def test_hough_finds_known_lines():
    img = np.zeros((300, 400), np.uint8)
    cv2.line(img, (0, 100), (399, 100), 255, 2)             # y = 100: theta = 90 deg, r = 100
    cv2.line(img, (250, 0), (250, 299), 255, 2)             # x = 250: theta = 0, r = 250
    lines = hough_lines(img, votes=150)
    expect = np.array([[100.5, np.pi / 2], [250.5, 0.0]])
    for r, th in expect:
        d = np.abs(lines[:, 0] - r) + 100 * np.abs(lines[:, 1] - th)
        assert d.min() < 2.0, (r, th, lines[:5])


@pytest.mark.parametrize('kind', ['sift', 'orb'])
def test_ratio_test_matches_a_rotated_copy(kind):
    img = cv2.imread(str(ASSETS / 'aero1.jpg'), cv2.IMREAD_GRAYSCALE)
    h, w = img.shape
    A = cv2.getRotationMatrix2D((w / 2, h / 2), 20, 0.9)
    rot = cv2.warpAffine(img, A, (w, h))
    xy1, d1 = detect_and_describe(img, kind, 2000)
    xy2, d2 = detect_and_describe(rot, kind, 2000)
    i1, i2 = match(d1, d2, kind, ratio=0.75)
    err = np.linalg.norm(xy1[i1] @ A[:, :2].T + A[:, 2] - xy2[i2], axis=1)
    assert len(i1) > 100 and np.mean(err < 3) > 0.9         # ratio test keeps good matches
    j1, _ = match(d1, d2, kind, ratio=0.95)
    assert len(j1) > len(i1)                                 # a looser ratio keeps more


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match='8-bit'):
        robust_corners(np.zeros((100, 100), np.float32))
    with pytest.raises(ValueError, match='increasing'):
        robust_corners(np.zeros((100, 100), np.uint8), block_sizes=(5, 3))
    with pytest.raises(ValueError, match='unknown feature kind'):
        detect_and_describe(np.zeros((64, 64), np.uint8), 'surf')
