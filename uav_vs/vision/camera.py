"""Pinhole camera with lens distortion and world pose (chapter section 3.0.2, eq 15-16, 20-21).

A `Camera` holds the intrinsics K (eq 15), the plumb-bob distortion k1 k2 p1 p2 k3
(Zhang 2000, as in sensor_msgs/CameraInfo), and the world-to-camera extrinsics R, t
(eq 16): x_c = R x_w + t. The optical frame is x right, y down, z forward.
"""
from dataclasses import dataclass
from typing import Mapping

import cv2
import numpy as np

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)


class CalibrationError(ValueError):
    """A calibration value is missing or malformed; the message names the parameter."""


@dataclass(frozen=True)
class Camera:
    """One calibrated camera: intrinsics, distortion and world-to-camera pose."""

    name: str
    width: int
    height: int
    K: np.ndarray          # 3x3 intrinsics (eq 15)
    D: np.ndarray          # (5,) k1 k2 p1 p2 k3
    R: np.ndarray          # 3x3 world-to-camera rotation (eq 16)
    t: np.ndarray          # (3,) world-to-camera translation, m
    frame_id: str = ''

    @property
    def P(self) -> np.ndarray:
        """3x4 projection matrix K [R | t] (eq 15 with eq 16)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates, -R^T t."""
        return -self.R.T @ self.t

    def to_camera(self, Xw: np.ndarray) -> np.ndarray:
        """World points (N,3) to the camera frame (eq 16 / eq 21)."""
        return np.asarray(Xw, float) @ self.R.T + self.t

    def project(self, Xw: np.ndarray) -> np.ndarray:
        """World points (N,3) to distorted pixel coordinates (N,2) (eq 15, 16).

        Points behind the camera come out as NaN.
        """
        Xc = self.to_camera(Xw)
        z = Xc[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            x, y = Xc[:, 0] / z, Xc[:, 1] / z
        x = np.where(z > 0, x, np.nan)
        y = np.where(z > 0, y, np.nan)
        k1, k2, p1, p2, k3 = self.D
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        K = self.K
        return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])

    def normalize(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) to ideal normalised coordinates x_c/z_c, y_c/z_c (eq 20)."""
        pts = np.asarray(px, np.float64).reshape(-1, 1, 2)
        if not np.any(self.D):
            out = (pts.reshape(-1, 2) - self.K[:2, 2]) / np.diag(self.K)[:2]
            out[:, 0] -= self.K[0, 1] / self.K[0, 0] * out[:, 1]
            return out
        return cv2.undistortPoints(pts, self.K, self.D, None, None,
                                   criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) to the pixels an ideal pinhole camera would see."""
        n = self.normalize(px)
        return n @ self.K[:2, :2].T + self.K[:2, 2]

    def camera_info_fields(self) -> dict:
        """The sensor_msgs/CameraInfo fields this calibration fills (monocular)."""
        return {'width': self.width, 'height': self.height,
                'distortion_model': 'plumb_bob', 'd': self.D.tolist(),
                'k': self.K.ravel().tolist(), 'r': np.eye(3).ravel().tolist(),
                'p': np.hstack([self.K, np.zeros((3, 1))]).ravel().tolist()}

    @classmethod
    def from_params(cls, name: str, params: Mapping[str, object], prefix: str = '') -> 'Camera':
        """Build from flat parameters `<prefix>width, height, K, D, R, t, frame_id`.

        K and R are 9 numbers row-major (as CameraInfo.k), D is 5 numbers, t is 3.
        Raises CalibrationError naming the parameter on anything missing or malformed.
        """
        def get(key: str) -> object:
            if key not in params or params[key] is None:
                raise CalibrationError(f'{prefix}{key}: missing')
            return params[key]

        width = _positive_int(get('width'), prefix + 'width')
        height = _positive_int(get('height'), prefix + 'height')
        K = finite_numbers(get('K'), 9, prefix + 'K').reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.any(K[2] != (0, 0, 1)) or K[1, 0] != 0:
            raise CalibrationError(f'{prefix}K: expected [fx,s,cx, 0,fy,cy, 0,0,1] with fx, fy > 0')
        D = finite_numbers(get('D'), 5, prefix + 'D')
        R = finite_numbers(get('R'), 9, prefix + 'R').reshape(3, 3)
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
            raise CalibrationError(f'{prefix}R: expected a rotation matrix '
                                   '(orthonormal, det +1), 9 numbers row-major')
        t = finite_numbers(get('t'), 3, prefix + 't')
        frame_id = str(params.get('frame_id') or f'{name}_optical')
        return cls(name, width, height, K, D, R, t, frame_id)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])
            ) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera R, t of an optical frame at `eye` looking at `target` (z forward)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.vstack([x, y, z])
    return R, -R @ np.asarray(eye, float)


def finite_numbers(value: object, n: int, name: str) -> np.ndarray:
    """`value` as n finite floats; CalibrationError naming `name` otherwise."""
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(f'{name}: expected {n} numbers, got {value!r}') from None
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise CalibrationError(f'{name}: expected {n} finite numbers, got {arr.size}')
    return arr


def _positive_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise CalibrationError(f'{name}: expected a positive integer, got {value!r}')
    return int(value)
