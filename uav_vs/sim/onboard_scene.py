"""Down-looking onboard camera over a textured ground plane, with ground truth (section 4).

The ground is the plane z = 0 of `world` (ENU). Its texture is the two real aerial
photographs `assets/aero1.jpg | aero3.jpg` side by side, mirrored without end
(BORDER_REFLECT), at `metres_per_pixel`; texture pixel (u, v) lies at
X = (u - u0) m, Y = -(v - v0) m (image up is north), with (u0, v0) the centre of aero1.

A frame is rendered by exact projection: the plane-to-image homography of the true
pose, K [r1 r2 t] (eq 27), composed with the texture-to-plane scale; lens distortion
(plumb bob) by a remap through the camera's ideal rays. Then optional defocus blur and
Gaussian sensor noise
(uav_vs.sim.camera_effects.GaussianNoise).

The vehicle flies `Trajectory`: minimum-jerk segments between waypoints, yaw
interpolated the same way, roll and pitch those of a multirotor whose thrust produces
the acceleration.
"""
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from uav_vs.sim.camera_effects import GaussianNoise
from uav_vs.sim.ground_target import GroundTarget
from uav_vs.vision.camera import Camera
from uav_vs.vision.plane_pose import camera_pose, plane_homography

ASSETS = Path(__file__).resolve().parent / 'assets'
GRAVITY = 9.80665


def ground_texture() -> np.ndarray:
    """The ground photo: aero1 | aero3 side by side (BGR, 480 x 1280)."""
    return np.hstack([cv2.imread(str(ASSETS / 'aero1.jpg')), cv2.imread(str(ASSETS / 'aero3.jpg'))])


class OnboardScene:
    """Renders what a camera on the vehicle sees of the textured ground plane."""

    def __init__(self, camera: Camera, camera_to_body: np.ndarray | None,
                 texture: np.ndarray | None = None, metres_per_pixel: float = 0.005,
                 origin_px: tuple[float, float] = (319.5, 239.5), noise_sigma: float = 1.5,
                 seed: int = 0) -> None:
        self.camera = camera
        self.camera_to_body = camera_to_body
        self.texture = ground_texture() if texture is None else texture
        self.mpp = metres_per_pixel
        u0, v0 = origin_px
        # Plane (X, Y, 1) -> texture (u, v, 1).
        self.plane_to_texture = np.array([[1 / self.mpp, 0, u0], [0, -1 / self.mpp, v0], [0, 0, 1]])
        self.noise = GaussianNoise(noise_sigma, (camera.height, camera.width),
                                   np.random.default_rng(seed))
        self._rays = None
        if np.any(camera.D):
            # Ideal normalised coordinates of every distorted pixel, for the remap.
            u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
            n = camera.normalize(np.column_stack([u.ravel(), v.ravel()]).astype(np.float64))
            self._rays = n.reshape(camera.height, camera.width, 2).astype(np.float32)

    def texture_to_plane(self, uv: np.ndarray) -> np.ndarray:
        """Texture pixels (N,2) to plane points (N,2), metres."""
        S = np.linalg.inv(self.plane_to_texture)
        return uv @ S[:2, :2].T + S[:2, 2]

    def homography(self, R_wb: np.ndarray, p_wb: np.ndarray) -> np.ndarray:
        """Plane-to-ideal-image homography K [r1 r2 t] of the body pose (eq 27)."""
        return plane_homography(self.camera.K, *camera_pose(R_wb, p_wb, self.camera_to_body))

    def render(self, R_wb: np.ndarray, p_wb: np.ndarray, blur_sigma: float = 0.0,
               decals: tuple[tuple[np.ndarray, np.ndarray], ...] = ()) -> np.ndarray:
        """The camera image (BGR uint8) with the body at world-from-body R_wb, p_wb.

        `decals` are pictures lying on the ground over the texture (a target): each a BGR
        image and the 3x3 homography from its pixels to plane points (x, y, 1), m."""
        H_img_plane = self.homography(R_wb, p_wb)
        img = self._warp(self.texture, H_img_plane @ np.linalg.inv(self.plane_to_texture),
                         cv2.BORDER_REFLECT)
        for picture, plane_from_picture in decals:
            H = H_img_plane @ plane_from_picture
            inside = self._warp(np.full(picture.shape[:2], 255, np.uint8), H,
                                cv2.BORDER_CONSTANT)
            warped = self._warp(picture, H, cv2.BORDER_CONSTANT).astype(np.float32)
            alpha = (inside.astype(np.float32) / 255.0)[..., None]
            img = (img * (1.0 - alpha) + warped * alpha + 0.5).astype(np.uint8)
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        return self.noise(img)

    def _warp(self, source: np.ndarray, H_img_source: np.ndarray, border: int) -> np.ndarray:
        """`source` seen through the camera, given the homography from its pixels to ideal
        image pixels; through the lens distortion when the camera has one."""
        cam = self.camera
        if self._rays is None:
            return cv2.warpPerspective(source, H_img_source, (cam.width, cam.height),
                                       flags=cv2.INTER_LINEAR, borderMode=border)
        # Ideal normalised coordinates -> source pixel: (K^-1 H_img_source)^-1.
        M = np.linalg.inv(np.linalg.solve(cam.K, H_img_source))
        return cv2.remap(source, cv2.perspectiveTransform(self._rays, M), None,
                         cv2.INTER_LINEAR, borderMode=border)


@dataclass(frozen=True)
class Waypoint:
    """Where base_link is at time t: position (m, world ENU) and yaw (rad, about z)."""

    t: float
    position: tuple[float, float, float]
    yaw: float


# Hover at 1 m after take-off, climb to 3 m, move east and north while turning, descend.
DEFAULT_WAYPOINTS = (
    Waypoint(0.0, (0.0, 0.0, 1.0), 0.0),
    Waypoint(0.5, (0.0, 0.0, 1.0), 0.0),
    Waypoint(3.0, (0.0, 0.0, 3.0), 0.0),
    Waypoint(5.5, (2.5, -0.8, 3.0), np.radians(60)),
    Waypoint(7.5, (3.5, 0.8, 2.5), np.radians(20)),
    Waypoint(10.0, (3.0, 0.5, 1.5), np.radians(-20)),
)


class Trajectory:
    """Rest-to-rest minimum-jerk flight through waypoints; attitude from the acceleration."""

    def __init__(self, waypoints: tuple[Waypoint, ...] = DEFAULT_WAYPOINTS) -> None:
        if len(waypoints) < 2 or any(b.t <= a.t for a, b in zip(waypoints, waypoints[1:])):
            raise ValueError('waypoints: need at least two, with increasing times')
        self.waypoints = waypoints

    @property
    def duration(self) -> float:
        return self.waypoints[-1].t - self.waypoints[0].t

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """World-from-body rotation R_wb (3x3) and position (3,) at time t (clamped)."""
        wp = self.waypoints
        t = min(max(t, wp[0].t), wp[-1].t)
        k = max(i for i in range(len(wp) - 1) if wp[i].t <= t)
        a, b = wp[k], wp[k + 1]
        T = b.t - a.t
        s = (t - a.t) / T
        blend = 10 * s**3 - 15 * s**4 + 6 * s**5          # minimum-jerk profile
        blend_dd = (60 * s - 180 * s**2 + 120 * s**3) / T**2
        p0, p1 = np.array(a.position), np.array(b.position)
        position = p0 + (p1 - p0) * blend
        accel = (p1 - p0) * blend_dd
        yaw = a.yaw + (b.yaw - a.yaw) * blend
        # Thrust along body z balances gravity and produces the acceleration; body x
        # is chosen so that the Z-Y-X Euler yaw (heading of body x) is `yaw`.
        z_b = accel + [0.0, 0.0, GRAVITY]
        z_b /= np.linalg.norm(z_b)
        x_b = np.cross([-np.sin(yaw), np.cos(yaw), 0.0], z_b)
        x_b /= np.linalg.norm(x_b)
        return np.column_stack([x_b, np.cross(z_b, x_b), z_b]), position


def fly(scene: OnboardScene, trajectory: Trajectory, rate: float, duration: float | None = None,
        target: GroundTarget | None = None
        ) -> Iterator[tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
    """Frames at `rate` Hz from the trajectory's start: (t s, BGR image, R_wb, p_wb); the
    target, if any, lies on the ground at its pose of time t."""
    end = trajectory.duration if duration is None else duration
    t0 = trajectory.waypoints[0].t
    for k in range(int(np.floor(end * rate + 1e-9)) + 1):
        R_wb, p_wb = trajectory.sample(t0 + k / rate)
        decals = () if target is None else (target.decal(k / rate),)
        yield k / rate, scene.render(R_wb, p_wb, decals=decals), R_wb, p_wb


def following(target: GroundTarget, duration: float, offsets: tuple[tuple[float, ...], ...] = (
        (0.0, 0.0, 1.5, 0.0), (0.12, -0.08, 1.35, 0.3), (-0.1, 0.1, 1.65, -0.2),
        (0.08, 0.12, 1.45, 0.1), (-0.12, -0.06, 1.55, -0.3), (0.0, 0.0, 1.5, 0.0))
        ) -> Trajectory:
    """A flight above a moving target: a waypoint every duration / (len(offsets) - 1) s at
    the target's position then, moved by (dx, dy) m, at height z, yaw north + dyaw rad."""
    n = len(offsets) - 1
    waypoints = []
    for k, (dx, dy, z, dyaw) in enumerate(offsets):
        t = duration * k / n
        (x, y), _ = target.path.pose(t)
        waypoints.append(Waypoint(t, (x + dx, y + dy, z), np.pi / 2 + dyaw))
    return Trajectory(tuple(waypoints))
