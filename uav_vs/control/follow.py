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

The vehicle's pose comes from another pipeline (three ground cameras) whose latency is
its own and grows on a loaded machine: an image waits until a pose and an attitude
stamped at or after it have arrived (or until an image `max_wait` s newer has), and the
pose at its stamp is interpolated between the two either side of it, as a TF buffer
would, instead of taking whichever pose happened to have arrived.
"""
import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_target import TargetOnGround, target_on_ground


@dataclass(frozen=True)
class FollowConfig:
    height: float = 1.5             # setpoint height above the ground, m
    yaw: float = math.pi / 2        # setpoint yaw, rad (ENU)
    lead: float = 0.5               # setpoint ahead of the target by its velocity, s
    max_pose_gap: float = 0.1       # image this far from the nearest pose: not placed, s
    velocity_gain: float = 0.2      # beta of the alpha-beta filter (alpha: 2 sqrt(beta) - beta)
    max_speed: float = 2.0          # a target estimated faster is not believed, m/s
    max_pose_interval: float = 0.5  # poses either side of an image this close: interpolated, s
    max_wait: float = 0.5           # an image waits for the pose at its stamp this long, s

    def __post_init__(self) -> None:
        for name in ('height', 'max_pose_gap', 'max_speed', 'max_pose_interval', 'max_wait'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name}: expected a positive number, got {getattr(self, name)}')
        if not 0 <= self.lead <= 10:
            raise ValueError(f'lead: expected 0 to 10 s, got {self.lead}')
        if not 0 < self.velocity_gain <= 1:
            raise ValueError(f'velocity_gain: expected (0, 1], got {self.velocity_gain}')


@dataclass(frozen=True)
class FollowStep:
    """What one target observation gave: the setpoint (x, y, z, yaw) or why none."""

    stamp: float                    # the image's, s
    setpoint: tuple[float, float, float, float] | None
    target: TargetOnGround | None
    velocity: np.ndarray            # (2,) estimated target velocity, m/s
    reason: str                     # '' when there is a setpoint


class PoseHistory:
    """The last vehicle poses by stamp, to find the one an image was taken at."""

    def __init__(self, size: int = 64) -> None:
        self.poses: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=size)
        self._newest = -math.inf

    def add(self, stamp: float, R_wb: np.ndarray, p_wb: np.ndarray) -> None:
        self.poses.append((stamp, R_wb, p_wb))
        self._newest = max(self._newest, stamp)

    def newest(self) -> float:
        """The latest stamp added, s (-inf before the first)."""
        return self._newest

    def at(self, stamp: float, max_gap: float, max_interval: float
           ) -> tuple[np.ndarray, np.ndarray] | str:
        """(R_wb, p_wb) at `stamp`: interpolated between the poses either side of it when
        they are at most `max_interval` apart, else the nearest one within `max_gap`;
        otherwise why not."""
        if not self.poses:
            return 'none yet'
        before = max((q for q in self.poses if q[0] <= stamp), default=None, key=lambda q: q[0])
        after = min((q for q in self.poses if q[0] >= stamp), default=None, key=lambda q: q[0])
        if before is not None and after is not None and after[0] - before[0] <= max_interval:
            return interpolate(before, after, stamp)
        s, R, p = min(self.poses, key=lambda q: abs(q[0] - stamp))
        if abs(s - stamp) > max_gap:
            return f'none within {max_gap:g} s of the image'
        return R, p


def interpolate(a: tuple[float, np.ndarray, np.ndarray], b: tuple[float, np.ndarray, np.ndarray],
                stamp: float) -> tuple[np.ndarray, np.ndarray]:
    """The pose at `stamp` between the stamped poses a and b: position linear, rotation
    along the shortest arc (slerp)."""
    (s0, R0, p0), (s1, R1, p1) = a, b
    if s1 == s0:
        return R0, p0
    f = (stamp - s0) / (s1 - s0)
    turn = cv2.Rodrigues(R0.T @ R1)[0]
    return R0 @ cv2.Rodrigues(f * turn)[0], p0 + f * (p1 - p0)


class TargetFollower:
    """Target observations and vehicle poses in, position setpoints out.

    Every input returns the steps it completed, oldest first: an image is placed once
    the pose (and attitude) at its stamp can be known, so a step may come out of a later
    pose rather than of its own image."""

    def __init__(self, camera: Camera, camera_to_body: np.ndarray,
                 config: FollowConfig = FollowConfig(), attitude_source: bool = False) -> None:
        """With `attitude_source`, roll and pitch come from on_attitude, not on_pose."""
        self.camera, self.camera_to_body, self.config = camera, camera_to_body, config
        self.poses = PoseHistory()
        self.attitudes = PoseHistory() if attitude_source else None
        self.waiting: deque[tuple[float, np.ndarray]] = deque()   # images, oldest first
        self._last: tuple[float, np.ndarray] | None = None    # stamp, filtered position
        self.velocity = np.zeros(2)

    def on_pose(self, stamp: float, R_wb: np.ndarray, p_wb: np.ndarray) -> list[FollowStep]:
        self.poses.add(stamp, R_wb, p_wb)
        return self._release()

    def on_attitude(self, stamp: float, R_wb: np.ndarray) -> list[FollowStep]:
        """The vehicle's attitude (its yaw is not used) from the attitude source."""
        if self.attitudes is not None:
            self.attitudes.add(stamp, R_wb, np.zeros(3))
        return self._release()

    def on_target(self, stamp: float, polygon: np.ndarray) -> list[FollowStep]:
        """One tracker polygon (raw pixels, TL TR BR BL centre) of the image stamped `stamp`."""
        self.waiting.append((stamp, polygon))
        return self._release()

    def waiting_for(self) -> str:
        """What the oldest waiting image waits for ('' when none waits)."""
        if not self.waiting:
            return ''
        stamp = self.waiting[0][0]
        late = [name for name, history in (('vehicle pose', self.poses),
                                           ('attitude', self.attitudes))
                if history is not None and history.newest() < stamp]
        return f"waiting for the {' and '.join(late)} at the image's stamp"

    def _release(self) -> list[FollowStep]:
        """Place the waiting images whose pose can be known: one at or after each image's
        stamp has arrived, or an image max_wait newer has (then it is placed on what there is)."""
        steps = []
        while self.waiting:
            stamp, polygon = self.waiting[0]
            arrived = self.poses.newest() >= stamp and (
                self.attitudes is None or self.attitudes.newest() >= stamp)
            if not arrived and self.waiting[-1][0] - stamp < self.config.max_wait:
                break
            self.waiting.popleft()
            steps.append(self._place(stamp, polygon))
        return steps

    def _place(self, stamp: float, polygon: np.ndarray) -> FollowStep:
        c = self.config
        pose = self.poses.at(stamp, c.max_pose_gap, c.max_pose_interval)
        if isinstance(pose, str):
            return FollowStep(stamp, None, None, self.velocity, f'vehicle pose: {pose}')
        R_wb, p_wb = pose
        if self.attitudes is not None:
            attitude = self.attitudes.at(stamp, c.max_pose_gap, c.max_pose_interval)
            if isinstance(attitude, str):
                return FollowStep(stamp, None, None, self.velocity, f'attitude: {attitude}')
            R_wb = with_yaw_of(R_wb, attitude[0])
        target = target_on_ground(self.camera, self.camera_to_body, R_wb, p_wb, polygon)
        if target is None:
            return FollowStep(stamp, None, None, self.velocity, 'target rays miss the ground')
        position = self._filter(stamp, target.position)
        x, y = position + c.lead * self.velocity
        return FollowStep(stamp, (float(x), float(y), c.height, c.yaw), target,
                          self.velocity.copy(), '')

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
