"""What the ground cameras see of the vehicle's coloured landmarks (chapter section 3).

Rendering is projection of the true geometry through each `Camera` (eq 15-16 with the
lens distortion), so the ground truth is exact:

- every pixel's viewing ray is precomputed once per camera from `Camera.normalize`
  (the inverse of the distortion), so the image is distorted exactly as the model says;
- the ground plane z = 0 is textured with a real aerial photograph (`assets/aero*.jpg`,
  mirrored beyond its edges, fading into haze with distance) and the sky above the horizon;
- per frame, the rays of a window around the vehicle are intersected with the landmark
  spheres and the dark body and arms (ellipsoids); the two nearest surfaces of each
  pixel are composited, shaded with a Lambertian term plus ambient light (no specular,
  so a landmark keeps its hue);
  silhouette edges are anti-aliased from the ray's distance to the surface;
- several vehicles, each with its own landmark colours, share the view (`render_fleet`):
  each camera draws them farthest first, so a nearer one hides a farther one;
- global lighting drifts slowly (gain and sun direction), and Gaussian sensor noise is
  added (uav_vs.sim.camera_effects.GaussianNoise).

The trajectory (`figure_eight`) gives the truth pose: position in `world` ENU and the
base_link (FLU) attitude, tilted with the acceleration as a multirotor is.
"""
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from uav_vs.sim.camera_effects import GaussianNoise
from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_config import GroundConfig

ASSETS = Path(__file__).resolve().parent / 'assets'
GRAVITY = 9.81


@dataclass(frozen=True)
class Pose:
    """Truth pose of base_link in world: x_w = R x_b + position."""

    t: float                  # s since the start of the trajectory
    position: np.ndarray      # (3,) m, world ENU
    yaw: float                # rad, about world z
    R: np.ndarray             # (3, 3) base_link -> world


@dataclass(frozen=True)
class Ellipsoid:
    """An axis-aligned ellipsoid in base_link: centre (m), semi-axes (m), BGR albedo 0..1."""

    centre: np.ndarray
    axes: np.ndarray
    albedo: np.ndarray


@dataclass(frozen=True)
class RenderInfo:
    """Per camera and landmark: how much of the sphere is visible and where (anti-aliased
    coverage, so these are exact for the rendered geometry before noise)."""

    visible: np.ndarray       # (n_cams, n_landmarks) visible / unoccluded coverage in the image
    centroid: np.ndarray      # (n_cams, n_landmarks, 2) px, centroid of the visible part
    full_centroid: np.ndarray  # (n_cams, n_landmarks, 2) px, centroid ignoring occluders


def figure_eight(t: float, size: tuple[float, float] = (1.4, 0.6), altitude: float = 1.2,
                 period: float = 10.0, yaw_rate: float = 0.55, yaw0: float = 2.0) -> Pose:
    """A horizontal figure-eight (x = a sin wt, y = b sin 2wt) bobbing in z, yawing at a
    constant rate, with pitch/roll that tilt the thrust along the acceleration."""
    w = 2 * np.pi / period
    a, b = size
    s1, s2 = np.sin(w * t), np.sin(2 * w * t)
    position = np.array([a * s1, b * s2, altitude + 0.3 * np.sin(0.5 * w * t)])
    accel = np.array([-a * w * w * s1, -4 * b * w * w * s2, -0.075 * w * w * np.sin(0.5 * w * t)])
    yaw = float(np.angle(np.exp(1j * (yaw0 + yaw_rate * t))))
    Rz = rot_z(yaw)
    ab = Rz.T @ accel                       # acceleration in the yawed (heading) frame
    pitch = np.arctan2(ab[0], GRAVITY + ab[2])
    roll = np.arctan2(-ab[1], np.hypot(ab[0], GRAVITY + ab[2]))
    return Pose(float(t), position, yaw, Rz @ rot_y(pitch) @ rot_x(roll))


def landmark_albedo(hue: np.ndarray) -> np.ndarray:
    """BGR albedo (0..1) of each landmark: the middle of its hue range (wrapping through 0
    for lo > hi), saturation 230, value 215 (headroom for the lighting gain)."""
    lo, hi = hue[:, 0].astype(float), hue[:, 1].astype(float)
    mid = np.where(lo <= hi, (lo + hi) / 2, ((lo + hi + 180) / 2) % 180)
    hsv = np.stack([mid, np.full_like(mid, 230), np.full_like(mid, 215)], axis=1)
    return cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2BGR)[0] / 255.0


def vehicle_parts(config: GroundConfig) -> list[Ellipsoid]:
    """Landmark spheres (first, in config order), then a dark body and two crossed arms
    hanging below them, so the spheres sit on the arm tips."""
    dark = np.array([0.09, 0.08, 0.08])
    reach = np.abs(config.layout[:, :2]).max()
    z = config.layout[:, 2].mean()
    parts = [Ellipsoid(p, np.full(3, config.radius), c)
             for p, c in zip(config.layout, landmark_albedo(config.hue))]
    parts.append(Ellipsoid(np.array([0.0, 0.0, z - 0.09]), np.array([0.16, 0.13, 0.07]), dark))
    parts.append(Ellipsoid(np.array([0.0, 0.0, z - 0.06]), np.array([reach, 0.018, 0.018]), dark))
    parts.append(Ellipsoid(np.array([0.0, 0.0, z - 0.06]), np.array([0.018, reach, 0.018]), dark))
    return parts


class Body:
    """One vehicle's parts as arrays (base_link, m): centres, semi-axes and BGR albedo
    (0..255); the first `n_landmarks` parts are its landmark spheres."""

    def __init__(self, config: GroundConfig) -> None:
        parts = vehicle_parts(config)
        self.n_landmarks = len(config.landmark_names)
        self.centres = np.stack([p.centre for p in parts])
        self.axes = np.stack([p.axes for p in parts])
        self.albedo = np.stack([p.albedo for p in parts]) * 255.0
        self.reach = float(np.max(np.linalg.norm(self.centres, axis=1) + self.axes.max(1)))


class GroundScene:
    """Renders the configured cameras' images of the vehicle at a given pose; with
    `others`, the landmark sets of further vehicles in the same view (config's cameras)."""

    def __init__(self, config: GroundConfig, background: str = 'aero1.jpg',
                 ground_size: float = 30.0, noise_sigma: float = 2.0, ambient: float = 0.4,
                 seed: int = 0, others: Sequence[GroundConfig] = ()):
        self.cameras = config.cameras
        self.bodies = [Body(c) for c in (config, *others)]
        self.n_landmarks = self.bodies[0].n_landmarks
        self.ambient = ambient
        self._rays = [_pixel_rays(c) for c in self.cameras]
        self._ray_products = [np.concatenate([r * r, r[[0, 0, 1]] * r[[1, 2, 2]]])
                              for r in self._rays]
        texture = cv2.imread(str(ASSETS / background), cv2.IMREAD_COLOR)
        if texture is None:
            raise FileNotFoundError(f'cannot read {ASSETS / background}')
        self._background = [_ground_image(c, r, texture, ground_size)
                            for c, r in zip(self.cameras, self._rays)]
        h = max(c.height for c in self.cameras)
        w = max(c.width for c in self.cameras)
        self._noise = GaussianNoise(noise_sigma, (h, w), np.random.default_rng(seed))

    def lighting(self, t: float) -> tuple[float, np.ndarray]:
        """Global gain and sun direction (world, unit, towards the sun) at time t, drifting
        slowly as clouds pass and the sun moves."""
        gain = 1.0 + 0.15 * np.sin(2 * np.pi * t / 9.0) + 0.05 * np.sin(2 * np.pi * t / 3.7)
        az, el = 0.8 + 0.04 * t, np.radians(55.0)
        sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return float(gain), sun

    def render(self, pose: Pose | Sequence[Pose]) -> tuple[list[np.ndarray], RenderInfo]:
        """BGR uint8 images, one per camera, and the landmarks' visibility at this pose
        (or at each camera's own pose: cameras that capture at different instants)."""
        images, (info,) = self.render_fleet([pose])
        return images, info

    def render_fleet(self, poses: Sequence[Pose | Sequence[Pose]]
                     ) -> tuple[list[np.ndarray], list[RenderInfo]]:
        """The images of every vehicle the scene has, each at its pose (or its pose per
        camera), and each one's RenderInfo. A vehicle's visibility counts its own parts
        as occluders, not the other vehicles'."""
        if len(poses) != len(self.bodies):
            raise ValueError(f'{len(poses)} poses for {len(self.bodies)} vehicles')
        per_camera = [self._per_camera(p) for p in poses]
        infos = []
        for body in self.bodies:
            shape = (len(self.cameras), body.n_landmarks)
            infos.append(RenderInfo(np.zeros(shape), np.full(shape + (2,), np.nan),
                                    np.full(shape + (2,), np.nan)))
        images = []
        for k, cam in enumerate(self.cameras):
            gain, sun = self.lighting(per_camera[0][k].t)
            img = cv2.convertScaleAbs(self._background[k], alpha=gain)
            depth = [cam.to_camera(p[k].position[None])[0, 2] for p in per_camera]
            for v in np.argsort(depth)[::-1]:               # the farthest first
                self._draw_vehicle(k, img, per_camera[v][k], self.bodies[v], gain, sun, infos[v])
            images.append(self._noise(img))
        return images, infos

    def landmark_discs(self, pose: Pose | Sequence[Pose], vehicle: int = 0) -> np.ndarray:
        """(n_cams, n_landmarks, 3): each landmark's image centre (u, v) and radius (px,
        from the focal length over its depth) in each camera at `pose` (or at each
        camera's own pose); NaN behind a camera. `vehicle`: whose landmarks."""
        body = self.bodies[vehicle]
        n = body.n_landmarks
        out = np.full((len(self.cameras), n, 3), np.nan)
        for k, (cam, at) in enumerate(zip(self.cameras, self._per_camera(pose))):
            centres = body.centres[:n] @ at.R.T + at.position
            depth = cam.to_camera(centres)[:, 2]
            ahead = depth > 0
            out[k, ahead, :2] = cam.project(centres[ahead])
            out[k, ahead, 2] = cam.K[0, 0] * body.axes[:n, 0][ahead] / depth[ahead]
        return out

    def _per_camera(self, pose: Pose | Sequence[Pose]) -> list[Pose]:
        poses = [pose] * len(self.cameras) if isinstance(pose, Pose) else list(pose)
        if len(poses) != len(self.cameras):
            raise ValueError(f'{len(poses)} poses for {len(self.cameras)} cameras')
        return poses

    def _draw_vehicle(self, k: int, img: np.ndarray, pose: Pose, body: Body, gain: float,
                      sun: np.ndarray, info: RenderInfo) -> None:
        """Ray-cast every part inside the vehicle's image window and composite the two
        nearest surfaces of each pixel over the background.

        A part (centre C, rotation Q and semi-axes a in the camera frame) is
        x^T G x = 1 with G = Q diag(1/a^2) Q^T; on the unit ray x = s d - C, so the
        quadratic forms in d are products with the precomputed ray products.
        """
        cam = self.cameras[k]
        win = _window(cam, pose.position, 1.1 * body.reach)
        if win is None:
            return
        y0, y1, x0, x1 = win
        d = self._rays[k][:, y0:y1, x0:x1].reshape(3, -1)
        dd = self._ray_products[k][:, y0:y1, x0:x1].reshape(6, -1)
        C = (body.centres @ pose.R.T + pose.position) @ cam.R.T + cam.t       # (m, 3)
        Q = cam.R @ pose.R
        G = np.einsum('ij,mj,kj->mik', Q, 1.0 / body.axes ** 2, Q)           # (m, 3, 3)
        GC = np.einsum('mij,mj->mi', G, C)
        cc = np.einsum('mi,mi->m', C, GC)[:, None].astype(np.float32)
        inv_a = 1.0 / (_sym6(G).astype(np.float32) @ dd)                     # 1 / d^T G d
        b = GC.astype(np.float32) @ d                                        # d^T G C
        s0 = b * inv_a                                   # closest approach to the centre
        rho2 = cc - b * s0                               # its scaled distance^2 (1 = surface)
        s = s0 - np.sqrt(np.maximum(1.0 - rho2, 0.0) * inv_a)   # first hit (s0 on a miss)
        # px per unit of scaled distance: the thinnest semi-axis times the focal length
        edge_px = (np.sqrt(np.maximum(rho2, 0.0)) - 1.0) * \
            (body.axes.min(1) * cam.K[0, 0] / np.linalg.norm(C, axis=1)).astype(np.float32)[:, None]
        alpha = np.clip(0.5 - edge_px, 0.0, 1.0)
        rows = np.flatnonzero(alpha.max(axis=0) > 0)
        if rows.size == 0:
            return
        alpha, s, d, dd = alpha[:, rows], s[:, rows], d[:, rows], dd[:, rows]
        depth = np.where(alpha > 0, s, np.inf)

        # Lambert + ambient: the outward normal at x is G x = s G d - G C
        L = cam.R @ sun
        G2 = np.einsum('mij,mjk->mik', G, G)
        n_dot_l = s * (np.einsum('mij,j->mi', G, L) @ d) - (GC @ L)[:, None]
        n_norm2 = s * s * (_sym6(G2) @ dd) - 2 * s * (np.einsum('mij,mj->mi', G2, C) @ d) \
            + np.einsum('mi,mi->m', GC, GC)[:, None]
        lambert = np.maximum(n_dot_l / np.sqrt(np.maximum(n_norm2, 1e-30)), 0.0)
        shade = gain * (self.ambient + (1.0 - self.ambient) * lambert)

        # the two nearest surfaces per pixel, front over back over the background
        r = np.arange(rows.size)
        i1 = np.argmin(depth, axis=0)
        depth2 = depth.copy()
        depth2[i1, r] = np.inf
        i2 = np.argmin(depth2, axis=0)
        a1, a2 = alpha[i1, r][:, None], alpha[i2, r][:, None]
        c1 = shade[i1, r][:, None] * body.albedo[i1]
        c2 = shade[i2, r][:, None] * body.albedo[i2]
        patch = img[y0:y1, x0:x1].reshape(-1, 3)
        out = a1 * c1 + (1.0 - a1) * (a2 * c2 + (1.0 - a2) * patch[rows])
        patch[rows] = np.clip(out + 0.5, 0, 255).astype(np.uint8)
        img[y0:y1, x0:x1] = patch.reshape(y1 - y0, x1 - x0, 3)

        w = x1 - x0
        xy = np.column_stack([x0 + rows % w, y0 + rows // w]).astype(np.float64)
        for i in range(body.n_landmarks):
            total = alpha[i].sum(dtype=np.float64)
            if total == 0:
                continue
            seen = alpha[i] * np.prod(np.where(depth < depth[i], 1.0 - alpha, 1.0), axis=0)
            info.visible[k, i] = seen.sum(dtype=np.float64) / total
            info.full_centroid[k, i] = alpha[i] @ xy / total
            if seen.sum() > 0:
                info.centroid[k, i] = seen @ xy / seen.sum(dtype=np.float64)


def _sym6(G: np.ndarray) -> np.ndarray:
    """(m, 6) coefficients of d^T G d on the ray products (dx2, dy2, dz2, dxdy, dxdz, dydz)."""
    return np.stack([G[:, 0, 0], G[:, 1, 1], G[:, 2, 2],
                     2 * G[:, 0, 1], 2 * G[:, 0, 2], 2 * G[:, 1, 2]], axis=1)


def _window(cam: Camera, centre: np.ndarray, radius: float) -> tuple[int, int, int, int] | None:
    """Pixel bounds (y0, y1, x0, x1) enclosing the image of a sphere, or None if off-image."""
    c = cam.to_camera(centre[None])[0]
    if c[2] <= radius:
        return None
    dist = np.linalg.norm(c)
    a = np.cross(c, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(c / dist, a)
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    r = radius * dist / np.sqrt(dist * dist - radius * radius)   # tangent-cone silhouette
    ring_c = c + r * (np.outer(np.cos(ang), a) + np.outer(np.sin(ang), b))
    ring_w = (ring_c - cam.t) @ cam.R                           # back to world for project
    px = cam.project(ring_w)
    x0, y0 = np.floor(px.min(0)).astype(int) - 2
    x1, y1 = np.ceil(px.max(0)).astype(int) + 3
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height)
    return (y0, y1, x0, x1) if x1 > x0 and y1 > y0 else None


def _pixel_rays(cam: Camera) -> np.ndarray:
    """Unit viewing ray (camera frame) through every pixel centre, (3, H, W) float32."""
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    n = cam.normalize(np.column_stack([u.ravel(), v.ravel()]).astype(np.float64))
    rays = np.column_stack([n, np.ones(len(n))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return rays.T.reshape(3, cam.height, cam.width).astype(np.float32)


def _ground_image(cam: Camera, rays: np.ndarray, texture: np.ndarray, size: float
                  ) -> np.ndarray:
    """The textured ground plane z = 0 (texture `size` m wide, centred on the origin,
    mirrored beyond) and a sky gradient above the horizon, seen through `cam`."""
    d = rays.reshape(3, -1).T.astype(np.float64) @ cam.R      # world directions
    centre = cam.center
    with np.errstate(divide='ignore', invalid='ignore'):
        s = np.where(d[:, 2] < -1e-6, -centre[2] / d[:, 2], np.inf)
    ground = centre[:2] + np.minimum(s, 1e4)[:, None] * d[:, :2]
    h, w = texture.shape[:2]
    m_per_px = size / w
    map_x = (ground[:, 0] / m_per_px + w / 2).astype(np.float32).reshape(cam.height, cam.width)
    map_y = (h / 2 - ground[:, 1] / m_per_px).astype(np.float32).reshape(cam.height, cam.width)
    sharp = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    blurred = cv2.remap(cv2.GaussianBlur(texture, (0, 0), 4), map_x, map_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT_101)
    dist = np.where(np.isfinite(s), s, 1e4).reshape(cam.height, cam.width, 1)
    far = np.clip((dist - 12.0) / 20.0, 0.0, 1.0)       # texture detail fades with distance
    haze = 1.0 - np.exp(-dist / 60.0)
    sky = np.array([235, 215, 195], np.float32)         # pale blue-grey, BGR
    img = (1 - far) * sharp + far * blurred
    img = (1 - haze) * img + haze * sky
    elev = np.clip(d[:, 2], 0, 1).reshape(cam.height, cam.width, 1)
    img = np.where(np.isfinite(s).reshape(cam.height, cam.width, 1), img,
                   sky - 60 * elev * np.array([0.2, 0.6, 1.0], np.float32))
    return np.clip(img, 0, 255).astype(np.uint8)


def rot_x(a: float) -> np.ndarray:
    """Rotation matrix about x by `a` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation matrix about y by `a` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation matrix about z by `a` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
