"""Pyramidal Lucas-Kanade tracking (sections 2.1.1-2.1.2) against known image motions."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from uav_vs.vision.klt import KltParams, KltTracker

ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'


@pytest.fixture(scope='module')
def photo() -> np.ndarray:
    return cv2.imread(str(ASSETS / 'aero1.jpg'), cv2.IMREAD_GRAYSCALE)


def moved(img: np.ndarray, A: np.ndarray) -> np.ndarray:
    """img under the 2x3 affine map A (new(A x) = img(x)), edges replicated."""
    return cv2.warpAffine(img, A, img.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def features(tracker: KltTracker, img: np.ndarray, margin: int = 40) -> np.ndarray:
    region = np.zeros_like(img)
    region[margin:-margin, margin:-margin] = 255
    return tracker.detect(img, 100, region=region)


@pytest.mark.parametrize('shift', [(3.3, -2.7), (-0.4, 0.8)])
def test_tracks_a_known_translation(photo, shift):
    tracker = KltTracker()
    pts = features(tracker, photo)
    A = np.array([[1, 0, shift[0]], [0, 1, shift[1]]])
    new, ok = tracker.track(photo, moved(photo, A), pts)
    assert len(pts) >= 80 and ok.mean() > 0.9
    err = np.linalg.norm(new[ok] - (pts[ok] + shift), axis=1)
    assert np.median(err) < 0.1 and err.max() < 0.25


def test_tracks_a_known_affine_motion(photo):
    tracker = KltTracker()
    pts = features(tracker, photo)
    a, s = np.radians(2.0), 1.02                 # 2 deg rotation, 2 % zoom, and a shift
    A = np.array([[s * np.cos(a), -s * np.sin(a), 6.0], [s * np.sin(a), s * np.cos(a), -4.0]])
    new, ok = tracker.track(photo, moved(photo, A), pts)
    truth = pts @ A[:, :2].T + A[:, 2]
    err = np.linalg.norm(new[ok] - truth[ok], axis=1)
    assert ok.mean() > 0.8
    assert np.median(err) < 0.1 and np.percentile(err, 90) < 0.3


def test_pyramid_follows_motion_beyond_the_window(photo):
    """A 24 px jump: found with pyramid levels (section 2.1.2), not at level 0 alone."""
    A = np.array([[1, 0, 24.0], [0, 1, -13.0]])
    img = moved(photo, A)
    pyramidal, flat = KltTracker(KltParams(max_level=3)), KltTracker(KltParams(max_level=0))
    pts = features(pyramidal, photo)
    new, ok = pyramidal.track(photo, img, pts)
    assert ok.mean() > 0.9
    assert np.abs(new[ok] - (pts[ok] + A[:, 2])).max() < 0.3
    new, ok = flat.track(photo, img, pts)
    good = ok & (np.linalg.norm(new - (pts + A[:, 2]), axis=1) < 0.3)
    assert good.mean() < 0.2


def test_forward_backward_check_rejects_broken_tracks(photo):
    """Where the second image shows something else, tracks are dropped, not moved."""
    tracker = KltTracker()
    pts = features(tracker, photo)
    shift = np.array([2.0, 1.0])
    img = moved(photo, np.array([[1, 0, shift[0]], [0, 1, shift[1]]]))
    # Replace the left third with an unrelated part of another photo.
    other = cv2.imread(str(ASSETS / 'aero3.jpg'), cv2.IMREAD_GRAYSCALE)
    img[:, :210] = cv2.flip(other, -1)[:, :210]
    new, ok = tracker.track(photo, img, pts)
    inside = pts[:, 0] < 200             # window entirely in the replaced area
    outside = pts[:, 0] > 280            # beyond the reach of the level-3 window
    assert inside.sum() >= 15 and outside.sum() >= 40
    assert ok[inside].mean() < 0.2
    assert ok[outside].mean() > 0.9
    # Every track that survives is right: the check removes the wrong ones.
    assert np.abs(new[ok] - (pts[ok] + shift)).max() < 0.5


def test_flat_patches_are_not_tracked(photo):
    img = photo.copy()
    img[100:300, 100:300] = 128
    pts = np.array([[200.0, 200.0], [150.0, 250.0]], np.float32)
    _, ok = KltTracker().track(img, img, pts)
    assert not ok.any()


def test_detect_keeps_away_from_tracks_and_inside_the_region(photo):
    tracker = KltTracker(KltParams(min_distance_px=20.0))
    old = features(tracker, photo)[:40]
    region = np.zeros_like(photo)
    region[50:430, 50:590] = 255
    new = tracker.top_up(photo, old, 100, region)
    assert 0 < len(new) <= 60
    d = np.linalg.norm(new[:, None] - old[None], axis=2)
    assert d.min() >= 20.0 - 2.0          # detection level 1: locations good to ~2 px
    assert new[:, 0].min() >= 48 and new[:, 0].max() <= 592
    assert new[:, 1].min() >= 48 and new[:, 1].max() <= 432
    spacing = np.linalg.norm(new[:, None] - new[None], axis=2) + np.eye(len(new)) * 1e9
    assert spacing.min() >= 20.0 - 2.0
    assert len(tracker.top_up(photo, np.zeros((100, 2), np.float32), 100)) == 0


def test_no_points_is_not_an_error(photo):
    new, ok = KltTracker().track(photo, photo, np.empty((0, 2), np.float32))
    assert new.shape == (0, 2) and ok.shape == (0,)
