"""Pinhole camera with lens distortion and world pose (chapter section 3.0.2, eq 15-16, 20-21).

A `Camera` holds the intrinsics K (eq 15), the lens distortion D in any of OpenCV's
models, and the world-to-camera extrinsics R, t (eq 16): x_c = R x_w + t. The optical
frame is x right, y down, z forward. Only K is required:

- D has 0, 4, 5, 8, 12 or 14 coefficients, in OpenCV's order k1 k2 p1 p2 [k3 [k4 k5 k6
  [s1 s2 s3 s4 [tau_x tau_y]]]]: none, plumb bob (5, sensor_msgs/CameraInfo's
  `plumb_bob`; 4 is the same with k3 = 0), rational (8, `rational_polynomial`), thin
  prism (12) and tilted sensor (14). Projection and undistortion are OpenCV's
  (cv2.projectPoints, cv2.undistortPoints) with that D, on normalised coordinates, so
  a skew in K is honoured too.
- R, t default to the identity and zero (world = optical frame); name, width and
  height are only needed by what renders or publishes images.
"""
from dataclasses import dataclass
from typing import Mapping

import cv2
import numpy as np

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
DISTORTION_SIZES = (0, 4, 5, 8, 12, 14)      # the lengths of D OpenCV's models take
_ZERO3 = np.zeros(3)


def _undistort_points(pts: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """cv2.undistortPoints to _UNDISTORT_CRITERIA (OpenCV 5 takes them as an argument)."""
    return cv2.undistortPoints(pts, K, D, None, None, criteria=_UNDISTORT_CRITERIA)


def _undistort_points_iter(pts: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The same on OpenCV 4 (Ubuntu 24.04's 4.6), where undistortPointsIter takes them."""
    return cv2.undistortPointsIter(pts, K, D, None, None, _UNDISTORT_CRITERIA)


undistort_points = _undistort_points_iter if hasattr(cv2, 'undistortPointsIter') else _undistort_points


class CalibrationError(ValueError):
    """A calibration value is missing or malformed; the message names the parameter."""


@dataclass(frozen=True)
class Camera:
    """One calibrated camera: intrinsics, distortion and world-to-camera pose.

    `Camera(K=K, D=D)` is enough for geometry; the fields are checked and stored as
    float arrays, and a malformed one raises a one-line CalibrationError naming it.
    """

    name: str = 'camera'
    width: int | None = None   # image size, px: needed to render or publish images
    height: int | None = None
    K: np.ndarray = None       # 3x3 intrinsics (eq 15), required
    D: np.ndarray = ()         # 0, 4, 5, 8, 12 or 14 coefficients, OpenCV's order
    R: np.ndarray = None       # 3x3 world-to-camera rotation (eq 16); None: identity
    t: np.ndarray = None       # (3,) world-to-camera translation, m; None: zero
    frame_id: str = ''

    def __post_init__(self) -> None:
        if self.K is None:
            raise CalibrationError('K: missing, expected the 3x3 intrinsics matrix')
        K = check_intrinsics(finite_numbers(self.K, 9, 'K').reshape(3, 3), 'K')
        D = check_distortion(self.D, 'D')
        R = np.eye(3) if self.R is None else finite_numbers(self.R, 9, 'R').reshape(3, 3)
        t = _ZERO3.copy() if self.t is None else finite_numbers(self.t, 3, 't')
        for key, value in (('K', K), ('D', D), ('R', R), ('t', t)):
            object.__setattr__(self, key, value)

    @property
    def P(self) -> np.ndarray:
        """3x4 projection matrix K [R | t] (eq 15 with eq 16)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates, -R^T t."""
        return -self.R.T @ self.t

    def pose_in_world(self) -> tuple[np.ndarray, np.ndarray]:
        """The optical frame's pose in world, (R^T, -R^T t): x_w = R^T x_c + centre."""
        return self.R.T, self.center

    def to_camera(self, Xw: np.ndarray) -> np.ndarray:
        """World points (N,3) to the camera frame (eq 16 / eq 21)."""
        return np.asarray(Xw, float) @ self.R.T + self.t

    def project(self, Xw: np.ndarray) -> np.ndarray:
        """World points (N,3) to distorted pixel coordinates (N,2) (eq 15, 16).

        The lens model is OpenCV's with this D, applied to x_c/z_c, y_c/z_c; K then
        maps to pixels. Points behind the camera come out as NaN.
        """
        Xc = self.to_camera(Xw)
        z = Xc[:, 2:]
        with np.errstate(divide='ignore', invalid='ignore'):
            xy = np.where(z > 0, Xc[:, :2] / z, np.nan)
        if self.D.size and len(xy):
            rays = np.column_stack([xy, np.ones(len(xy))])
            xy = cv2.projectPoints(rays, _ZERO3, _ZERO3, np.eye(3), self.D)[0].reshape(-1, 2)
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def normalize(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) to ideal normalised coordinates x_c/z_c, y_c/z_c (eq 20)."""
        pts = np.asarray(px, np.float64).reshape(-1, 2)
        out = (pts - self.K[:2, 2]) / np.diag(self.K)[:2]
        out[:, 0] -= self.K[0, 1] / self.K[0, 0] * out[:, 1]
        if not np.any(self.D) or not len(out):
            return out
        return undistort_points(out.reshape(-1, 1, 2), np.eye(3), self.D).reshape(-1, 2)

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) to the pixels an ideal pinhole camera would see."""
        n = self.normalize(px)
        return n @ self.K[:2, :2].T + self.K[:2, 2]

    def camera_info_fields(self) -> dict:
        """The sensor_msgs/CameraInfo fields this calibration fills (monocular).

        D of up to 5 coefficients is written as `plumb_bob` (padded to 5 with zeros),
        longer ones as `rational_polynomial` with every coefficient (ROS names no
        12- or 14-coefficient model). An unknown image size is written as 0.
        """
        if self.D.size <= 5:
            model, d = 'plumb_bob', np.pad(self.D, (0, 5 - self.D.size))
        else:
            model, d = 'rational_polynomial', self.D
        return {'width': self.width or 0, 'height': self.height or 0,
                'distortion_model': model, 'd': d.tolist(),
                'k': self.K.ravel().tolist(), 'r': np.eye(3).ravel().tolist(),
                'p': np.hstack([self.K, np.zeros((3, 1))]).ravel().tolist()}

    @classmethod
    def from_params(cls, name: str, params: Mapping[str, object], prefix: str = '') -> 'Camera':
        """Build from flat parameters `<prefix>width, height, K, D, R, t, frame_id`.

        K and R are 9 numbers row-major (as CameraInfo.k), D is 0, 4, 5, 8, 12 or 14
        numbers (`DISTORTION_SIZES`), t is 3. Raises CalibrationError naming the parameter on anything missing or malformed.
        """
        def get(key: str) -> object:
            if key not in params or params[key] is None:
                raise CalibrationError(f'{prefix}{key}: missing')
            return params[key]

        width = _positive_int(get('width'), prefix + 'width')
        height = _positive_int(get('height'), prefix + 'height')
        K = check_intrinsics(finite_numbers(get('K'), 9, prefix + 'K').reshape(3, 3), prefix + 'K')
        D = check_distortion(get('D'), prefix + 'D')
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


def check_intrinsics(K: np.ndarray, name: str) -> np.ndarray:
    """K (3x3) if it is [fx, s, cx; 0, fy, cy; 0, 0, 1] with fx, fy > 0; else CalibrationError."""
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.any(K[2] != (0, 0, 1)) or K[1, 0] != 0:
        raise CalibrationError(f'{name}: expected [fx,s,cx, 0,fy,cy, 0,0,1] with fx, fy > 0')
    return K


def check_distortion(value: object, name: str) -> np.ndarray:
    """D as finite floats of one of OpenCV's lengths (DISTORTION_SIZES); else CalibrationError."""
    try:
        D = np.asarray(value if value is not None else (), dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(f'{name}: expected distortion coefficients, got {value!r}') from None
    if D.size not in DISTORTION_SIZES:
        raise CalibrationError(f'{name}: expected 0, 4, 5, 8, 12 or 14 distortion coefficients '
                               f'(OpenCV\'s models), got {D.size}')
    if not np.all(np.isfinite(D)):
        raise CalibrationError(f'{name}: distortion coefficients must be finite')
    return D


def _positive_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise CalibrationError(f'{name}: expected a positive integer, got {value!r}')
    return int(value)
