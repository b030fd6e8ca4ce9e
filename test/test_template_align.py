"""Template alignment (section 2.1, eq 1-5; ICIA) against known warps of a real photo.

The photo is smoothed a little so that it is band-limited, then warped with
cv2.warpPerspective and Lanczos interpolation (not the bilinear sampling the solvers
use), so the truth is the warp matrix itself.
"""
from pathlib import Path

import cv2
import numpy as np
import pytest

from uav_vs.vision.template_align import (WARPS, AlignParams, InverseCompositional,
                                          align_ic, align_lk, bilinear_warp, corner_error)

ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'
X0, Y0, SIDE = 270, 190, 100          # where the template is cut from the photo
CENTRE = np.array([[1, 0, 320], [0, 1, 240], [0, 0, 1.0]])


def translation(x: float, y: float) -> np.ndarray:
    return np.array([[1, 0, x], [0, 1, y], [0, 0, 1.0]])


def about_centre(M: np.ndarray) -> np.ndarray:
    return CENTRE @ M @ np.linalg.inv(CENTRE)


def similarity(deg: float, scale: float) -> np.ndarray:
    c, s = scale * np.cos(np.radians(deg)), scale * np.sin(np.radians(deg))
    return about_centre(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]))


def perspective(f: float = 1.0) -> np.ndarray:
    """Shift, 3 deg rotation, 3 % zoom and a tilt, scaled by f (0: none)."""
    return (translation(2.3 * f, -1.7 * f) @ similarity(3.0 * f, 1 + 0.03 * f)
            @ about_centre(np.array([[1, 0, 0], [0, 1, 0], [2e-4 * f, -1.5e-4 * f, 1.0]])))


MOTIONS = {   # image motion G: moved(G x) = photo(x)
    'translation': translation(2.3, -1.7),
    'affine': translation(2.3, -1.7) @ similarity(3.0, 1.03)
    @ about_centre(np.array([[1, 0.02, 0], [0, 1, 0], [0, 0, 1.0]])),
    'homography': perspective(),
}
ALGORITHMS = {'lk': align_lk, 'ic': align_ic}


@pytest.fixture(scope='module')
def photo() -> np.ndarray:
    img = cv2.imread(str(ASSETS / 'aero1.jpg'), cv2.IMREAD_GRAYSCALE)
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)


def moved(photo: np.ndarray, G: np.ndarray, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    out = cv2.warpPerspective(photo, G, photo.shape[::-1], flags=cv2.INTER_LANCZOS4)
    return out + np.random.default_rng(seed).normal(0, noise, out.shape).astype(np.float32)


def cut(photo: np.ndarray, x0: int = X0, y0: int = Y0, side: int = SIDE) -> np.ndarray:
    return photo[y0:y0 + side, x0:x0 + side]


@pytest.mark.parametrize('algo', ALGORITHMS)
@pytest.mark.parametrize('warp', WARPS)
@pytest.mark.parametrize('noise, tolerance', [(0.0, 0.05), (5.0, 0.3)])
def test_recovers_a_known_warp(photo, warp, algo, noise, tolerance):
    G = MOTIONS[warp]
    template = cut(photo) + np.random.default_rng(1).normal(0, noise, (SIDE, SIDE))
    M0 = translation(X0 + 3, Y0 - 2)                  # a few px off, before the motion
    r = ALGORITHMS[algo](template.astype(np.float32), moved(photo, G, noise), M0, warp)
    truth = G @ translation(X0, Y0)
    assert r.converged and r.status == 'converged' and r.iterations < 30
    assert corner_error(r.M, truth, template.shape) < tolerance
    assert r.rms < 2.0 + 1.5 * noise
    assert np.allclose(WARPS[warp].matrix(r.params), r.M)


@pytest.mark.parametrize('warp', WARPS)
def test_lk_and_icia_agree(photo, warp):
    image, M0 = moved(photo, MOTIONS[warp], 3.0), translation(X0 - 2, Y0 + 2)
    lk, ic = align_lk(cut(photo), image, M0, warp), align_ic(cut(photo), image, M0, warp)
    assert lk.converged and ic.converged
    assert corner_error(lk.M, ic.M, (SIDE, SIDE)) < 0.02
    assert abs(lk.rms - ic.rms) < 0.01


def test_one_template_tracks_many_images(photo):
    tracker = InverseCompositional(cut(photo), 'homography')
    M = translation(X0, Y0)
    for k, f in enumerate(np.linspace(0.25, 1.0, 4)):
        G = perspective(f)
        r = tracker.align(moved(photo, G, 2.0, seed=k), M)
        assert r.converged and corner_error(r.M, G @ translation(X0, Y0), (SIDE, SIDE)) < 0.1
        M = r.M


@pytest.mark.parametrize('algo', ALGORITHMS)
def test_template_partly_outside_the_image(photo, algo):
    x0, y0 = 0, 150                          # the motion takes its left edge out of view
    G = translation(-20.4, 1.3)
    r = ALGORITHMS[algo](cut(photo, x0, y0), moved(photo, G), translation(x0 - 18, y0),
                         'affine')
    assert r.converged
    assert corner_error(r.M, G @ translation(x0, y0), (SIDE, SIDE)) < 0.05


@pytest.mark.parametrize('algo', ALGORITHMS)
@pytest.mark.parametrize('warp', WARPS)
def test_textureless_template_is_singular(algo, warp):
    flat = np.full((480, 640), 120, np.uint8)
    stripes = np.tile((np.arange(640) % 7 * 30).astype(np.uint8), (480, 1))  # aperture problem
    M0 = translation(100.0, 100.0)
    for image in (flat, stripes):
        r = ALGORITHMS[algo](cut(image, 101, 99, 64), image, M0, warp)
        assert not r.converged and r.status == 'singular'
        assert np.allclose(r.M, M0)


@pytest.mark.parametrize('algo', ALGORITHMS)
def test_pyramid_extends_the_capture_range(photo, algo):
    G = translation(20.0, -12.0) @ similarity(3.0, 1.03)
    image, truth = moved(photo, G), G @ translation(X0, Y0)
    single = ALGORITHMS[algo](cut(photo), image, translation(X0, Y0), 'affine')
    pyramid = ALGORITHMS[algo](cut(photo), image, translation(X0, Y0), 'affine',
                               AlignParams(levels=3))
    assert not (single.converged and corner_error(single.M, truth, (SIDE, SIDE)) < 1.0)
    assert pyramid.converged and corner_error(pyramid.M, truth, (SIDE, SIDE)) < 0.05


@pytest.mark.parametrize('M', [np.array([[1.02, 0.03, 10.3], [-0.02, 0.99, 7.7], [1e-4, -2e-4, 1]]),
                               np.array([[1, 0, -3.3], [0, 1, 50.2], [0, 0, 1]])])
def test_bilinear_warp_is_exact_on_a_plane_and_replicates_the_border(M):
    """A bilinear sample of a linear image is the plane itself at the exact coordinate
    (clamped to the image: replicated border), to float32 precision."""
    ys, xs = np.mgrid[0:60, 0:80]
    img = (0.7 * xs + 1.3 * ys + 5).astype(np.float32)
    out = bilinear_warp(img, M, (40, 30))
    v, u = np.mgrid[0:30, 0:40]
    p = M @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    x, y = np.clip(p[0] / p[2], 0, 79), np.clip(p[1] / p[2], 0, 59)
    assert out.shape == (30, 40) and out.dtype == np.float32
    assert np.allclose(out.ravel(), 0.7 * x + 1.3 * y + 5, atol=1e-3)
