"""Calibration error: the simulated world's true cameras are a little off the calibration
the vision nodes are given, as a real rig is off its calibration (chapter sections 3.0.2
and 4: eq 15's K, eq 16's R, t; the onboard camera's mount on base_link).

Each error is drawn once, at start-up, from zero-mean normal laws: the optical centre moved
by `position_sigma` m per axis, the optical frame rotated by `angle_sigma` rad about each
axis, the focal length scaled by 1 + `focal_sigma` (fx and fy together, as a zoom) and the
principal point moved by `principal_sigma` px per axis. The lens distortion D is kept.
"""
from dataclasses import dataclass, replace

import cv2
import numpy as np

from uav_vs.vision.camera import Camera


@dataclass(frozen=True)
class CalibrationSpread:
    """Standard deviations of the calibration error; all zero: exact."""

    position_sigma: float = 0.0     # m, per axis
    angle_sigma: float = 0.0        # rad, per axis
    focal_sigma: float = 0.0        # relative
    principal_sigma: float = 0.0    # px, per axis


def small_rotation(rng: np.random.Generator, sigma: float) -> np.ndarray:
    """A rotation of normal angles of `sigma` rad about each axis (axis-angle vector)."""
    return cv2.Rodrigues(rng.normal(0.0, sigma, 3))[0]


def true_camera(nominal: Camera, spread: CalibrationSpread, rng: np.random.Generator) -> Camera:
    """The camera as it really is, for the `nominal` calibration the nodes are given."""
    K = nominal.K.copy()
    K[:2, :2] *= 1.0 + rng.normal(0.0, spread.focal_sigma)
    K[:2, 2] += rng.normal(0.0, spread.principal_sigma, 2)
    R = small_rotation(rng, spread.angle_sigma) @ nominal.R     # rotated in its own frame
    centre = nominal.center + rng.normal(0.0, spread.position_sigma, 3)
    return replace(nominal, K=K, R=R, t=-R @ centre)


def true_mount(camera_to_body: np.ndarray, spread: CalibrationSpread,
               rng: np.random.Generator) -> np.ndarray:
    """The onboard camera's real 4x4 camera-to-base_link transform for its nominal one."""
    T = np.array(camera_to_body, np.float64)
    T[:3, :3] = T[:3, :3] @ small_rotation(rng, spread.angle_sigma)
    T[:3, 3] += rng.normal(0.0, spread.position_sigma, 3)
    return T
