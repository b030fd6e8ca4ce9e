"""Onboard plane-pose pipeline (section 4): per-frame time on rendered flights.

Each case renders the sample bag's flight (config/onboard.yaml camera, scaled to the
case's resolution, JPEG q90 like the bag) and times `PlanePoseEstimator.update` frame
by frame on one OpenCV thread, next to a straightforward loop on the same frames (as
OpenCV's lk_homography sample: good features to track on every frame, pyramidal L-K
forward and back, cv2.findHomography RANSAC). Accuracy against the simulator truth is
reported with it.

The refinement cases time the pose refinement on its own (eq 27, the last step of every
frame), the package's Levenberg-Marquardt next to cv2.solvePnPRefineLM from the same
start, on 50 random views of 100 noisy plane points, with their error against the true
pose.

The relocalisation case loses the texture for 1 or 1.5 s while the flight goes on
(14 losses) and times the first update on ground again, which matches the keyframe by
descriptors: ORB (the default) next to SIFT, with how many losses each recovered
within three frames and how many poses were more than 2 % of the height off, and how
many the L-K tracking recovers alone.
"""
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bench.common import report, timeit
from uav_vs.sim.onboard_scene import OnboardScene, Trajectory, fly
from uav_vs.vision.camera import look_at
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_geometry import (REFINERS, plane_homography, pose_from_plane_homography,
                                          refine_plane_pose)
from uav_vs.vision.plane_pose import PlanePoseEstimator
from uav_vs.vision.plane_pose_covariance import fit_covariance

SUITE = 'onboard'
CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'onboard.yaml'
REFERENCE = 'gftt+lk+findHomography loop'
_GFTT = dict(maxCorners=1000, qualityLevel=0.01, minDistance=8, blockSize=19)
_LK = dict(winSize=(19, 19), maxLevel=2,
           criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.03))


def reference_step(prev: np.ndarray, gray: np.ndarray) -> np.ndarray | None:
    """The straightforward frame-to-frame loop the pipeline is compared with."""
    p0 = cv2.goodFeaturesToTrack(prev, **_GFTT)
    p1, _, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, None, **_LK)
    back, _, _ = cv2.calcOpticalFlowPyrLK(gray, prev, p1, None, **_LK)
    good = np.abs(p0 - back).reshape(-1, 2).max(axis=1) < 1.0
    return cv2.findHomography(p0[good], p1[good], cv2.RANSAC, 10.0)[0]


def _ms(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return (time.perf_counter() - t0) * 1e3


def pose_case(width: int, height: int) -> dict:
    """Render the flight at width x height, time the pipeline and the reference."""
    cfg = load_onboard_config(read_params_file(CONFIG))
    scale = width / cfg.camera.width
    K = cfg.camera.K * [[scale], [scale], [1]]
    K[:2, 2] = [(width - 1) / 2, (height - 1) / 2]
    camera = replace(cfg.camera, width=width, height=height, K=K)
    scene = OnboardScene(camera, cfg.camera_to_body, metres_per_pixel=0.005 / scale, seed=0)
    frames = []
    for _, img, R, p in fly(scene, Trajectory(), 15.0):
        ok, jpeg = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        frames.append((cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE), R, p))
    est = PlanePoseEstimator(camera, cfg.params, cfg.camera_to_body)
    est.initialise(frames[0][0], scene.homography(*frames[0][1:]))
    ms, pos_err, att_err, lost = [], [], [], 0
    for gray, R, p in frames[1:]:
        t0 = time.perf_counter()
        r = est.update(gray)
        ms.append((time.perf_counter() - t0) * 1e3)
        if not r.ok:
            lost += 1
            continue
        pos_err.append(np.linalg.norm(r.position - p) / p[2])
        att_err.append(np.degrees(np.linalg.norm(Rotation.from_matrix(R.T @ r.R).as_rotvec())))
    ref_ms = [_ms(reference_step, a[0], b[0]) for a, b in zip(frames, frames[1:])]
    return report(SUITE, f'onboard/pose_{width}x{height}', np.array(ms), REFERENCE,
                  np.array(ref_ms), frames=len(ms), lost=lost, reanchors=est.reanchors,
                  pos_rmse_pct_height=round(100 * float(np.sqrt(np.mean(np.square(pos_err)))), 3),
                  att_rmse_deg=round(float(np.sqrt(np.mean(np.square(att_err)))), 3))


def relocalise_case() -> dict:
    """Losses while the vehicle flies on: recovery by ORB (default) and by SIFT matches."""
    cfg = load_onboard_config(read_params_file(CONFIG))
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=4)
    traj = Trajectory()
    frames: dict[float, tuple] = {}

    def frame(t: float) -> tuple:
        if t not in frames:
            R, p = traj.sample(t)
            ok, jpeg = cv2.imencode('.jpg', scene.render(R, p), [cv2.IMWRITE_JPEG_QUALITY, 90])
            frames[t] = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE), p
        return frames[t]

    out = {}
    for name, params in (('orb', replace(cfg.params, relocalise_features='orb')),
                         ('sift', replace(cfg.params, relocalise_features='sift')),
                         ('off', replace(cfg.params, relocalise_after=0))):
        ms, recovered, wrong = [], 0, 0
        for t_lost in np.arange(1.0, 8.0):
            for gap in (1.0, 1.5):
                est = PlanePoseEstimator(cfg.camera, params, cfg.camera_to_body)
                est.initialise(frame(t_lost)[0], scene.homography(*traj.sample(t_lost)))
                est.lost_frames = round(gap * 15) - 1       # the texture-less frames
                ok = []
                for k in range(3):
                    gray, p = frame(round(t_lost + gap + k / 15, 6))
                    t0 = time.perf_counter()
                    r = est.update(gray)
                    if k == 0:
                        ms.append((time.perf_counter() - t0) * 1e3)
                    ok.append(r.ok)
                    if r.ok and np.linalg.norm(r.position - p) > 0.02 * p[2]:
                        wrong += 1
                recovered += any(ok)
        out[name] = np.array(ms), recovered, wrong
    (orb, n_orb, bad_orb), (sift, n_sift, bad_sift) = out['orb'], out['sift']
    return report(SUITE, 'onboard/relocalise_640x480', orb, 'sift relocalisation', sift,
                  recovered=f'{n_orb}/{len(orb)}', wrong_poses=bad_orb,
                  sift_recovered=f'{n_sift}/{len(sift)}', sift_wrong_poses=bad_sift,
                  without_recovered=f"{out['off'][1]}/{len(orb)}")


def refine_views(K: np.ndarray, count: int = 50, n: int = 100, noise_px: float = 0.5,
                 seed: int = 7) -> list[tuple]:
    """(R, t, plane_xy, pixels, R0, t0) of `count` random views: a camera 1-10 m up looking
    up to 30 deg off the vertical, n plane points seen in a 640x480 image with Gaussian
    pixel noise, the start the DLT homography's pose (as in the pipeline)."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(count):
        eye = np.r_[rng.uniform(-3, 3, 2), rng.uniform(1, 10)]
        off = np.tan(np.radians(rng.uniform(0, 30))) * eye[2]
        a = rng.uniform(0, 2 * np.pi)
        R, t = look_at(eye, eye + [off * np.cos(a), off * np.sin(a), -eye[2]])
        px = rng.uniform([20, 20], [620, 460], (n, 2))
        q = np.c_[px, np.ones(n)] @ np.linalg.inv(plane_homography(K, R, t)).T
        xy, px = q[:, :2] / q[:, 2:], px + rng.normal(0, noise_px, px.shape)
        H, _ = cv2.findHomography(xy, px, 0)
        views.append((R, t, xy, px, *pose_from_plane_homography(K, H)))
    return views


def refine_cases() -> list[dict]:
    """Each refinement on the same views: per-call time, position and angle errors."""
    K = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
    views = refine_views(K)
    times, errors = {}, {}
    for method in REFINERS:
        times[method] = np.concatenate([timeit(lambda v=v: refine_plane_pose(
            K, v[2], v[3], v[4], v[5], method=method), repeat=20, warmup=1) for v in views])
        pos, ang = [], []
        for R, t, xy, px, R0, t0 in views:
            fit = refine_plane_pose(K, xy, px, R0, t0, method=method)
            pos.append(np.linalg.norm(fit.R.T @ fit.t - R.T @ t) / np.linalg.norm(t) * 100)
            ang.append(np.degrees(np.linalg.norm(Rotation.from_matrix(R.T @ fit.R).as_rotvec())))
        errors[method] = dict(position_error_pct_median=round(float(np.median(pos)), 4),
                              angle_error_deg_median=round(float(np.median(ang)), 4))
    return [report(SUITE, f'onboard/pose_refine_{m}', times[m], f'pose_refine_{other}',
                   times[other], **errors[m])
            for m, other in (('lm', 'opencv'), ('opencv', 'lm'))]


def covariance_case() -> dict:
    """The pose's fit covariance per frame (uav_vs.vision.plane_pose_covariance: sigma^2
    (J^T J)^-1 of 100 inliers, to base_link in world), on the refined poses of
    refine_views. Reference: central differences of the whole fit (each of the 200 pixel
    coordinates moved, the pose refined again, the camera's centre and rotation taken);
    the largest relative difference of their standard deviations is the accuracy figure."""
    K = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
    views = []
    for R, t, xy, px, R0, t0 in refine_views(K, count=10):
        fit = refine_plane_pose(K, xy, px, R0, t0, method='opencv')
        views.append((fit.R, fit.t, np.c_[xy, np.zeros(len(xy))], px))

    def analytic(R, t, xyz, px) -> np.ndarray:
        return fit_covariance(K, R, t, xyz, px, -R.T @ t, 0.0)[0]

    def numeric(R, t, xyz, px) -> np.ndarray:
        sigma = fit_covariance(K, R, t, xyz, px, -R.T @ t, 0.0)[1]
        flat, h = px.reshape(-1), 1e-3
        G = np.empty((6, flat.size))
        for j in range(flat.size):
            moved = []
            for step in (h, -h):
                shifted = flat.copy()
                shifted[j] += step
                f = refine_plane_pose(K, xyz, shifted.reshape(px.shape), R, t, method='lm')
                turn = Rotation.from_matrix(f.R.T @ R).as_rotvec()    # world rotation
                moved.append(np.r_[-f.R.T @ f.t, turn])
            G[:, j] = (moved[0] - moved[1]) / (2 * h)
        return sigma ** 2 * G @ G.T

    ms = np.concatenate([timeit(lambda v=v: analytic(*v), repeat=100, warmup=5) for v in views])
    ref_ms = timeit(lambda: numeric(*views[0]), repeat=3, warmup=0)
    worst = 0.0
    for v in views[:5]:
        a, b = np.sqrt(np.diag(analytic(*v))), np.sqrt(np.diag(numeric(*v)))
        worst = max(worst, float(np.max(np.abs(a / b - 1))))
    return report(SUITE, 'onboard/pose_covariance', ms, reference='central differences of the fit',
                  ref_ms=ref_ms, max_sd_difference=round(worst, 4))


def pose_cases() -> list[dict]:
    """Both resolutions, on one OpenCV thread (the target is one core)."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return [pose_case(640, 480), pose_case(1280, 720), *refine_cases(), covariance_case(),
                relocalise_case()]
    finally:
        cv2.setNumThreads(threads)


def main() -> None:
    pose_cases()


if __name__ == '__main__':
    main()
