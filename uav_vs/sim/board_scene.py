"""A printed chessboard or ChArUco board held in the ground cameras' view, rendered
through each camera's own lens, for calibrating the simulated rig as a real one is
calibrated (uav_vs.vision.calibration, uav_vs.vision.rig_calibration).

As in uav_vs.sim.ground_scene, rendering is exact projection: every pixel is the mean of
`supersample` x `supersample` viewing rays through it (`Camera.normalize`, the inverse
of the distortion), each intersected with the board's plane and coloured by what is
printed where it meets it (black and white, lit, with a white margin of one square): a
chessboard's square, or the pixel of OpenCV's own drawing of the ChArUco board
(CharucoBoard.generateImage, TEXELS per square, so every edge of a square falls on a
texel's edge). The corners lie exactly where the camera model projects them and the
edges are anti-aliased as a lens and sensor blur them. Outside the board the camera sees
the ground scene's background (grey); the board's back is plain grey card. Gaussian
sensor noise is added.

The poses a user moves the board through to calibrate a rig: `close_ups` before each
camera alone (its intrinsics), `through_the_volume` where the cameras see it together
(the rig), and `on_the_ground`, flat at the world's origin (the world frame).
"""
from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from uav_vs.sim.camera_effects import GaussianNoise
from uav_vs.vision.calibration import Board, Detection
from uav_vs.vision.camera import Camera
from uav_vs.vision.rig_calibration import BOARD_TO_WORLD

INK, PAPER, CARD = 40.0, 215.0, 120.0      # grey levels of a black square, white, the back
TEXELS = 64                                 # a ChArUco board's drawing, pixels per square


class BoardScene:
    """Renders `board` (a chessboard or a ChArUco board) at a pose in the world into each
    camera's image."""

    def __init__(self, cameras: Sequence[Camera], board: Board,
                 backgrounds: Sequence[np.ndarray] | None = None, supersample: int = 3,
                 noise_sigma: float = 2.0, seed: int = 0):
        if board.kind not in ('chessboard', 'charuco'):
            raise ValueError(f'board kind: the scene renders a chessboard or a ChArUco board, '
                             f'got {board.kind!r}')
        self.cameras = list(cameras)
        self.board = board
        self.supersample = supersample
        self._rays = [_subpixel_rays(c, supersample) for c in self.cameras]
        self._backgrounds = ([cv2.cvtColor(b, cv2.COLOR_BGR2GRAY) if b.ndim == 3 else b
                              for b in backgrounds] if backgrounds is not None else
                             [np.full((c.height, c.width), 128, np.uint8) for c in cameras])
        s = board.square
        # the squares (board frame, m: a chessboard's first inner corner, a ChArUco
        # board's outer corner is the origin) and the printed sheet, a white margin of one
        # square around them
        x0 = y0 = -s if board.kind == 'chessboard' else 0.0
        self._squares = (x0, y0, x0 + board.cols * s, y0 + board.rows * s)
        self._sheet = (x0 - s, y0 - s, x0 + (board.cols + 1) * s, y0 + (board.rows + 1) * s)
        self._texture = None
        if board.kind == 'charuco':
            drawing = board.charuco().generateImage((board.cols * TEXELS, board.rows * TEXELS))
            if board.inverted:
                drawing = 255 - drawing
            self._texture = INK + (PAPER - INK) / 255.0 * drawing.astype(np.float32)
        self._noise = GaussianNoise(noise_sigma, (max(c.height for c in cameras),
                                                  max(c.width for c in cameras)),
                                    np.random.default_rng(seed))

    def corners_in(self, T_world_board: np.ndarray) -> np.ndarray:
        """(4, 3) world corners of the printed sheet at this pose."""
        x0, y0, x1, y1 = self._sheet
        local = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
        return local @ T_world_board[:3, :3].T + T_world_board[:3, 3]

    def render(self, T_world_board: np.ndarray) -> list[np.ndarray]:
        """BGR uint8 images (grey scenes), one per camera, of the board at `T_world_board`
        (4x4, board frame -> world; the board frame is Board.object_points' own)."""
        out = []
        for k, cam in enumerate(self.cameras):
            img = self._backgrounds[k].astype(np.float32)
            window = self._window(cam, T_world_board)
            if window is not None:
                y0, y1, x0, x1 = window
                img[y0:y1, x0:x1] = self._shade(k, T_world_board, window, img[y0:y1, x0:x1])
            grey = np.clip(img, 0, 255).astype(np.uint8)
            out.append(self._noise(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)))
        return out

    def _window(self, cam: Camera, T_world_board: np.ndarray
                ) -> tuple[int, int, int, int] | None:
        """Pixel rows and columns the sheet may cover (its corners' hull, one pixel more)."""
        corners = self.corners_in(T_world_board)
        if (cam.to_camera(corners)[:, 2] <= 0).any():
            return None
        px = cam.project(corners)
        x0, y0 = np.floor(px.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height)
        return (y0, y1, x0, x1) if x1 > x0 and y1 > y0 else None

    def _shade(self, k: int, T_world_board: np.ndarray, window: tuple[int, int, int, int],
               background: np.ndarray) -> np.ndarray:
        cam, n = self.cameras[k], self.supersample
        y0, y1, x0, x1 = window
        rays = self._rays[k][:, y0 * n:y1 * n, x0 * n:x1 * n].reshape(3, -1)
        # the board in the camera frame: x_c = R_cb x_b + t_cb
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3], T_cam_world[:3, 3] = cam.R, cam.t
        T = T_cam_world @ T_world_board
        R_cb, t_cb = T[:3, :3], T[:3, 3]
        normal = R_cb[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            depth = (normal @ t_cb) / (normal @ rays)
        hit = R_cb.T @ (rays * depth - t_cb[:, None])          # board coordinates, m
        x_lo, y_lo, x_hi, y_hi = self._sheet
        on = ((depth > 0) & (hit[0] >= x_lo) & (hit[0] <= x_hi)
              & (hit[1] >= y_lo) & (hit[1] <= y_hi))
        front = normal @ t_cb > 0          # the camera is on the printed side
        level = self._printed(hit[:2], on) if front else np.full(on.shape, CARD)
        h, w = y1 - y0, x1 - x0
        back = np.repeat(np.repeat(background, n, axis=0), n, axis=1).reshape(-1)
        value = np.where(on, level, back).reshape(h, n, w, n)
        return value.mean(axis=(1, 3))

    def _printed(self, xy: np.ndarray, on: np.ndarray) -> np.ndarray:
        """Grey level printed at board points `xy` (2, N), m; PAPER off the squares and
        where `on` is False."""
        s, board = self.board.square, self.board
        x0, y0, x1, y1 = self._squares
        inside = on & (xy[0] >= x0) & (xy[0] < x1) & (xy[1] >= y0) & (xy[1] < y1)
        level = np.full(on.shape, PAPER, np.float32)
        if self._texture is None:
            col, row = np.floor(xy[:, inside] / s)
            level[inside] = np.where((col + row) % 2 == 1, INK, PAPER)   # see Board
        else:
            u, v = np.floor(xy[:, inside] / s * TEXELS).astype(np.int64)
            level[inside] = self._texture[np.minimum(v, board.rows * TEXELS - 1),
                                          np.minimum(u, board.cols * TEXELS - 1)]
        return level


def _subpixel_rays(cam: Camera, n: int) -> np.ndarray:
    """Viewing rays (camera frame, z = 1) through an n x n grid inside every pixel,
    (3, H n, W n) float32."""
    offsets = (np.arange(n) + 0.5) / n - 0.5
    v = np.arange(cam.height)[:, None] + offsets[None, :]
    u = np.arange(cam.width)[:, None] + offsets[None, :]
    vv, uu = np.meshgrid(v.ravel(), u.ravel(), indexing='ij')
    xy = cam.normalize(np.column_stack([uu.ravel(), vv.ravel()]))
    rays = np.vstack([xy.T, np.ones(len(xy))])
    return rays.reshape(3, cam.height * n, cam.width * n).astype(np.float32)


def pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def in_front_of(camera: Camera, board: Board, pixel: Sequence[float], distance: float,
                rvec: Sequence[float]) -> np.ndarray:
    """4x4 board -> world pose of `board` with its centre `distance` m along the ray
    through `pixel`, facing `camera` turned by `rvec` (axis-angle, rad, camera frame)."""
    ray = np.append(camera.normalize(np.asarray(pixel, float)[None])[0], 1.0)
    R_cb = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    t_cb = ray / np.linalg.norm(ray) * distance - R_cb @ board.object_points().mean(axis=0)
    return pose(camera.R.T @ R_cb, camera.R.T @ (t_cb - camera.t))


def close_ups(camera: Camera, board: Board, count: int, rng: np.random.Generator,
              distance: tuple[float, float] = (2.0, 3.0), tilt_deg: tuple[float, float] = (15, 45),
              margin: float = 0.2, whole: float | None = None) -> list[np.ndarray]:
    """Board poses for one camera's intrinsics: `distance` m before it, its centre anywhere
    but the image's outer `margin` (a fraction of the image), tilted `tilt_deg` about a
    random axis. With `whole` (px), a board that would cross the image's edge is slid
    back along it until every point lies that far inside, and a pose that cannot fit is
    drawn again: a board seen whole, as far out as the image goes (a board aimed at a
    corner ends in it), as a user fills the image with a chessboard."""
    out = []
    size = np.array([camera.width, camera.height], float)
    while len(out) < count:
        pixel = rng.uniform(margin * size, (1 - margin) * size)
        axis = rng.normal(size=3)
        rvec = axis / np.linalg.norm(axis) * np.radians(rng.uniform(*tilt_deg))
        depth = rng.uniform(*distance)
        T = (in_front_of(camera, board, pixel, depth, rvec) if whole is None else
             _slid_inside(camera, board, pixel, depth, rvec, whole))
        if T is not None:
            out.append(T)
    return out


def _slid_inside(camera: Camera, board: Board, pixel: np.ndarray, distance: float,
                 rvec: np.ndarray, inset: float, tries: int = 5) -> np.ndarray | None:
    """in_front_of's pose, its centre's pixel moved until every point of the board lies
    `inset` px inside the image (None if it does not within `tries` moves)."""
    objects = board.object_points().astype(np.float64)
    far = np.array([camera.width, camera.height], float) - 1 - inset
    for _ in range(tries):
        T = in_front_of(camera, board, pixel, distance, rvec)
        px = camera.project(objects @ T[:3, :3].T + T[:3, 3])
        under, over = inset - px.min(axis=0), px.max(axis=0) - far
        if (under <= 0).all() and (over <= 0).all():
            return T
        pixel = pixel + np.maximum(under, 0) - np.maximum(over, 0)
    return None


def through_the_volume(board: Board, count: int, rng: np.random.Generator,
                       half_width: float = 1.2, heights: tuple[float, float] = (0.3, 1.8),
                       max_tilt_deg: float = 35.0) -> list[np.ndarray]:
    """Board poses for the rig: face up over the flight area (centre within `half_width`
    m of the origin, at `heights` m), tilted up to `max_tilt_deg` about a random axis."""
    centre = board.object_points().mean(axis=0)
    out = []
    for _ in range(count):
        axis = rng.normal(size=3)
        rvec = axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.0, max_tilt_deg))
        R = cv2.Rodrigues(rvec)[0] @ BOARD_TO_WORLD
        at = np.array([*rng.uniform(-half_width, half_width, 2), rng.uniform(*heights)])
        out.append(pose(R, at - R @ centre))
    return out


def on_the_ground() -> np.ndarray:
    """The board flat on the ground, its first point at the world's origin and its first
    row along x: the view that fixes the world frame (uav_vs.vision.rig_calibration)."""
    return pose(BOARD_TO_WORLD, np.zeros(3))


def seen_points(cameras: Sequence[Camera], board: Board, poses: dict[str, np.ndarray],
                noise_px: float, rng: np.random.Generator) -> dict[str, dict[str, Detection]]:
    """The board's points where each camera projects them at each named pose (4x4 board ->
    world), when the camera faces its printed side and sees every point, with Gaussian
    pixel noise: what a perfect detector would give, for checks that need no image.
    {camera name: {pose name: Detection}}."""
    objects = board.object_points().astype(np.float64)
    out: dict[str, dict[str, Detection]] = {c.name: {} for c in cameras}
    for name, T in poses.items():
        world = objects @ T[:3, :3].T + T[:3, 3]
        printed_side = T[:3, :3] @ [0.0, 0.0, -1.0]
        for cam in cameras:
            px = cam.project(world)
            facing = printed_side @ (cam.center - world.mean(axis=0)) > 0
            if facing and (px > 0).all() and (px < (cam.width, cam.height)).all():
                noisy = px + rng.normal(0.0, noise_px, px.shape)
                out[cam.name][name] = Detection(np.arange(len(px), dtype=np.int32),
                                                noisy.astype(np.float32))
    return out
