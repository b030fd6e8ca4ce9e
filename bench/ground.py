"""Ground trinocular benchmarks (chapter section 3).

`CASES` is the suite: each entry is a function that times one case and reports it with
bench.common.report. Other ground cases (detection, latency) live in their own modules
and are appended to CASES here.
"""
from itertools import cycle
from typing import Callable

import numpy as np

from bench.common import report, timeit
from uav_vs.sim.ground_scene import GroundScene, figure_eight
from uav_vs.vision.body_pose import solve_pose
from uav_vs.vision.ground_config import (GroundConfig, default_config_path, load_ground_config,
                                        read_params_file)
from uav_vs.vision.pose_covariance import PixelNoise, landmark_covariances, pose_covariance
from uav_vs.vision.triangulation import triangulate

SUITE = 'ground'
PIXEL_SIGMA = 0.5


def noisy_frame_sets() -> tuple[GroundConfig, list, list[np.ndarray]]:
    """The default config, the figure-eight's poses every 0.05 s for 10 s, and each one's
    centroids: exact projections of the landmarks with 0.5 px Gaussian noise."""
    cfg = load_ground_config(read_params_file(default_config_path()))
    rng = np.random.default_rng(0)
    poses = [figure_eight(t) for t in np.arange(0.0, 10.0, 0.05)]
    sets = [np.stack([c.project(cfg.layout @ p.R.T + p.position) for c in cfg.cameras])
            + rng.normal(0.0, PIXEL_SIGMA, (len(cfg.cameras), len(cfg.layout), 2))
            for p in poses]
    return cfg, poses, sets


def triangulation() -> None:
    """Triangulation (eq 24-25) + pose (eq 26) per frame set of 4 landmarks in 3 cameras,
    eq 25 least squares vs OpenCV's DLT, on exact projections of the figure-eight with
    0.5 px Gaussian centroid noise; mean position and yaw errors as accuracy figures."""
    cfg, poses, sets = noisy_frame_sets()

    def run(method: str) -> tuple[np.ndarray, dict]:
        frames = cycle(sets)

        def one() -> None:
            solve_pose(cfg.layout, triangulate(cfg.cameras, next(frames), method).points)
        ms = timeit(one, repeat=1000, warmup=20)
        err_pos, err_yaw = [], []
        for p, px in zip(poses, sets):
            pose = solve_pose(cfg.layout, triangulate(cfg.cameras, px, method).points)
            err_pos.append(np.linalg.norm(pose.position - p.position))
            err_yaw.append(abs(np.angle(np.exp(1j * (pose.yaw - p.yaw)))))
        return ms, {'pos_err_mean_mm': round(1e3 * float(np.mean(err_pos)), 2),
                    'yaw_err_mean_deg': round(float(np.degrees(np.mean(err_yaw))), 3)}

    ms, acc = run('lsq')
    ref_ms, ref_acc = run('opencv')
    report(SUITE, 'ground/triangulation', ms, reference='cv2.triangulatePoints DLT',
           ref_ms=ref_ms, pixel_sigma=PIXEL_SIGMA, **acc,
           **{f'ref_{k}': v for k, v in ref_acc.items()})


def covariance() -> None:
    """The ground pose's covariance per frame set (uav_vs.vision.pose_covariance: pixel
    noise pooled from the residuals, each landmark's sigma^2 (J^T J)^-1, eq 26
    linearised), on the frame sets of `triangulation`, after their triangulation and pose.
    Reference: the same covariance from central differences of the whole chain (each of
    the 24 centroid coordinates moved, triangulated and solved again); the largest
    relative difference of their standard deviations is the accuracy figure."""
    cfg, _, sets = noisy_frame_sets()
    solved = [(triangulate(cfg.cameras, px), px) for px in sets]
    solved = [(tri, solve_pose(cfg.layout, tri.points), px) for tri, px in solved]
    noise = PixelNoise()

    def analytic(tri, pose, px) -> np.ndarray:
        cov_x = landmark_covariances(cfg.cameras, tri, noise.update(tri))
        return pose_covariance(cfg.layout, pose, cov_x)

    def numeric(tri, pose, px) -> np.ndarray:
        h, flat = 1e-3, px.reshape(-1)
        G = np.empty((4, flat.size))
        for j in range(flat.size):
            moved = []
            for step in (h, -h):
                shifted = flat.copy()
                shifted[j] += step
                tri_j = triangulate(cfg.cameras, shifted.reshape(px.shape))
                p = solve_pose(cfg.layout, tri_j.points)
                moved.append(np.append(p.position, p.yaw))
            G[:, j] = (moved[0] - moved[1]) / (2 * h)
        return noise.sigma ** 2 * G @ G.T

    frames = cycle(solved)
    ms = timeit(lambda: analytic(*next(frames)), repeat=1000, warmup=20)
    ref_ms = timeit(lambda: numeric(*next(frames)), repeat=50, warmup=2)
    worst = 0.0
    for item in solved[::10]:
        a = np.sqrt(np.diag(analytic(*item))[[0, 1, 2, 5]])
        b = np.sqrt(np.diag(numeric(*item)))
        worst = max(worst, float(np.max(np.abs(a / b - 1))))
    report(SUITE, 'ground/pose_covariance', ms, reference='central differences of the chain',
           ref_ms=ref_ms, max_sd_difference=round(worst, 4))


def render() -> None:
    """Simulator: one frame set of three 640x480 ground-camera images (ray-cast vehicle,
    textured ground, lighting, noise, distortion), the cost of a live 30 Hz simulation."""
    scene = GroundScene(load_ground_config(read_params_file(default_config_path())))
    poses = cycle([figure_eight(t) for t in np.arange(0.0, 10.0, 0.05)])
    ms = timeit(lambda: scene.render(next(poses)), repeat=200, warmup=5)
    report(SUITE, 'ground/render', ms, cameras=len(scene.cameras))


CASES: list[Callable[[], None]] = [triangulation, covariance, render]


def main() -> None:
    for case in CASES:
        case()


if __name__ == '__main__':
    main()
