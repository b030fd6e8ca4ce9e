"""Onboard camera and plane-pose configuration (chapter section 4; config/onboard.yaml).

`SETTINGS` lists every flat parameter key with its default, meaning and limits, so a
node can declare them; `load_onboard_config(flat_params)` checks them and builds the
camera, its extrinsic, the first frame's plane homography and the estimator settings.
A bad value raises CalibrationError (calibration, extrinsic, initialisation) or
ValueError (tuning), one line naming the parameter.

`homography.method` defaults to 'opencv_magsac': on the pose pipeline's own
keyframe-to-frame tracks every estimator gives the same pose accuracy (0.13-0.17 % of
the height, 0.06-0.08 deg, no frame lost, also with 20-40 % of the tracks made random)
and MAGSAC is the fastest (0.7 ms a frame; cv2 RANSAC 0.7-1.3 ms, 'ransac' 2.4-3.2 ms).
On the Oxford SIFT pairs its corner error is lower than cv2 RANSAC's on 3 of 8, higher
on 3 (bench/onboard_homography.py).
"""
from dataclasses import dataclass
from typing import Mapping

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from uav_vs.vision.camera import CalibrationError, Camera
from uav_vs.vision.features import KINDS
from uav_vs.vision.homography import METHODS
from uav_vs.vision.klt import KltParams
from uav_vs.vision.plane_geometry import REFINERS
from uav_vs.vision.plane_pose import PlanePoseParams, camera_pose, plane_homography

REQUIRED = None
_P = PlanePoseParams()   # the estimator's defaults are the settings' defaults
INIT_MODES = ('pose', 'reference_points', 'pose_topic')


@dataclass(frozen=True)
class Setting:
    """One flat parameter: key, kind, default (REQUIRED if none), meaning, limits.

    kind is 'int', 'float', 'str' or 'floats' (a list of numbers of length `size`;
    size 0 means x y pairs, at least four of them; None, any length).
    """

    key: str
    kind: str
    default: object
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    size: int | None = None


SETTINGS = (
    Setting('camera.width', 'int', REQUIRED, 'image width, px', 1, 20000),
    Setting('camera.height', 'int', REQUIRED, 'image height, px', 1, 20000),
    Setting('camera.K', 'floats', REQUIRED, 'intrinsics K (eq 15), 9 numbers row-major, px',
            size=9),
    Setting('camera.D', 'floats', REQUIRED, 'distortion, OpenCV order k1 k2 p1 p2 [k3 [k4 k5 k6 '
            '[s1 s2 s3 s4 [tx ty]]]]: 0, 4, 5, 8, 12 or 14 numbers'),
    Setting('camera.frame_id', 'str', 'onboard_camera_optical', 'optical frame of the images'),
    Setting('camera_to_base_link.xyz', 'floats', [0.0, 0.0, 0.0],
            'optical frame origin in base_link (FLU), m', size=3),
    Setting('camera_to_base_link.rpy', 'floats', [np.pi, 0.0, -np.pi / 2],
            'optical frame orientation in base_link, fixed-axis roll pitch yaw, rad', size=3),
    Setting('init.mode', 'str', 'pose',
            'first-frame plane homography from: pose (init.position, init.rpy), '
            'reference_points, or pose_topic (the pose another source gives at the first '
            "frame's stamp)", choices=INIT_MODES),
    Setting('init.pose_topic', 'str', 'ground/pose', 'with init.mode pose_topic: the '
            'base_link poses (geometry_msgs/PoseStamped, world frame) the first frame is '
            'initialised at, interpolated to its stamp'),
    Setting('init.max_interval', 'float', 0.1, 'with init.mode pose_topic: poses either side '
            'of the first frame at most this far apart are interpolated, s', 0.001, 10.0),
    Setting('init.max_gap', 'float', 0.02, 'with init.mode pose_topic: else the nearest '
            'pose, if at most this far from the frame, s', 0.0, 10.0),
    Setting('init.max_wait', 'float', 1.0, 'with init.mode pose_topic: the first frame waits '
            'this long (by image stamps) for the pose after it; later, a newer frame is '
            'held instead, s', 0.01, 60.0),
    Setting('init.position', 'floats', [0.0, 0.0, 1.0], 'base_link position in world at the '
            'first frame (z = height above the ground plane), m', size=3),
    Setting('init.rpy', 'floats', [0.0, 0.0, 0.0], 'base_link roll pitch yaw in world at the '
            'first frame, rad', size=3),
    Setting('init.plane_points', 'floats', [0.0] * 8, 'reference points on the ground plane, '
            'x1 y1 x2 y2 ... (>= 4 points), m', size=0),
    Setting('init.image_points', 'floats', [0.0] * 8, 'their raw pixels in the first frame, '
            'u1 v1 u2 v2 ...', size=0),
    Setting('klt.win_size', 'int', _P.klt.win_size, 'L-K window side, odd, px', 3, 99),
    Setting('klt.max_level', 'int', _P.klt.max_level, 'deepest pyramid level (section 2.1.2)',
            0, 6),
    Setting('klt.max_iterations', 'int', _P.klt.max_iterations,
            'L-K iterations per pyramid level', 1, 1000),
    Setting('klt.epsilon', 'float', _P.klt.epsilon,
            'L-K stops when its update is below this, px', 1e-6, 10.0),
    Setting('klt.min_eig_threshold', 'float', _P.klt.min_eig_threshold,
            'reject L-K windows flatter than this', 0.0, 1.0),
    Setting('klt.fb_max_error_px', 'float', _P.klt.fb_max_error_px,
            'forward-backward disagreement allowed, px', 0.01, 50.0),
    Setting('features.max_features', 'int', _P.max_features, 'features kept after a re-anchor',
            8, 5000),
    Setting('features.min_tracks', 'int', _P.min_tracks,
            'fewer surviving tracks is a tracking loss', 4, 5000),
    Setting('features.quality_level', 'float', _P.klt.quality_level,
            'GFTT corner strength relative to the best', 1e-4, 0.99),
    Setting('features.min_distance_px', 'float', _P.klt.min_distance_px,
            'spacing between features, px', 1.0, 1000.0),
    Setting('features.block_size', 'int', _P.klt.block_size,
            'GFTT eigenvalue window at the detection level, odd, px', 3, 31),
    Setting('features.detect_level', 'int', _P.klt.detect_level,
            'pyramid level features are detected on', 0, 3),
    Setting('homography.method', 'str', _P.method, 'robust homography estimator',
            choices=METHODS),
    Setting('homography.threshold_px', 'float', _P.threshold_px, 'inlier distance, px',
            0.1, 50.0),
    Setting('homography.confidence', 'float', _P.confidence, 'RANSAC confidence p (Algorithm 1)',
            0.5, 0.999999),
    Setting('homography.max_trials', 'int', _P.max_trials, 'RANSAC trial cap', 1, 100000),
    Setting('homography.min_inliers', 'int', _P.min_inliers, 'fewer inliers is a tracking loss',
            4, 5000),
    Setting('pose.max_rms_px', 'float', _P.max_rms_px,
            'refined pose reprojection RMS above this is a loss, px', 0.01, 100.0),
    Setting('pose.refine', 'str', _P.refine,
            "pose refinement on the inliers: opencv (cv2.solvePnPRefineLM) or lm (eq 27 by "
            "this package's Levenberg-Marquardt)", choices=REFINERS),
    Setting('covariance.pixel_sigma_floor', 'float', _P.pixel_sigma_floor,
            "the pose covariance's pixel noise is never taken smaller than this, px",
            0.001, 10.0),
    Setting('covariance.init_position_sigma', 'float', _P.init_position_sigma,
            "the first keyframe's position uncertainty (the init pose's), m per axis",
            1e-4, 100.0),
    Setting('covariance.init_angle_sigma', 'float', _P.init_angle_sigma,
            "the first keyframe's rotation uncertainty, rad per axis", 1e-5, 3.2),
    Setting('keyframe.reanchor_inliers', 'int', _P.reanchor_inliers,
            're-anchor when inliers drop below this', 4, 5000),
    Setting('keyframe.reanchor_coverage', 'float', _P.reanchor_coverage,
            "re-anchor when the inliers' bounding box covers less than this fraction of the "
            'image', 0.0, 0.99),
    Setting('relocalise.after_frames', 'int', _P.relocalise_after,
            'consecutive lost frames before the keyframe is matched by descriptors; 0 never',
            0, 10000),
    Setting('relocalise.features', 'str', _P.relocalise_features, 'descriptor for relocalisation',
            choices=KINDS),
    Setting('relocalise.max_features', 'int', _P.relocalise_max_features,
            'keypoints per image for relocalisation; 0 = every SIFT keypoint', 0, 100000),
    Setting('relocalise.ratio', 'float', _P.relocalise_ratio,
            "Lowe's ratio test for relocalisation matches", 0.1, 1.0),
    Setting('relocalise.max_shift', 'float', _P.relocalise_max_shift,
            'a relocalised camera farther than this times its last height from its last '
            'position is refused', 0.0, 100.0),
    Setting('image_quality.blur_level', 'int', _P.blur_level,
            'pyramid level the sharpness is measured on', 0, 4),
    Setting('image_quality.min_sharpness', 'float', _P.min_sharpness,
            'variance of the Laplacian below this is a blurred or texture-less image (loss)',
            0.0, 1e6),
)


@dataclass(frozen=True)
class InitFromPoses:
    """init.mode pose_topic: where the poses come from and how close in time they must be."""

    topic: str
    max_interval: float
    max_gap: float
    max_wait: float


@dataclass(frozen=True)
class OnboardConfig:
    """Everything the plane-pose estimator needs (section 4)."""

    camera: Camera                 # intrinsics and distortion; R, t unused (identity, zero)
    camera_to_body: np.ndarray     # 4x4 pose of the optical frame in base_link, x_b = T x_c
    initial_homography: np.ndarray | None  # H_0: plane (X, Y, 1), m -> ideal pixels of
    params: PlanePoseParams                 # frame 0 (None with init.mode pose_topic)
    init_mode: str
    init_pose: InitFromPoses | None = None    # with init.mode pose_topic

    def homography_at(self, R_wb: np.ndarray, p_wb: np.ndarray) -> np.ndarray:
        """H_0 of a first frame taken with base_link at R_wb, p_wb (world)."""
        return homography_at(self.camera, self.camera_to_body, R_wb, p_wb, 'init.pose_topic')


def homography_at(camera: Camera, camera_to_body: np.ndarray, R_wb: np.ndarray,
                  p_wb: np.ndarray, name: str) -> np.ndarray:
    """The plane homography (eq 21) of the camera on base_link at R_wb, p_wb; `name`, the
    parameter blamed when the camera is not above the plane looking down at it."""
    R, t = camera_pose(R_wb, p_wb, camera_to_body)
    if (-R.T @ t)[2] <= 0 or R[2, 2] >= 0:
        raise CalibrationError(f'{name}: the camera must be above the ground plane (z > 0) '
                               'and look down at it (check its orientation and '
                               'camera_to_base_link.rpy)')
    return plane_homography(camera.K, R, t)


def load_onboard_config(params: Mapping[str, object]) -> OnboardConfig:
    """Check flat parameters (keys of SETTINGS) and build the onboard configuration."""
    v = {s.key: _value(params, s) for s in SETTINGS}
    sub = {k.removeprefix('camera.'): x for k, x in v.items() if k.startswith('camera.')}
    camera = Camera.from_params('onboard_camera', {**sub, 'R': np.eye(3).ravel(),
                                                   't': np.zeros(3)}, 'camera.')
    if v['pose.refine'] == 'opencv' and camera.K[0, 1] != 0.0:
        raise ValueError(f"pose.refine: opencv ignores the skew of camera.K "
                         f"({camera.K[0, 1]:g}); use lm")
    T = camera_to_body(v['camera_to_base_link.xyz'], v['camera_to_base_link.rpy'])
    init_pose = None
    if v['init.mode'] == 'pose':
        R_wb = Rotation.from_euler('xyz', v['init.rpy']).as_matrix()
        H0 = homography_at(camera, T, R_wb, np.array(v['init.position']), 'init.position')
    elif v['init.mode'] == 'pose_topic':
        if not v['init.pose_topic']:
            raise CalibrationError('init.pose_topic: expected a topic name, got an empty one')
        H0 = None
        init_pose = InitFromPoses(v['init.pose_topic'], v['init.max_interval'],
                                  v['init.max_gap'], v['init.max_wait'])
    else:
        H0 = _reference_homography(camera, np.array(v['init.plane_points']),
                                   np.array(v['init.image_points']))
    for low, high in (('features.min_tracks', 'features.max_features'),
                      ('homography.min_inliers', 'features.min_tracks'),
                      ('homography.min_inliers', 'keyframe.reanchor_inliers'),
                      ('keyframe.reanchor_inliers', 'features.max_features')):
        if v[low] > v[high]:
            raise ValueError(f'{low}: {v[low]} must not exceed {high} ({v[high]})')
    if v['klt.win_size'] % 2 == 0 or v['features.block_size'] % 2 == 0:
        bad = 'klt.win_size' if v['klt.win_size'] % 2 == 0 else 'features.block_size'
        raise ValueError(f'{bad}: expected an odd number, got {v[bad]}')
    klt = KltParams(v['klt.win_size'], v['klt.max_level'], v['klt.max_iterations'],
                    v['klt.epsilon'], v['klt.min_eig_threshold'], v['klt.fb_max_error_px'],
                    v['features.quality_level'], v['features.min_distance_px'],
                    v['features.block_size'], v['features.detect_level'])
    pose = PlanePoseParams(
        klt, v['features.max_features'], v['features.min_tracks'], v['homography.min_inliers'],
        v['keyframe.reanchor_inliers'], v['keyframe.reanchor_coverage'],
        v['homography.method'], v['homography.threshold_px'], v['homography.confidence'],
        v['homography.max_trials'], v['pose.max_rms_px'], v['image_quality.blur_level'],
        v['image_quality.min_sharpness'], v['relocalise.after_frames'],
        v['relocalise.features'], v['relocalise.max_features'], v['relocalise.ratio'],
        v['relocalise.max_shift'], v['pose.refine'], v['covariance.pixel_sigma_floor'],
        v['covariance.init_position_sigma'], v['covariance.init_angle_sigma'])
    return OnboardConfig(camera, T, H0, pose, v['init.mode'], init_pose)


def camera_to_body(xyz: list[float], rpy: list[float]) -> np.ndarray:
    """4x4 pose of the optical frame in base_link (x_b = T x_c) from `camera_to_base_link.*`:
    origin xyz, m, and fixed-axis roll, pitch, yaw, rad (URDF)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('xyz', rpy).as_matrix()
    T[:3, 3] = xyz
    return T


def _value(params: Mapping[str, object], s: Setting) -> object:
    """The checked value of one setting (camera.* details are left to Camera.from_params)."""
    raw = params.get(s.key)
    if raw is None:
        if s.default is REQUIRED:
            raise CalibrationError(f'{s.key}: missing, expected {_expected(s)}')
        return s.default
    if s.key.startswith('camera.') and s.key != 'camera.frame_id':
        return raw
    if s.kind == 'str':
        ok = isinstance(raw, str) and (not s.choices or raw in s.choices)
    elif s.kind == 'floats':
        ok = (not isinstance(raw, (str, bytes)) and hasattr(raw, '__len__')
              and all(_is_number(x) for x in raw)
              and (len(raw) == s.size if s.size else len(raw) >= 8 and len(raw) % 2 == 0))
    else:
        ok = ((isinstance(raw, int) if s.kind == 'int' else _is_number(raw))
              and not isinstance(raw, bool) and s.low <= raw <= s.high)
    if not ok:
        error = CalibrationError if s.key.startswith(('camera', 'init')) else ValueError
        text = repr(raw) if len(repr(raw)) < 80 else repr(raw)[:77] + '...'
        raise error(f'{s.key}: expected {_expected(s)}, got {text}')
    if s.kind == 'floats':
        return [float(x) for x in raw]
    return {'int': int, 'float': float, 'str': str}[s.kind](raw)


def _expected(s: Setting) -> str:
    if s.kind == 'str':
        return 'one of ' + ', '.join(s.choices) if s.choices else 'a string'
    if s.kind == 'floats':
        if s.size is None:
            return 'a list of numbers'
        return f'{s.size} numbers' if s.size else 'x y pairs of numbers, at least 4 pairs'
    return f"{'an integer' if s.kind == 'int' else 'a number'} in [{s.low:g}, {s.high:g}]"


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and bool(np.isfinite(x))


def _reference_homography(camera: Camera, plane: np.ndarray, image: np.ndarray) -> np.ndarray:
    """H_0 by least squares (DLT) from >= 4 plane points and their raw pixels."""
    plane, image = plane.reshape(-1, 2), image.reshape(-1, 2)
    if len(plane) != len(image):
        raise CalibrationError(f'init.image_points: {len(image)} points for '
                               f'{len(plane)} init.plane_points')
    ideal = camera.undistort(image)
    H, _ = cv2.findHomography(plane, ideal, 0)
    if H is None or abs(np.linalg.det(H)) < 1e-12:
        raise CalibrationError('init.plane_points: degenerate (three or more collinear?)')
    q = plane @ H[:2, :2].T + H[:2, 2]
    q = q / (plane @ H[2, :2] + H[2, 2])[:, None]
    rms = float(np.sqrt(np.mean(np.sum((q - ideal) ** 2, axis=1))))
    if rms > 3.0:
        raise CalibrationError(f'init.image_points: do not match init.plane_points by a plane '
                               f'homography (RMS {rms:.1f} px > 3 px)')
    return H / H[2, 2]
