"""Onboard camera pose over a ground plane from chained homographies (chapter section 4, eq 27).

Following Simon et al. (2000): the ground is the plane z = 0 of the `world` frame
(ENU, the vehicle above it at z > 0). A plane point (X, Y, 0) projects by eq 27 as
s x = K [r1 r2 r3 t] (X, Y, 0, 1)^T = K [r1 r2 t] (X, Y, 1)^T, so the plane-to-image
homography is H = K [r1 r2 t] and the pose comes back from K^-1 H (section 4.1); the
eq 27 geometry itself (H from a pose, the pose from H, its refinement) is in
plane_geometry.py.

Conventions:
- R, t are world-to-camera (x_c = R x_w + t, as `Camera`); the optical frame is
  x right, y down, z forward (the down-looking camera's z points at the ground).
- Homographies map plane (X, Y, 1) in metres to ideal (undistorted) pixels.
- Poses handed out are world-from-frame: position of the frame's origin in `world`
  and its orientation R_w (columns are the frame's axes), quaternion x y z w.

Drift control: features are detected in a KEYFRAME and mapped onto the plane through
the keyframe's plane homography H_k. Each frame, the keyframe is warped (through the
lens model) by the predicted keyframe-to-frame homography and the features are tracked
from it into the frame by pyramidal L-K (section 2.1.2): they are measured against the
keyframe itself, so nothing accumulates from frame to frame. The robust
keyframe-to-frame homography (section 2.3, Algorithm 1) is chained onto H_k, never the
product of every frame-to-frame matrix, decomposed, and the pose refined by
Levenberg-Marquardt on the inliers' plane points. When inliers or image coverage drop,
the current frame becomes the new keyframe (a re-anchor): tracks that survive keep
their plane points, new features get theirs from the current estimate.

Relocalisation: L-K only converges near its prediction, so after a loss during which
the vehicle kept moving (occlusion, blur, a dropout) the last good homography no
longer predicts the frame. From the `relocalise_after`-th consecutive lost frame on,
the keyframe is also matched against the frame by descriptors (section 2.2: SIFT or
ORB, FLANN, ratio test) and a robust homography (section 2.3); that homography becomes
the prediction for the usual keyframe tracking, which alone decides whether the
frame has a pose, so a wrong match costs a retry. Only a repeated ground texture can
look right in the wrong place: a match that moves the camera farther than
`relocalise_max_shift` times its height from its last good position is refused.
"""
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from uav_vs.vision.camera import Camera
from uav_vs.vision.features import DescribedImage
from uav_vs.vision.homography import estimate_homography
from uav_vs.vision.klt import KltParams, KltTracker
from uav_vs.vision.plane_geometry import (DEFAULT_REFINER, plane_homography,
                                          pose_from_plane_homography, refine_plane_pose)
from uav_vs.vision.plane_pose_covariance import fit_covariance


@dataclass(frozen=True)
class PlanePoseParams:
    """Feature, homography, keyframe and image-quality settings (config/onboard.yaml)."""

    klt: KltParams = KltParams()
    max_features: int = 120          # tracks kept after a re-anchor
    min_tracks: int = 20             # fewer L-K survivors: tracking loss
    min_inliers: int = 15            # fewer homography inliers: tracking loss
    reanchor_inliers: int = 70       # re-anchor when inliers drop below this
    reanchor_coverage: float = 0.35  # ... or their bounding box covers less of the image
    method: str = 'opencv_magsac'    # robust homography estimator (homography.py)
    threshold_px: float = 2.0        # inlier distance for the homography, px
    confidence: float = 0.995        # RANSAC confidence p (Algorithm 1)
    max_trials: int = 500            # RANSAC trial cap
    max_rms_px: float = 1.5          # refined pose reprojection RMS above this: loss
    blur_level: int = 2              # pyramid level the sharpness is measured on
    min_sharpness: float = 50.0      # variance of the Laplacian at blur_level below: loss
    relocalise_after: int = 2        # consecutive lost frames before matching features; 0 never
    relocalise_features: str = 'orb'  # descriptor for relocalisation (features.KINDS)
    relocalise_max_features: int = 1000  # keypoints per image for relocalisation
    relocalise_ratio: float = 0.8    # Lowe's ratio test for relocalisation matches
    relocalise_max_shift: float = 1.0  # camera moved farther than this x its height: refused
    refine: str = DEFAULT_REFINER    # pose refinement on the inliers (plane_geometry.REFINERS)
    pixel_sigma_floor: float = 0.1   # the covariance's pixel noise is never taken smaller, px
    init_position_sigma: float = 0.02  # the first keyframe's pose: its position, m per axis
    init_angle_sigma: float = 0.01   # ... and its rotation, rad per axis


@dataclass
class PlanePose:
    """One frame's result.

    position, R, quaternion (x y z w): base_link in `world` when a camera-to-body
    extrinsic is set, else the camera optical frame. camera_position / camera_R are
    always the optical frame in `world`; H maps the plane to ideal pixels; `covariance`
    is the pose's (x, y, z, rotation about world x, y, z: uav_vs.vision.
    plane_pose_covariance). When ok is False the pose fields are None and `reason` says
    why (tracking loss).
    """

    ok: bool
    position: np.ndarray | None = None
    quaternion: np.ndarray | None = None
    R: np.ndarray | None = None
    camera_position: np.ndarray | None = None
    camera_R: np.ndarray | None = None
    H: np.ndarray | None = None
    reason: str = ''
    stats: dict = field(default_factory=dict)
    covariance: np.ndarray | None = None


def body_pose(R_cw: np.ndarray, t: np.ndarray, camera_to_body: np.ndarray | None
              ) -> tuple[np.ndarray, np.ndarray]:
    """World-from-body rotation and position from the camera's world-to-camera R, t.

    camera_to_body is the 4x4 pose of the optical frame in base_link (x_b = T x_c);
    None returns the optical frame itself.
    """
    R_wc, c = R_cw.T, -R_cw.T @ t
    if camera_to_body is None:
        return R_wc, c
    R_wb = R_wc @ camera_to_body[:3, :3].T
    return R_wb, c - R_wb @ camera_to_body[:3, 3]


def camera_pose(R_wb: np.ndarray, p_wb: np.ndarray, camera_to_body: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera R, t of the camera on a body at world-from-body R_wb, p_wb."""
    if camera_to_body is None:
        R_wc, c = R_wb, p_wb
    else:
        R_wc = R_wb @ camera_to_body[:3, :3]
        c = p_wb + R_wb @ camera_to_body[:3, 3]
    return R_wc.T, -R_wc.T @ c


class PlanePoseEstimator:
    """Camera / vehicle pose over the ground plane, frame by frame (section 4).

    State: the keyframe (raw image, plane homography H_k), the tracks (their ideal
    pixels in the keyframe and their plane points), the keyframe-to-frame homography
    of the last good frame and the last inter-frame motion (for the prediction). A lost
    frame leaves the state untouched, so tracking resumes from the last good one.
    """

    def __init__(self, camera: Camera, params: PlanePoseParams = PlanePoseParams(),
                 camera_to_body: np.ndarray | None = None, seed: int = 0) -> None:
        if not (camera.width and camera.height):
            raise ValueError('camera: the image size (width, height) is needed to track features')
        self.camera = camera
        self.params = params
        self.camera_to_body = None if camera_to_body is None else np.asarray(camera_to_body, float)
        self.klt = KltTracker(params.klt)
        self._rng = np.random.default_rng(seed)
        self._warp = KeyframeWarp(camera)
        # Features start half a window inside the image.
        self._margin = m = params.klt.win_size // 2 + 1
        self._region = np.zeros((camera.height, camera.width), np.uint8)
        self._region[m:-m, m:-m] = 255
        self._key: np.ndarray | None = None        # keyframe, raw image
        self._H_k = np.eye(3)                       # plane -> keyframe ideal pixels
        self._kf_px = np.empty((0, 2))              # tracks in the keyframe, ideal px
        self._xyz = np.empty((0, 3))                # their plane points (X, Y, 0), m
        self._H_prev = np.eye(3)                    # keyframe -> last good frame (ideal px)
        self._motion = np.eye(3)                    # last good inter-frame homography
        self._key_features: DescribedImage | None = None   # the keyframe's, when needed
        self._centre = np.zeros(3)                  # camera centre of the last good frame, m
        self._map_cov = np.zeros((6, 6))            # the tracks' plane points' error (drift)
        self.reanchors = 0
        self.relocalisations = 0
        self.lost_frames = 0

    @property
    def initialised(self) -> bool:
        return self._key is not None

    @property
    def drift_covariance(self) -> np.ndarray:
        """6x6 covariance of the error the tracks' plane points carry (the first keyframe's
        and the re-anchors'): what every pose has beside its own fit's."""
        return self._map_cov.copy()

    def initialise(self, gray: np.ndarray, init: np.ndarray | tuple) -> PlanePose:
        """Start on `gray` with the first frame's plane-to-image homography H_0.

        `init` is H_0 (3x3, plane metres to ideal pixels, e.g. from reference points),
        or (position (3,), quaternion xyzw (4,)) of base_link in `world` (the camera's
        height and attitude), from which H_0 = K [r1 r2 t] (eq 27).
        """
        gray = self._check(gray)
        if isinstance(init, tuple):
            position, quaternion = init
            R_wb = Rotation.from_quat(quaternion).as_matrix()
            H0 = plane_homography(self.camera.K, *camera_pose(R_wb, np.asarray(position, float),
                                                              self.camera_to_body))
        else:
            H0 = np.asarray(init, float)
        if H0.shape != (3, 3) or not np.all(np.isfinite(H0)) or abs(np.linalg.det(H0)) < 1e-12:
            raise ValueError('initial plane homography: expected a finite, invertible 3x3 matrix')
        stats: dict = {'sharpness': round(sharpness(gray, self.params.blur_level), 1)}
        if stats['sharpness'] < self.params.min_sharpness:
            return self._lost(self._blurred(stats['sharpness']), stats)
        new = self.klt.detect(gray, self.params.max_features, region=self._region)
        if len(new) < self.params.min_tracks:
            return self._lost(f'too few features to initialise ({len(new)} < '
                              f'{self.params.min_tracks})', {**stats, 'tracked': len(new)})
        self._kf_px, self._xyz = np.empty((0, 2)), np.empty((0, 3))
        self._new_keyframe(gray, H0 / H0[2, 2], new)
        self.reanchors, self.relocalisations, self.lost_frames = 0, 0, 0
        self._motion = np.eye(3)
        p = self.params
        self._map_cov = np.diag([p.init_position_sigma ** 2] * 3 + [p.init_angle_sigma ** 2] * 3)
        R, t = pose_from_plane_homography(self.camera.K, H0)
        return self._result(R, t, {**stats, 'tracked': len(new), 'inliers': len(new),
                                   'trials': 0, 'rms_px': 0.0, 'reanchored': True},
                            np.zeros((6, 6)))

    def update(self, gray: np.ndarray, covariance: bool = True) -> PlanePose:
        """Pose for the next frame, or a tracking loss with the reason (state kept).

        With `covariance` False the pose carries none (covariance None): the fit's is then
        solved only on the frames that re-anchor, whose error the drift takes on."""
        p = self.params
        try:
            gray = self._check(gray)
        except ValueError as exc:
            return self._lost(str(exc), {})
        if self._key is None:
            return self._lost('not initialised', {})
        stats: dict = {'sharpness': round(sharpness(gray, p.blur_level), 1)}
        if stats['sharpness'] < p.min_sharpness:
            return self._lost(self._blurred(stats['sharpness']), stats)
        result = self._track(gray, self._motion @ self._H_prev, self._H_prev, stats,
                             covariance)
        if isinstance(result, str) and 0 < p.relocalise_after <= self.lost_frames + 1:
            H = self._relocalise(gray)
            if H is not None:
                tracks = self._kf_px, self._xyz
                self._reseed_overlap(H)
                retry = self._track(gray, H, H, dict(stats), covariance)
                if not isinstance(retry, str):
                    self.relocalisations += 1
                    retry.stats.update(relocalised=True, **self._counters())
                    return retry
                self._kf_px, self._xyz = tracks
                result = f'{result}; relocalised, then {retry}'
        return self._lost(result, stats) if isinstance(result, str) else result

    def _track(self, gray: np.ndarray, H_pred: np.ndarray, H_prev: np.ndarray, stats: dict,
               covariance: bool) -> PlanePose | str:
        """Keyframe tracking from the predicted keyframe-to-frame homography H_pred; H_prev
        is the homography the motion model starts from. The pose, or why there is none."""
        p = self.params
        # Track the keyframe's features from the keyframe warped by the predicted
        # keyframe-to-frame homography: no drift accumulates within a keyframe.
        template = self._warp.warp(self._key, H_pred)
        start = self._warp.distort(_apply(H_pred, self._kf_px))
        raw, ok = self.klt.track(template, gray, start)
        stats['tracked'] = n = int(ok.sum())
        if n < p.min_tracks:
            return f'too few tracked features ({n} < {p.min_tracks})'
        pts, xyz, kf_px = self.camera.undistort(raw[ok]), self._xyz[ok], self._kf_px[ok]
        est = estimate_homography(kf_px, pts, method=p.method, threshold_px=p.threshold_px,
                                  confidence=p.confidence, max_trials=p.max_trials,
                                  min_inliers=p.min_inliers, rng=self._rng)
        stats['trials'] = est.trials
        stats['inliers'] = int(est.inliers.sum()) if est.ok else 0
        if not est.ok:
            return f'homography: {est.reason}'
        pts, xyz, kf_px = pts[est.inliers], xyz[est.inliers], kf_px[est.inliers]
        # Chain the keyframe-to-frame homography onto the keyframe's plane homography
        # (eq 27), decompose, then refine the pose on the inliers' plane points.
        R, t = pose_from_plane_homography(self.camera.K, est.H @ self._H_k)
        fit = refine_plane_pose(self.camera.K, xyz, pts, R, t, method=p.refine)
        R, t, rms = fit.R, fit.t, fit.rms_px
        proj = xyz @ (self.camera.K @ R).T + self.camera.K @ t
        stats['rms_px'] = round(rms, 3)
        if not rms <= p.max_rms_px:
            return f'reprojection RMS {rms:.2f} px > {p.max_rms_px:g}'
        if np.any(proj[:, 2] <= 0):
            return 'plane behind the camera'
        self._motion = est.H @ np.linalg.inv(H_prev)
        self._H_prev, self._kf_px, self._xyz = est.H, kf_px, xyz
        self.lost_frames = 0
        stats['reanchored'] = reanchor = bool(self._needs_reanchor(pts))
        fit = None
        if covariance or reanchor:
            fit, sigma = fit_covariance(
                self.camera.K, R, t, xyz, pts, body_pose(R, t, self.camera_to_body)[1],
                p.pixel_sigma_floor)
            stats['pixel_sigma'] = round(sigma, 3)
        result = self._result(R, t, stats, fit if covariance else None)
        if reanchor:
            # Survivors keep their plane points (anchoring); new features get theirs
            # from the current estimate, and its error with them.
            self._kf_px = pts
            new = self.klt.top_up(gray, raw[ok][est.inliers], p.max_features, self._region)
            self._new_keyframe(gray, plane_homography(self.camera.K, R, t), new)
            self._map_cov = self._map_cov + fit
            self.reanchors += 1
        stats.update(self._counters())
        return result

    def _relocalise(self, gray: np.ndarray) -> np.ndarray | None:
        """Keyframe-to-frame homography (ideal px) from descriptor matches, or None."""
        p = self.params
        if self._key_features is None:      # described once per keyframe, when first needed
            self._key_features = DescribedImage(self._key, p.relocalise_features,
                                                p.relocalise_max_features)
        if len(self._key_features.xy) < p.min_inliers:
            return None
        key_px, frame_px = self._key_features.match(gray, p.relocalise_ratio)
        if len(key_px) < p.min_inliers:
            return None
        est = estimate_homography(self.camera.undistort(key_px), self.camera.undistort(frame_px),
                                  method=p.method, threshold_px=p.threshold_px,
                                  confidence=p.confidence, max_trials=p.max_trials,
                                  min_inliers=p.min_inliers, rng=self._rng)
        if not est.ok:
            return None
        # A repeated texture can match elsewhere: refuse a jump no flight could have made.
        R, t = pose_from_plane_homography(self.camera.K, est.H @ self._H_k)
        shift = np.linalg.norm(-R.T @ t - self._centre)
        return est.H if shift <= p.relocalise_max_shift * self._centre[2] else None

    def _reseed_overlap(self, H: np.ndarray) -> None:
        """Tracks for a relocalised frame: the keyframe's tracks that H maps into the frame,
        topped up with keyframe features where the frame overlaps it (plane points from H_k)."""
        p = self.params
        raw = self._warp.distort(_apply(H, self._kf_px))
        m = self._margin
        keep = np.all((raw >= m) & (raw < [self.camera.width - m, self.camera.height - m]), axis=1)
        self._kf_px, self._xyz = self._kf_px[keep], self._xyz[keep]
        overlap = self._warp.warp(self._region, np.linalg.inv(H))
        self._add_tracks(self.klt.top_up(self._key, self._warp.distort(self._kf_px),
                                         p.max_features, (overlap > 127).astype(np.uint8) * 255))

    def _needs_reanchor(self, pts: np.ndarray) -> bool:
        """Too few inliers, or they cover too little of the image (overlap dropping)."""
        if len(pts) < self.params.reanchor_inliers:
            return True
        span = pts.max(axis=0) - pts.min(axis=0)
        image_area = self.camera.width * self.camera.height
        return span[0] * span[1] < self.params.reanchor_coverage * image_area

    def _new_keyframe(self, gray: np.ndarray, H_k: np.ndarray, new_raw: np.ndarray) -> None:
        """Make gray the keyframe with plane homography H_k; add features `new_raw` (raw px)."""
        self._key, self._H_k, self._H_prev = gray, H_k, np.eye(3)
        self._key_features = None
        self._add_tracks(new_raw)

    def _add_tracks(self, raw: np.ndarray) -> None:
        """Keyframe features (raw px) become tracks; their plane points come through H_k."""
        if len(raw):
            ideal = self.camera.undistort(raw)
            xy = _apply(np.linalg.inv(self._H_k), ideal)
            self._kf_px = np.vstack([self._kf_px, ideal])
            self._xyz = np.vstack([self._xyz, np.column_stack([xy, np.zeros(len(xy))])])

    def _check(self, gray: np.ndarray) -> np.ndarray:
        img = np.asarray(gray)
        if img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if img.dtype != np.uint8 or img.ndim != 2:
            raise ValueError(f'image: expected 8-bit grey or BGR, got {img.dtype} {img.shape}')
        if img.shape != (self.camera.height, self.camera.width):
            raise ValueError(f'image: {img.shape[1]}x{img.shape[0]} does not match the camera '
                             f'({self.camera.width}x{self.camera.height})')
        return img

    def _blurred(self, sharp: float) -> str:
        return (f'blurred or texture-less image (sharpness {sharp:.1f} < '
                f'{self.params.min_sharpness:g})')

    def _counters(self) -> dict:
        return dict(reanchors=self.reanchors, relocalisations=self.relocalisations,
                    lost_frames=self.lost_frames)

    def _lost(self, reason: str, stats: dict) -> PlanePose:
        self.lost_frames += 1
        self._motion = np.eye(3)
        stats.update(self._counters())
        return PlanePose(False, reason=reason, stats=stats)

    def _result(self, R: np.ndarray, t: np.ndarray, stats: dict, fit: np.ndarray | None
                ) -> PlanePose:
        """The frame's pose, its covariance that of the fit `fit` and of the map (None
        without `fit`)."""
        R_wc, c = body_pose(R, t, None)
        R_w, pos = body_pose(R, t, self.camera_to_body)
        self._centre = c
        stats.update(self._counters())
        return PlanePose(True, pos, Rotation.from_matrix(R_w).as_quat(), R_w, c, R_wc,
                         plane_homography(self.camera.K, R, t), '', stats,
                         None if fit is None else fit + self._map_cov)


class KeyframeWarp:
    """Warps a raw keyframe into the raw geometry of a frame, given the homography between
    their ideal (undistorted) images: raw frame -> undistort -> H^-1 -> distort -> keyframe.

    The map is evaluated exactly on a grid every `step` px and interpolated bilinearly
    in between (the error is a few thousandths of a pixel for lens distortion), so one
    remap replaces undistorting the frame and warping the keyframe.
    """

    def __init__(self, camera: Camera, step: int = 8) -> None:
        self.camera = camera
        self._at_origin = replace(camera, R=np.eye(3), t=np.zeros(3))
        self.step = step
        nx, ny = -(-camera.width // step) + 2, -(-camera.height // step) + 2
        # cv2.resize puts grid node j at x = (j + 0.5) step - 0.5; one node of margin each side.
        gx = (np.arange(nx) - 0.5) * step - 0.5
        gy = (np.arange(ny) - 0.5) * step - 0.5
        u, v = np.meshgrid(gx, gy)
        self._grid_ideal = camera.undistort(np.column_stack([u.ravel(), v.ravel()]))
        self._shape = (ny, nx)

    def distort(self, ideal: np.ndarray) -> np.ndarray:
        """Ideal pixels (N,2) to raw (distorted) pixels (N,2)."""
        ray = np.column_stack([ideal, np.ones(len(ideal))]) @ np.linalg.inv(self.camera.K).T
        return self._at_origin.project(ray)

    def warp(self, key: np.ndarray, H: np.ndarray) -> np.ndarray:
        """The keyframe as seen in a frame whose ideal pixels are H (keyframe ideal px)."""
        grid = self.distort(_apply(np.linalg.inv(H), self._grid_ideal)).astype(np.float32)
        ny, nx = self._shape
        s, w, h = self.step, self.camera.width, self.camera.height
        maps = cv2.resize(grid.reshape(ny, nx, 2), (nx * s, ny * s), interpolation=cv2.INTER_LINEAR)
        return cv2.remap(key, maps[s:s + h, s:s + w], None, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


def sharpness(gray: np.ndarray, level: int) -> float:
    """Variance of the Laplacian on pyramid level `level` (low: blurred or texture-less)."""
    for _ in range(level):
        gray = cv2.pyrDown(gray)
    return float(cv2.meanStdDev(cv2.Laplacian(gray, cv2.CV_16S))[1][0, 0] ** 2)


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a homography to (N,2) points."""
    q = pts @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:]
