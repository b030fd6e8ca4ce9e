"""Planar target tracking (Fig. 2): box.png in real and synthetic scenes."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from uav_vs.vision.target_tracking import PlanarTargetTracker

ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'


def load(path):
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f'cannot read {path}'
    return img


@pytest.fixture(scope='module')
def box():
    return load(ASSETS / 'box.png')


@pytest.fixture(scope='module')
def tracker(box):
    return PlanarTargetTracker(box, 'sift')


def opencv_reference_corners(template, scene):
    """Corners from OpenCV's own pipeline (SIFT, ratio 0.75, RANSAC 3 px + LM)."""
    sift = cv2.SIFT_create()
    k1, d1 = sift.detectAndCompute(template, None)
    k2, d2 = sift.detectAndCompute(scene, None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [a for a, b in pairs if a.distance < 0.75 * b.distance]
    src = np.float32([k1[m.queryIdx].pt for m in good])
    dst = np.float32([k2[m.trainIdx].pt for m in good])
    H, _ = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    h, w = template.shape
    c = np.float32([[0, 0], [w, 0], [w, h], [0, h]])[:, None]
    return cv2.perspectiveTransform(c, H)[:, 0]


def test_box_found_in_cluttered_scene(shared_data, box, tracker):
    scene = load(shared_data / 'opencv' / 'box_in_scene.png')
    r = tracker.find(scene)
    assert r.ok, r.reason
    assert r.n_inliers >= 60
    ref = opencv_reference_corners(box, scene)
    assert np.linalg.norm(r.corners - ref, axis=1).max() < 2.0
    assert np.allclose(r.center, _project(r.H, [box.shape[1] / 2, box.shape[0] / 2]))


def _project(H, p):
    q = H @ np.array([p[0], p[1], 1.0])
    return q[:2] / q[2]


def test_box_warped_onto_aerial_photo_with_known_homography(box, tracker):
    ground = load(ASSETS / 'aero1.jpg')
    h, w = box.shape
    corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    truth = np.float32([[230, 120], [470, 150], [450, 330], [210, 300]])   # a perspective view
    H = cv2.getPerspectiveTransform(corners, truth)
    warped = cv2.warpPerspective(box, H, ground.shape[::-1], flags=cv2.INTER_LINEAR)
    mask = cv2.warpPerspective(np.full_like(box, 255), H, ground.shape[::-1],
                               flags=cv2.INTER_NEAREST)
    frame = np.where(mask > 0, warped, ground)
    r = tracker.find(frame)
    assert r.ok, r.reason
    assert np.linalg.norm(r.corners - truth, axis=1).max() < 1.5
    assert np.linalg.norm(r.center - _project(H, [w / 2, h / 2])) < 1.0


def test_frame_without_target_is_not_found(tracker):
    r = tracker.find(load(ASSETS / 'aero3.jpg'))
    assert not r.ok and r.corners is None and r.H is None
    assert r.reason


def test_bad_frame_is_reported_not_raised(tracker):
    r = tracker.find(np.zeros((4, 4, 2), np.float32))
    assert not r.ok and 'image' in r.reason
    blank = tracker.find(np.full((480, 640), 128, np.uint8))      # texture-less: no features
    assert not blank.ok and blank.reason
