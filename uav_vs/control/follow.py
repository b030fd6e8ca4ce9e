"""Following a moving target (chapter section 5, the fourth task): the target tracked in
the onboard images, placed on the ground, becomes the position setpoint.

Each tracker polygon (uav_vs.vision.target_tracking) is placed on the ground plane
(uav_vs.vision.ground_target) from the vehicle pose nearest its image stamp. The camera
is fixed to the body, so the vehicle's roll and pitch move the target in the image as
much as the target's own motion does (1 degree is 2.6 cm on the ground from 1.5 m): with
an attitude source (the autopilot's, from its IMU) the pose's roll and pitch are
replaced by that source's, nearest the image stamp, and the pose gives the position and
yaw; without one (a level-only pose such as the trinocular station's) a tilting vehicle
misplaces the target and can drive the loop into oscillation. An
alpha-beta filter on those ground positions estimates the target's velocity, and the
setpoint is the target's position `lead` seconds ahead at `height` above it, yaw fixed.
The position controller (section 6) flies to that setpoint like to any other.
"""
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_target import TargetOnGround, target_on_ground


@dataclass(frozen=True)
class FollowConfig:
    height: float = 1.5             # setpoint height above the ground, m
    yaw: float = math.pi / 2        # setpoint yaw, rad (ENU)
    lead: float = 0.5               # setpoint ahead of the target by its velocity, s
    max_pose_gap: float = 0.1       # pose and image stamps further apart: not used, s
    velocity_gain: float = 0.2      # beta of the alpha-beta filter (alpha: 2 sqrt(beta) - beta)
    max_speed: float = 2.0          # a target estimated faster is not believed, m/s

    def __post_init__(self) -> None:
        for name in ('height', 'max_pose_gap', 'max_speed'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name}: expected a positive number, got {getattr(self, name)}')
        if not 0 <= self.lead <= 10:
            raise ValueError(f'lead: expected 0 to 10 s, got {self.lead}')
        if not 0 < self.velocity_gain <= 1:
            raise ValueError(f'velocity_gain: expected (0, 1], got {self.velocity_gain}')


@dataclass(frozen=True)
class FollowStep:
    """What one target observation gave: the setpoint (x, y, z, yaw) or why none."""

    setpoint: tuple[float, float, float, float] | None
    target: TargetOnGround | None
    velocity: np.ndarray            # (2,) estimated target velocity, m/s
    reason: str                     # '' when there is a setpoint


class PoseHistory:
    """The last vehicle poses by stamp, to find the one an image was taken at."""

    def __init__(self, size: int = 64) -> None:
        self.poses: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=size)

    def add(self, stamp: float, R_wb: np.ndarray, p_wb: np.ndarray) -> None:
        self.poses.append((stamp, R_wb, p_wb))

    def nearest(self, stamp: float) -> tuple[float, np.ndarray, np.ndarray] | None:
        """(|stamp gap| s, R_wb, p_wb) of the pose stamped closest to `stamp`."""
        if not self.poses:
            return None
        s, R, p = min(self.poses, key=lambda pose: abs(pose[0] - stamp))
        return abs(s - stamp), R, p


class TargetFollower:
    """Target observations and vehicle poses in, position setpoints out."""

    def __init__(self, camera: Camera, camera_to_body: np.ndarray,
                 config: FollowConfig = FollowConfig(), attitude_source: bool = False) -> None:
        """With `attitude_source`, roll and pitch come from on_attitude, not on_pose."""
        self.camera, self.camera_to_body, self.config = camera, camera_to_body, config
        self.poses = PoseHistory()
        self.attitudes = PoseHistory() if attitude_source else None
        self._last: tuple[float, np.ndarray] | None = None    # stamp, filtered position
        self.velocity = np.zeros(2)

    def on_pose(self, stamp: float, R_wb: np.ndarray, p_wb: np.ndarray) -> None:
        self.poses.add(stamp, R_wb, p_wb)

    def on_attitude(self, stamp: float, R_wb: np.ndarray) -> None:
        """The vehicle's attitude (its yaw is not used) from the attitude source."""
        if self.attitudes is not None:
            self.attitudes.add(stamp, R_wb, np.zeros(3))

    def on_target(self, stamp: float, polygon: np.ndarray) -> FollowStep:
        """One tracker polygon (raw pixels, TL TR BR BL centre) of the image stamped `stamp`."""
        c = self.config
        pose = self.poses.nearest(stamp)
        if pose is None or pose[0] > c.max_pose_gap:
            why = 'no vehicle pose yet' if pose is None else \
                f'no vehicle pose within {c.max_pose_gap:g} s of the image'
            return FollowStep(None, None, self.velocity, why)
        R_wb = pose[1]
        if self.attitudes is not None:
            attitude = self.attitudes.nearest(stamp)
            if attitude is None or attitude[0] > c.max_pose_gap:
                why = 'no attitude yet' if attitude is None else \
                    f'no attitude within {c.max_pose_gap:g} s of the image'
                return FollowStep(None, None, self.velocity, why)
            R_wb = with_yaw_of(R_wb, attitude[1])
        target = target_on_ground(self.camera, self.camera_to_body, R_wb, pose[2], polygon)
        if target is None:
            return FollowStep(None, None, self.velocity, 'target rays miss the ground')
        position = self._filter(stamp, target.position)
        x, y = position + c.lead * self.velocity
        return FollowStep((float(x), float(y), c.height, c.yaw), target, self.velocity.copy(), '')

    def _filter(self, stamp: float, measured: np.ndarray) -> np.ndarray:
        """Alpha-beta filter of the target's ground position; restarts after a gap of a
        second or a stamp going back, or when the velocity it implies is not believable."""
        beta = self.config.velocity_gain
        alpha = 2 * math.sqrt(beta) - beta
        last = self._last
        if last is None or not 0 < stamp - last[0] <= 1.0:
            self.velocity = np.zeros(2)
            self._last = (stamp, measured)
            return measured
        dt = stamp - last[0]
        predicted = last[1] + dt * self.velocity
        residual = measured - predicted
        position = predicted + alpha * residual
        velocity = self.velocity + beta / dt * residual
        if np.linalg.norm(velocity) > self.config.max_speed:
            self.velocity, position = np.zeros(2), measured
        else:
            self.velocity = velocity
        self._last = (stamp, position)
        return position


def with_yaw_of(R_yaw: np.ndarray, R_tilt: np.ndarray) -> np.ndarray:
    """The rotation with R_tilt's roll and pitch (its tilt of the body z axis) and R_yaw's
    yaw (Z-Y-X Euler yaw, the heading of body x)."""
    def yaw(R: np.ndarray) -> float:
        return math.atan2(R[1, 0], R[0, 0])

    turn = yaw(R_yaw) - yaw(R_tilt)
    c, s = math.cos(turn), math.sin(turn)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_tilt
