"""Following a target (section 5): one tracker polygon -> the follower's setpoint.

onboard/follow_ground_points: the five pixel rays to the ground plane alone
(uav_vs.vision.ground_target.ground_points, lens distortion removed).
onboard/follow_target: `TargetFollower.on_target` per tracker polygon (corners and
centre, raw pixels), with 64 vehicle poses and 64 attitudes in its history as in flight:
the pose and attitude at the image stamp, the ground points, the target's place and heading, the
alpha-beta filter and the lead. The reference of both is OpenCV's route to the same
ground points: cv2.undistortPoints onto the pixel plane, then cv2.perspectiveTransform
by the inverse of the ground-plane homography K [r1 r2 t]. Views: 200 random vehicle
poses 1-2 m high, tilted up to 10 deg, the target somewhere in the image; pixels from
cv2.projectPoints with the lens model of config/onboard.yaml. Accuracy is the largest
ground error of the target's centre, m.
"""
import math
from pathlib import Path

import cv2
import numpy as np

from bench.common import report, timeit
from uav_vs.control.follow import FollowConfig, TargetFollower
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.ground_target import ground_points
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import camera_pose

SUITE = 'onboard'
CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'onboard.yaml'
REFERENCE = 'cv2.undistortPoints + perspectiveTransform'
HALF = 0.2                      # the target's half width, m
VIEWS = 200


def rotation(yaw: float, roll: float, pitch: float) -> np.ndarray:
    """World-from-body: yaw about z, then pitch about y, roll about x."""
    R_z, R_y, R_x = (cv2.Rodrigues(np.array(v, float))[0]
                     for v in ((0, 0, yaw), (0, pitch, 0), (roll, 0, 0)))
    return R_z @ R_y @ R_x


View = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def views(cfg, rng: np.random.Generator) -> list[View]:
    """(R_wb, p_wb, polygon pixels (5,2), true centre (2,)) of targets inside the image."""
    cam = cfg.camera
    out = []
    while len(out) < VIEWS:
        R_wb = rotation(rng.uniform(-math.pi, math.pi), *np.radians(rng.uniform(-10, 10, 2)))
        p_wb = np.array([*rng.uniform(-1, 1, 2), rng.uniform(1.0, 2.0)])
        R, t = camera_pose(R_wb, p_wb, cfg.camera_to_body)
        centre = p_wb[:2] + rng.uniform(-0.3, 0.3, 2) * p_wb[2]
        heading = rng.uniform(-math.pi, math.pi)
        f = HALF * np.array([math.cos(heading), math.sin(heading)])
        left = np.array([-f[1], f[0]])
        ground = np.array([centre + f + left, centre + f - left, centre - f - left,
                           centre - f + left, centre])
        cam_z = (np.column_stack([ground, np.zeros(5)]) @ R.T + t)[:, 2]
        px = cv2.projectPoints(np.column_stack([ground, np.zeros(5)]), cv2.Rodrigues(R)[0], t,
                               cam.K, cam.D)[0].reshape(-1, 2)
        inside = (px >= 0).all() and (px < [cam.width, cam.height]).all()
        if (cam_z > 0).all() and inside:
            out.append((R_wb, p_wb, px, centre))
    return out


def opencv_ground(cfg, R_wb: np.ndarray, p_wb: np.ndarray, px: np.ndarray) -> np.ndarray:
    """The reference: ground points of raw pixels by OpenCV's undistortion and the inverse
    ground-plane homography."""
    cam = cfg.camera
    R, t = camera_pose(R_wb, p_wb, cfg.camera_to_body)
    H = cam.K @ np.column_stack([R[:, 0], R[:, 1], t])
    ideal = cv2.undistortPoints(px.reshape(-1, 1, 2), cam.K, cam.D, P=cam.K)
    return cv2.perspectiveTransform(ideal, np.linalg.inv(H)).reshape(-1, 2)


def main() -> None:
    cfg = load_onboard_config(read_params_file(CONFIG))
    cases = views(cfg, np.random.default_rng(0))
    follower = TargetFollower(cfg.camera, cfg.camera_to_body, FollowConfig(),
                              attitude_source=True)
    k = 0

    def step():
        nonlocal k
        R_wb, p_wb, px, _ = cases[k % VIEWS]
        stamp = 0.1 * k
        follower.on_pose(stamp, R_wb, p_wb)
        follower.on_attitude(stamp, R_wb)
        k += 1
        return follower.on_target(stamp, px)[0]

    def reference():
        nonlocal k
        R_wb, p_wb, px, _ = cases[k % VIEWS]
        k += 1
        return opencv_ground(cfg, R_wb, p_wb, px)

    def rays():
        nonlocal k
        R_wb, p_wb, px, _ = cases[k % VIEWS]
        k += 1
        return ground_points(cfg.camera, cfg.camera_to_body, R_wb, p_wb, px)

    ms = timeit(step, 1000, 70)
    rays_ms = timeit(rays, 1000, 70)
    ref_ms = timeit(reference, 1000, 70)
    ours = []
    for R_wb, p_wb, px, centre in cases:
        fresh = TargetFollower(cfg.camera, cfg.camera_to_body, FollowConfig(),
                               attitude_source=True)
        fresh.on_pose(0.0, R_wb, p_wb)
        fresh.on_attitude(0.0, R_wb)
        step, = fresh.on_target(0.0, px)
        ours.append(np.linalg.norm(step.target.position - centre))
    theirs = [np.linalg.norm(opencv_ground(cfg, R_wb, p_wb, px)[4] - centre)
              for R_wb, p_wb, px, centre in cases]
    rays_err = [np.linalg.norm(ground_points(cfg.camera, cfg.camera_to_body, R_wb, p_wb, px)[4]
                               - centre) for R_wb, p_wb, px, centre in cases]
    report(SUITE, 'onboard/follow_ground_points', rays_ms, REFERENCE, ref_ms,
           max_err_m=float(f'{max(rays_err):.2e}'), ref_max_err_m=float(f'{max(theirs):.2e}'),
           views=VIEWS)
    report(SUITE, 'onboard/follow_target', ms, REFERENCE, ref_ms,
           max_err_m=float(f'{max(ours):.2e}'), ref_max_err_m=float(f'{max(theirs):.2e}'),
           views=VIEWS)


if __name__ == '__main__':
    main()
