"""Where a target seen by the onboard camera lies on the ground (chapter sections 4-5).

A pixel's ray (the inverse of eq 15, lens distortion removed) leaves the optical centre
of the camera on the vehicle; with the vehicle's pose in `world` (ENU) it meets the
ground plane z = 0 (the plane of section 4) at one point. Applied to the tracked
target's centre and corners (uav_vs.vision.target_tracking: template corners TL, TR,
BR, BL, then the centre) it gives the target's position and heading on the ground.
"""
from dataclasses import dataclass

import numpy as np

from uav_vs.vision.camera import Camera


def ground_points(camera: Camera, camera_to_body: np.ndarray, R_wb: np.ndarray,
                  p_wb: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Raw pixels (N,2) -> their rays' points on the ground plane (N,2), m, in world;
    NaN where a ray does not go down to the ground in front of the camera."""
    n = camera.normalize(pixels)
    R_wc = R_wb @ camera_to_body[:3, :3]
    origin = p_wb + R_wb @ camera_to_body[:3, 3]
    rays = np.column_stack([n, np.ones(len(n))]) @ R_wc.T
    with np.errstate(divide='ignore', invalid='ignore'):
        scale = -origin[2] / rays[:, 2]
    scale[~(scale > 0)] = np.nan
    return origin[:2] + scale[:, None] * rays[:, :2]


@dataclass(frozen=True)
class TargetOnGround:
    """The tracked target on the ground plane."""

    position: np.ndarray     # (2,) centre x, y in world, m
    heading: float           # direction of the template's top edge, rad (ENU)
    size: float              # mean length of its four sides, m


def target_on_ground(camera: Camera, camera_to_body: np.ndarray, R_wb: np.ndarray,
                     p_wb: np.ndarray, polygon: np.ndarray) -> TargetOnGround | None:
    """The target of a tracker polygon (5 points: corners TL, TR, BR, BL, centre; raw
    pixels) seen from the vehicle at R_wb, p_wb; None if a ray misses the ground."""
    g = ground_points(camera, camera_to_body, R_wb, p_wb, np.asarray(polygon, float)[:5])
    if len(g) < 5 or not np.isfinite(g).all():
        return None
    corners = g[:4]
    forward = (corners[0] + corners[1] - corners[2] - corners[3]) / 2
    size = float(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1).mean())
    return TargetOnGround(g[4], float(np.arctan2(forward[1], forward[0])), size)
