"""A calibration of the simulated ground station judged against its true cameras
(test_calibrated_flight; `make bench`, calibration/simulated_rig)."""
import math

import cv2
import numpy as np

from uav_vs.vision.camera import Camera


def lens_error(true: Camera, ours: Camera, step: int = 4) -> np.ndarray:
    """How far our K and D put each pixel of the image (every `step`-th) from where the
    true lens does, px: the pixel's ray through our lens, turned by the one rotation that
    best aligns our camera frame with the true one (which the principal point trades with
    R), projected through the true lens."""
    u, v = np.meshgrid(np.arange(0, true.width, float(step)),
                       np.arange(0, true.height, float(step)))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    ours_rays, true_rays = (np.column_stack([c.normalize(pixels), np.ones(len(pixels))])
                            for c in (ours, true))
    a, b = (r / np.linalg.norm(r, axis=1, keepdims=True) for r in (ours_rays, true_rays))
    U, _, Vt = np.linalg.svd(b.T @ a)
    turn = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    lens = Camera(K=true.K, D=true.D)
    return np.linalg.norm(lens.project(a @ turn.T) - pixels, axis=1)


def pose_error(true: Camera, ours: Camera) -> tuple[float, float]:
    """(the angle between our R and the true one, degrees; the distance between our t and
    the true one, m): eq 16's world-to-camera pose."""
    turn = math.degrees(np.linalg.norm(cv2.Rodrigues(ours.R @ true.R.T)[0]))
    return turn, float(np.linalg.norm(ours.t - true.t))
