"""Two vehicles in the ground cameras' view (chapter section 3 with a fleet): each carries
its own landmark colours (config/ground_trinocular.yaml's and config/landmarks_uav2.yaml's),
the simulator draws both into the same images (uav_vs.sim.ground_scene.render_fleet), and
one detector per camera and vehicle (eq 18-19), the triangulation (eq 24-25) and eq 26 give
each vehicle's pose. Truth: the poses drawn, and where each landmark was rendered."""
import math

import numpy as np
import pytest

from conftest import REPO
from uav_vs.sim.ground_scene import GroundScene, Pose, figure_eight
from uav_vs.vision.body_pose import solve_pose
from uav_vs.vision.colour_model import models_from_params
from uav_vs.vision.ground_config import load_ground_config, read_params_files
from uav_vs.vision.landmarks import LandmarkDetector, centroids
from uav_vs.vision.triangulation import triangulate

FILES = {'uav1': [REPO / 'config' / 'ground_trinocular.yaml'],
         'uav2': [REPO / 'config' / 'ground_trinocular.yaml',
                  REPO / 'config' / 'landmarks_uav2.yaml']}
PARAMS = {name: read_params_files(paths) for name, paths in FILES.items()}
CONFIGS = {name: load_ground_config(p) for name, p in PARAMS.items()}
RATE, FRAMES = 15.0, 75


def second_vehicle(t: float) -> Pose:
    """The second vehicle: a smaller figure-eight half a period behind, 0.8 m north and
    0.5 m above the first one's, so it crosses in front of and behind it in the views."""
    pose = figure_eight(t + 5.0, size=(1.2, 0.4), yaw0=-1.0)
    return Pose(pose.t, pose.position + [0.0, 0.8, 0.5], pose.yaw, pose.R)


def test_the_second_vehicles_colours_are_apart_from_the_first_ones():
    """No hue is in both vehicles' ranges: a detector can never take the other's landmark."""
    def hues(config) -> set[int]:
        return {h for lo, hi in config.hue
                for h in (range(lo, hi + 1) if lo <= hi else [*range(lo, 180), *range(hi + 1)])}
    assert not hues(CONFIGS['uav1']) & hues(CONFIGS['uav2'])
    assert np.array_equal(CONFIGS['uav1'].layout, CONFIGS['uav2'].layout)
    assert [c.name for c in CONFIGS['uav2'].cameras] == [c.name for c in CONFIGS['uav1'].cameras]


def test_each_vehicles_pose_comes_from_its_own_landmarks():
    """75 frames of both flying: every pose within 2 cm RMS and 1 degree RMS of its truth
    (the one-vehicle target of test_ground_scene), and no detection on the other
    vehicle: each centroid found lies on its own landmark's image disc."""
    first = CONFIGS['uav1']
    scene = GroundScene(first, others=[CONFIGS['uav2']])
    detectors = {name: [LandmarkDetector(models_from_params(p)) for _ in first.cameras]
                 for name, p in PARAMS.items()}
    errors = {name: [] for name in CONFIGS}
    yaw_errors = {name: [] for name in CONFIGS}
    found, strays, crossings = 0, 0, 0
    for k in range(FRAMES):
        truth = {'uav1': figure_eight(k / RATE), 'uav2': second_vehicle(k / RATE)}
        images, _ = scene.render_fleet([truth['uav1'], truth['uav2']])
        discs = [scene.landmark_discs(truth[name], vehicle=v) for v, name in enumerate(truth)]
        crossings += overlap(*discs)
        for (name, config), disc in zip(CONFIGS.items(), discs):
            pixels = np.stack([centroids(d.detect(img))[0]
                               for d, img in zip(detectors[name], images)])
            seen = ~np.isnan(pixels[..., 0])
            found += seen.sum()
            off = np.linalg.norm(pixels[seen] - disc[seen][:, :2], axis=1)
            strays += int((off > disc[seen][:, 2]).sum())
            pose = solve_pose(config.layout, triangulate(config.cameras, pixels).points)
            if pose.ok:
                errors[name].append(np.linalg.norm(pose.position - truth[name].position))
                yaw_errors[name].append(math.remainder(pose.yaw - truth[name].yaw, 2 * math.pi))
    assert crossings > 0, 'the vehicles never overlapped in a view: the test shows no crosstalk'
    assert found > 0.8 * FRAMES * 2 * 3 * 4 and strays == 0, (found, strays)
    for name in CONFIGS:
        rms = math.sqrt(np.mean(np.square(errors[name])))
        yaw_rms = math.degrees(math.sqrt(np.mean(np.square(yaw_errors[name]))))
        print(f'{name}: {len(errors[name])} poses, {100 * rms:.2f} cm RMS, {yaw_rms:.2f} deg RMS')
        assert len(errors[name]) >= 0.95 * FRAMES, (name, len(errors[name]))
        assert rms <= 0.02 and yaw_rms <= 1.0, (name, rms, yaw_rms)


def overlap(first: np.ndarray, second: np.ndarray) -> int:
    """Cameras in which two vehicles' landmark discs come within 40 px of each other."""
    gaps = np.linalg.norm(first[:, :, None, :2] - second[:, None, :, :2], axis=-1)
    return int((np.nanmin(gaps.reshape(len(first), -1), axis=1) < 40).sum())


def test_a_fleet_is_drawn_from_one_pose_per_vehicle():
    scene = GroundScene(CONFIGS['uav1'], others=[CONFIGS['uav2']], noise_sigma=0.0)
    with pytest.raises(ValueError, match='1 poses for 2 vehicles'):
        scene.render_fleet([figure_eight(0.0)])
    alone, _ = GroundScene(CONFIGS['uav1'], noise_sigma=0.0).render(figure_eight(0.0))
    both, infos = scene.render_fleet([figure_eight(0.0), second_vehicle(0.0)])
    assert len(infos) == 2 and infos[1].visible.shape == (3, 4)
    for a, b, info in zip(alone, both, infos[1].full_centroid):   # the second one is drawn
        for u, v in info[~np.isnan(info[:, 0])].astype(int):
            assert np.abs(a[v, u].astype(int) - b[v, u]).max() > 30
