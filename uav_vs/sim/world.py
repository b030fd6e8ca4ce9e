"""The closed-loop world (chapter section 5): what the cameras see of the simulated vehicle.

The vehicle is either the MAVLink simulator (uav_vs.sim.mavlink_vehicle, through
SimulatedVehicle) or ArduPilot SITL (uav_vs.sim.sitl_truth), flying in a local NED frame
with home on the ground at the origin. `world` (ENU, z up) has that same origin, so one
point in space has one set of coordinates for the autopilot (NED), the ground cameras'
calibration (eq 16) and the onboard camera's ground plane z = 0 (section 4); the
conversion is uav_vs.autopilot.frames. The MAVLink simulator has no attitude dynamics:
it stays level, and base_link's attitude is its heading alone; SITL's vehicle tilts.

Several vehicles can fly in one world: each autopilot's local frame has its origin where
that vehicle stood at boot (its home), at `start` (x, y) in `world`, which each truth
source adds. A SimWorld's `others` are further vehicles the ground cameras see beside its
own, each with its own landmarks (GroundScene's `others`).

`SimWorld` samples the vehicle's true state and renders the ground trinocular cameras
(uav_vs.sim.ground_scene, section 3) and the down-looking onboard camera
(uav_vs.sim.onboard_scene, section 4) at that state; the onboard camera also sees the
moving ground target when the world has one (uav_vs.sim.ground_target, section 5),
which starts its path when the world starts.
"""
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from uav_vs.autopilot.frames import ned_to_enu, yaw_ned_to_enu
from uav_vs.sim.ground_scene import GroundScene, Pose, rot_z
from uav_vs.sim.ground_target import GroundTarget
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, Truth
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.vision.camera import Camera
from uav_vs.vision.body_pose import quaternion_xyzw

_VELOCITY_STEP = 1e-3        # s, finite difference of the image-plane velocities


@dataclass(frozen=True)
class VehicleState:
    """The vehicle's truth in ROS frames: base_link (FLU) in world (ENU)."""

    time: float               # time.monotonic() of the sample, s
    position: np.ndarray      # (3,) m
    velocity: np.ndarray      # (3,) m/s
    yaw: float                # heading, rad (0 = east, counter-clockwise)
    R: np.ndarray             # (3, 3) base_link -> world
    armed: bool
    mode: str
    flying: bool

    @property
    def quaternion(self) -> np.ndarray:
        """Orientation of base_link in world, (x, y, z, w)."""
        return quaternion_xyzw(self.R)


def vehicle_state(truth: Truth, start: Sequence[float] = (0.0, 0.0)) -> VehicleState:
    """The simulator's NED truth as base_link in world (REP-103/105), its home at `start`."""
    yaw = float(yaw_ned_to_enu(truth.yaw))
    position = ned_to_enu(truth.position) + [start[0], start[1], 0.0]
    return VehicleState(truth.time, position, ned_to_enu(truth.velocity), yaw,
                        rot_z(yaw), truth.armed, truth.mode, truth.flying)


def point_image_velocity(camera: Camera, position: np.ndarray, velocity: np.ndarray
                         ) -> np.ndarray:
    """Image-plane velocity (px/s) of a world point moving at `velocity` (m/s) in a fixed
    camera (eq 15-16): what blurs it during an exposure."""
    h = _VELOCITY_STEP
    return np.diff(camera.project(np.stack([position, position + h * velocity])), axis=0)[0] / h


def ground_image_velocity(scene: OnboardScene, R_wb: np.ndarray, p_wb: np.ndarray,
                          velocity: np.ndarray) -> np.ndarray:
    """Image-plane velocity (px/s) of the ground point at the principal point of the onboard
    camera, the body translating at `velocity` (m/s), through the plane homography (eq 27)."""
    h, c = _VELOCITY_STEP, scene.camera.K[:2, 2]
    ground = np.linalg.solve(scene.homography(R_wb, p_wb), [*c, 1.0])
    moved = scene.homography(R_wb, p_wb + h * velocity) @ ground
    return (moved[:2] / moved[2] - c) / h


class Vehicle(Protocol):
    """Where the world's vehicle truth comes from."""

    def state(self) -> VehicleState: ...

    def close(self) -> None: ...


class SimulatedVehicle:
    """The MAVLink vehicle simulator as the world's vehicle."""

    def __init__(self, vehicle: MavlinkVehicle, start: Sequence[float] = (0.0, 0.0)) -> None:
        self.vehicle, self.start = vehicle, tuple(start)

    def state(self) -> VehicleState:
        return vehicle_state(self.vehicle.truth(), self.start)

    def close(self) -> None:
        self.vehicle.stop()


class SimWorld:
    """The vehicle's true state and the ground and onboard cameras' views of it."""

    def __init__(self, vehicle: Vehicle, ground: GroundScene, onboard: OnboardScene,
                 onboard_min_height: float, target: GroundTarget | None = None,
                 others: Sequence[Vehicle] = ()) -> None:
        if len(ground.bodies) != 1 + len(others):
            raise ValueError(f'{len(ground.bodies)} vehicles drawn for {1 + len(others)} flying')
        self.vehicle = vehicle
        self.others = list(others)
        self.ground = ground
        self.onboard = onboard
        self.onboard_min_height = onboard_min_height
        self.target = target
        self._t0 = vehicle.state().time

    def state(self) -> VehicleState:
        return self.vehicle.state()

    def ground_poses(self, state: VehicleState, lags: np.ndarray | None = None
                     ) -> Pose | list[Pose]:
        """The vehicle's pose each ground camera sees: `state`'s; with `lags`, camera k's
        lags[k] s later (moved on by its velocity, its attitude kept: lags are ms)."""
        t = state.time - self._t0
        if lags is None:
            return Pose(t, state.position, state.yaw, state.R)
        return [Pose(t + dt, state.position + dt * state.velocity, state.yaw, state.R)
                for dt in lags]

    def other_states(self) -> list[VehicleState]:
        """The other vehicles' truth now, in `others` order."""
        return [o.state() for o in self.others]

    def ground_images(self, state: VehicleState, lags: np.ndarray | None = None,
                      others: Sequence[VehicleState] = ()) -> list[np.ndarray]:
        """One BGR image per ground camera, in `cameras.names` order (section 3), each
        at its `ground_poses`, with the other vehicles at `others` (other_states)."""
        images, _ = self.ground.render_fleet(self._fleet_poses(state, lags, others))
        return images

    def ground_landmark_discs(self, state: VehicleState, lags: np.ndarray | None = None,
                              others: Sequence[VehicleState] = ()) -> np.ndarray:
        """Each landmark's image disc in each ground camera (GroundScene.landmark_discs),
        the other vehicles' after this one's."""
        return np.concatenate([self.ground.landmark_discs(poses, vehicle=v) for v, poses
                               in enumerate(self._fleet_poses(state, lags, others))], axis=1)

    def _fleet_poses(self, state: VehicleState, lags: np.ndarray | None,
                     others: Sequence[VehicleState]) -> list[Pose | list[Pose]]:
        return [self.ground_poses(s, lags) for s in (state, *others)]

    def ground_image_velocities(self, state: VehicleState) -> list[np.ndarray]:
        """Image-plane velocity (px/s) of the vehicle in each ground camera."""
        return [point_image_velocity(cam, state.position, state.velocity)
                for cam in self.ground.cameras]

    def onboard_image_velocity(self, state: VehicleState) -> np.ndarray:
        """Image-plane velocity (px/s) of the ground under the onboard camera."""
        return ground_image_velocity(self.onboard, state.R, state.position, state.velocity)

    def onboard_height(self, state: VehicleState) -> float:
        """Height of the onboard camera's optical centre above the ground plane, m."""
        return float((state.position + state.R @ self.onboard.camera_to_body[:3, 3])[2])

    def onboard_image(self, state: VehicleState) -> np.ndarray | None:
        """The down-looking camera's BGR image (section 4); None while the camera is lower
        than `onboard_min_height` (on the ground it would look into the ground plane)."""
        if self.onboard_height(state) < self.onboard_min_height:
            return None
        decals = () if self.target is None else (self.target.decal(state.time - self._t0),)
        return self.onboard.render(state.R, state.position, decals=decals)

    def target_pose(self, state: VehicleState) -> tuple[np.ndarray, float] | None:
        """The ground target's centre (x, y), m, and heading, rad, at `state`'s time."""
        return None if self.target is None else self.target.path.pose(state.time - self._t0)

    def close(self) -> None:
        for vehicle in (self.vehicle, *self.others):
            vehicle.close()
