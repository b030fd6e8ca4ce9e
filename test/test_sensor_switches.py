"""The vision cores cope with each camera effect of the `realistic` sensor profile on its
own switch (config/sensors_realistic.yaml, uav_vs.sim.camera_effects): frames rendered
from a known flight, degraded by that one effect at the profile's setting, measured by
the ground station (CamShift per camera, eq 24-26) and the onboard camera (section 4),
and compared with the flight's truth. What the effects do to the closed loop is the
demo's and test_closed_loop's. Unsynchronised ground cameras and partly occluded
landmarks are measured here too; the rest of the profile (latency, wind,
drift, calibration error) has its own tests (test_sim_world_node, test_mavlink_vehicle,
test_calibration_error)."""
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from conftest import REPO
from uav_vs.nodes.sim_world_node import effects_config, ideal_lens
from uav_vs.sim.camera_effects import CameraEffects, CameraLags, Occlusion
from uav_vs.sim.ground_scene import GroundScene, figure_eight
from uav_vs.sim.onboard_scene import OnboardScene, Trajectory, fly
from uav_vs.sim.world import ground_image_velocity, point_image_velocity
from uav_vs.vision.body_pose import quaternion_xyzw, solve_pose
from uav_vs.vision.colour_model import models_from_params
from uav_vs.vision.frame_sync import FrameSync
from uav_vs.vision.ground_config import load_ground_config, read_params_file
from uav_vs.vision.landmarks import LandmarkDetector, centroids
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import PlanePoseEstimator
from uav_vs.vision.triangulation import triangulate

GROUND = read_params_file(REPO / 'config' / 'ground_trinocular.yaml')
ONBOARD = load_onboard_config(read_params_file(REPO / 'config' / 'onboard.yaml'))
REALISTIC = read_params_file(REPO / 'config' / 'sensors_realistic.yaml')
WORLD = read_params_file(REPO / 'config' / 'sim_world.yaml')
SWITCHES = ['noise', 'distortion', 'motion_blur', 'exposure', 'jpeg', 'drops']


def only(switch: str) -> dict:
    """sim_world's parameters with the realistic profile's `switch` alone on."""
    params = {k: v for k, v in REALISTIC.items() if not k.endswith('.enabled')}
    params.update({f'{s}.enabled': s == switch for s in SWITCHES})
    return params


def rms(errors: list[float]) -> float:
    return math.sqrt(np.mean(np.square(errors)))


@pytest.fixture(scope='module')
def ground_scenes():
    config = load_ground_config(GROUND)
    pinhole = replace(config, cameras=[ideal_lens(c) for c in config.cameras])
    return {True: (config, GroundScene(config, noise_sigma=0.0)),
            False: (pinhole, GroundScene(pinhole, noise_sigma=0.0))}


@pytest.mark.parametrize('switch', SWITCHES)
def test_the_ground_station_copes(ground_scenes, switch):
    p = only(switch)
    config, scene = ground_scenes[p['distortion.enabled']]
    seeds = np.random.SeedSequence(11).spawn(len(config.cameras))
    effects = [CameraEffects(effects_config(p, WORLD['ground.noise_sigma']), (c.height, c.width), s)
               for c, s in zip(config.cameras, seeds)]
    detectors = [LandmarkDetector(models_from_params(GROUND)) for _ in config.cameras]
    rate, errors, yaw_errors, frames = 15.0, [], [], 0
    for k in range(60):                     # 4 s of the figure-eight, up to 1.3 m/s
        t = k / rate
        pose, ahead = figure_eight(t), figure_eight(t + 1e-3)
        velocity = (ahead.position - pose.position) / 1e-3
        images, _ = scene.render(pose)
        pixels = []
        for cam, fx, detector, image in zip(config.cameras, effects, detectors, images):
            frame = fx(image, point_image_velocity(cam, pose.position, velocity), 1 / rate)
            frames += frame is not None
            pixels.append(centroids(detector.detect(frame))[0] if frame is not None
                          else np.full((len(config.layout), 2), np.nan))
        solved = solve_pose(config.layout, triangulate(config.cameras, np.stack(pixels)).points)
        if solved.ok:
            errors.append(np.linalg.norm(solved.position - pose.position))
            yaw_errors.append(math.remainder(solved.yaw - pose.yaw, 2 * math.pi))
    assert len(errors) >= 0.9 * 60, (switch, len(errors), frames)
    assert rms(errors) < 0.02 and max(errors) < 0.06, (switch, rms(errors), max(errors))
    assert rms(yaw_errors) < math.radians(1.5), (switch, np.degrees(rms(yaw_errors)))


@pytest.mark.parametrize('switch', SWITCHES)
def test_the_onboard_camera_copes(switch):
    p = only(switch)
    camera = ONBOARD.camera if p['distortion.enabled'] else ideal_lens(ONBOARD.camera)
    scene = OnboardScene(camera, ONBOARD.camera_to_body, noise_sigma=0.0)
    effects = CameraEffects(effects_config(p, WORLD['onboard.noise_sigma']), (camera.height, camera.width),
                            np.random.SeedSequence(12))
    estimator = PlanePoseEstimator(camera, ONBOARD.params, ONBOARD.camera_to_body)
    trajectory, rate = Trajectory(), 10.0
    errors, lost = [], 0
    for t, image, R, position in fly(scene, trajectory, rate, duration=7.0):
        velocity = (trajectory.sample(t + 1e-3)[1] - position) / 1e-3
        frame = effects(image, ground_image_velocity(scene, R, position, velocity), 1 / rate)
        if frame is None:
            continue
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        if not estimator.initialised:
            assert estimator.initialise(gray, (position, quaternion_xyzw(R))).ok
            continue
        result = estimator.update(gray)
        if result.ok:
            errors.append(np.linalg.norm(result.position - position))
        else:
            lost += 1
    assert lost <= 2 and len(errors) >= 60, (switch, lost, len(errors))
    assert rms(errors) < 0.02 and max(errors) < 0.05, (switch, rms(errors), max(errors))


def test_the_ground_station_copes_with_unsynchronised_cameras(ground_scenes):
    # Cameras 2 and 3 capture up to lag + jitter after camera 1, each rendered at its own
    # instant of the flight; the frame set (grouped as trinocular_pose_node groups it) is
    # stamped with camera 1's capture, and its pose is compared with the truth of that
    # instant: the vehicle moved by up to 1.3 m/s * 6 ms between the captures.
    config, scene = ground_scenes[True]
    lag, jitter = REALISTIC['unsynchronised.lag'], REALISTIC['unsynchronised.jitter']
    clocks = CameraLags(len(config.cameras), lag, jitter, np.random.default_rng(13))
    assert 0 < clocks.lags.max() <= lag
    tolerance = int(GROUND['trinocular.sync_tolerance'] * 1e9)
    sync = FrameSync(len(config.cameras), tolerance, int(GROUND['trinocular.max_wait'] * 1e9))
    detectors = [LandmarkDetector(models_from_params(GROUND)) for _ in config.cameras]
    rate, truth, errors, spreads = 15.0, {}, [], []
    for k in range(60):
        t = k / rate
        lags = clocks.sample()
        spreads.append(lags.max())
        truth[round(t * 1e9)] = figure_eight(t)
        images, _ = scene.render([figure_eight(t + dt) for dt in lags])
        for c, (image, dt) in enumerate(zip(images, lags)):
            pixels = centroids(detectors[c].detect(image))[0]
            for frame_set in sync.add(c, round((t + dt) * 1e9), pixels):
                assert frame_set.n_present == len(config.cameras)
                pose = truth[frame_set.stamp_ns]           # camera 1's capture instant
                solved = solve_pose(config.layout, triangulate(config.cameras,
                                                               np.stack(frame_set.items)).points)
                assert solved.ok
                errors.append(np.linalg.norm(solved.position - pose.position))
    assert max(spreads) > 0.5 * lag                   # the cameras were apart
    assert len(errors) >= 58 and sync.dropped == 0, (len(errors), sync.dropped)
    assert rms(errors) < 0.02 and max(errors) < 0.06, (rms(errors), max(errors))


def test_the_ground_station_copes_with_partly_occluded_landmarks(ground_scenes):
    # The realistic profile's occluders (each landmark, camera and frame on its own),
    # drawn over the exact render of a known flight; the station measures through them.
    config, scene = ground_scenes[True]
    occlusion = Occlusion(REALISTIC['occlusion.probability'], REALISTIC['occlusion.fraction'],
                          np.random.default_rng(14))
    detectors = [LandmarkDetector(models_from_params(GROUND)) for _ in config.cameras]
    rate, errors, yaw_errors, occluded = 15.0, [], [], 0
    for k in range(60):
        pose = figure_eight(k / rate)
        images, info = scene.render(pose)
        discs = scene.landmark_discs(pose)      # where the occluders go: the rendered spheres
        assert np.nanmax(np.linalg.norm(discs[..., :2] - info.full_centroid, axis=2)) < 0.1
        pixels = []
        for detector, image, camera_discs in zip(detectors, images, discs):
            frame, count = occlusion(image, camera_discs)
            occluded += count
            pixels.append(centroids(detector.detect(frame))[0])
        solved = solve_pose(config.layout, triangulate(config.cameras, np.stack(pixels)).points)
        if solved.ok:
            errors.append(np.linalg.norm(solved.position - pose.position))
            yaw_errors.append(math.remainder(solved.yaw - pose.yaw, 2 * math.pi))
    expected = REALISTIC['occlusion.probability'] * 60 * len(config.cameras) * len(config.layout)
    assert occluded > 0.5 * expected, (occluded, expected)
    assert len(errors) >= 0.9 * 60, len(errors)
    assert rms(errors) < 0.02 and max(errors) < 0.06, (rms(errors), max(errors))
    assert rms(yaw_errors) < math.radians(1.5), np.degrees(rms(yaw_errors))
