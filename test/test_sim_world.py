"""The closed-loop world's frames agree (uav_vs.sim.world): the MAVLink vehicle's NED truth,
the ground cameras' `world` (section 3) and the onboard ground plane (section 4).

No ROS: the world renders a known vehicle state, the vision core measures it, and the
measurement must be that state.
"""
import math

import cv2
import numpy as np
import pytest

from conftest import REPO
from uav_vs.sim.ground_scene import GroundScene
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, Truth, VehicleConfig
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.sim.world import SimulatedVehicle, SimWorld, VehicleState, vehicle_state
from uav_vs.vision.body_pose import solve_pose
from uav_vs.vision.colour_model import models_from_params
from uav_vs.vision.ground_config import load_ground_config, read_params_file
from uav_vs.vision.landmarks import LandmarkDetector, centroids
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import PlanePoseEstimator
from uav_vs.vision.triangulation import triangulate

GROUND = read_params_file(REPO / 'config' / 'ground_trinocular.yaml')
ONBOARD = load_onboard_config(read_params_file(REPO / 'config' / 'onboard.yaml'))


@pytest.fixture(scope='module')
def world():
    vehicle = MavlinkVehicle(VehicleConfig(connection='tcpin:127.0.0.1:0'))
    world = SimWorld(SimulatedVehicle(vehicle), GroundScene(load_ground_config(GROUND)),
                     OnboardScene(ONBOARD.camera, ONBOARD.camera_to_body), onboard_min_height=0.3)
    yield world
    world.close()


def _state(position, yaw: float) -> VehicleState:
    truth = Truth(0.0, np.array([position[1], position[0], -position[2]]), np.zeros(3),
                  math.pi / 2 - yaw, 0.0, True, 'GUIDED', True, False)
    return vehicle_state(truth)


def test_ned_truth_is_base_link_in_enu_world():
    """NED (north 2, east 1, down -3), yaw 0 (north) is ENU (1, 2, 3) facing +y, FLU."""
    s = vehicle_state(Truth(0.0, np.array([2.0, 1.0, -3.0]), np.array([0.5, 0.0, -0.2]), 0.0,
                            0.1, True, 'GUIDED', True, False))
    np.testing.assert_allclose(s.position, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(s.velocity, [0.0, 0.5, 0.2])
    assert s.yaw == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(s.R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)   # forward: N
    np.testing.assert_allclose(s.R @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-12)  # left: W


def test_vehicle_at_home_is_at_the_world_origin(world):
    s = world.state()
    np.testing.assert_allclose(s.position, 0.0)
    assert s.yaw == pytest.approx(math.pi / 2)
    assert world.onboard_image(s) is None        # on the ground: no onboard image


@pytest.mark.parametrize('position, yaw', [((0.0, 0.0, 1.5), math.pi / 2),
                                           ((1.0, -0.8, 1.2), 0.3)])
def test_ground_station_measures_the_rendered_state(world, position, yaw):
    """Landmarks found in the rendered ground images, triangulated (eq 24-25), give the
    state's position and heading (eq 26)."""
    state = _state(position, yaw)
    config = load_ground_config(GROUND)
    detector = LandmarkDetector(models_from_params(GROUND))
    pixels = np.stack([centroids(detector.detect(img))[0] for img in world.ground_images(state)])
    pose = solve_pose(config.layout, triangulate(config.cameras, pixels).points)
    assert pose.ok
    assert np.linalg.norm(pose.position - state.position) < 0.02
    assert abs(math.remainder(pose.yaw - state.yaw, 2 * math.pi)) < math.radians(1.0)


def test_onboard_pose_follows_the_rendered_state(world):
    """Initialised at the first state (init.* = that pose), the onboard estimator
    (section 4, eq 27) measures a second state the vehicle moved to."""
    start = _state((0.2, 0.1, 1.5), math.pi / 2)
    moved = _state((0.3, 0.05, 1.45), math.pi / 2 + 0.1)
    estimator = PlanePoseEstimator(ONBOARD.camera, ONBOARD.params, ONBOARD.camera_to_body)
    gray = [cv2.cvtColor(world.onboard_image(s), cv2.COLOR_BGR2GRAY) for s in (start, moved)]
    assert estimator.initialise(gray[0], (start.position, start.quaternion)).ok
    result = estimator.update(gray[1])
    assert result.ok, result.reason
    assert np.linalg.norm(result.position - moved.position) < 0.01
    assert np.degrees(np.arccos(np.clip((np.trace(result.R.T @ moved.R) - 1) / 2, -1, 1))) < 0.5
