"""Planar target found in each frame by features + robust homography (chapter Fig. 2).

The template (e.g. a car seen from above, a helipad) is described once; each frame is
described, matched against it with the ratio test (section 2.2) and the template-to-
frame homography is estimated robustly (section 2.3, Algorithm 1). The target's
corners and centre are the template's corners and centre mapped by that homography.
The estimator defaults to the project's (homography.DEFAULT_METHOD, cv2 RANSAC);
'ransac' (Algorithm 1) is more accurate on the Oxford wide-baseline SIFT matches, the
kind this tracker makes, at a few ms a call more (homography.py).
"""
from dataclasses import dataclass

import numpy as np

from uav_vs.vision.features import DescribedImage, as_gray
from uav_vs.vision.homography import DEFAULT_METHOD, estimate_homography


@dataclass(frozen=True)
class TargetResult:
    """Where the target is in the frame; corners/center/H are None unless ok."""

    ok: bool
    corners: np.ndarray | None     # (4,2) px: template's TL, TR, BR, BL corners in the frame
    center: np.ndarray | None      # (2,) px: template centre mapped into the frame
    H: np.ndarray | None           # 3x3 template -> frame
    n_inliers: int
    reason: str


class PlanarTargetTracker:
    """Find one planar template in frames (Fig. 2)."""

    def __init__(self, template_gray: np.ndarray, kind: str = 'sift', ratio: float = 0.75,
                 method: str = DEFAULT_METHOD, threshold_px: float = 3.0, min_inliers: int = 12,
                 max_features: int = 0, rng: np.random.Generator | int | None = 0):
        template = as_gray(template_gray)
        self.ratio, self.method = ratio, method
        self.threshold_px, self.min_inliers = threshold_px, min_inliers
        self.rng = np.random.default_rng(rng)
        self.template = DescribedImage(template, kind, max_features)   # indexed once
        if len(self.template.xy) < min_inliers:
            raise ValueError(f'template has only {len(self.template.xy)} {kind} features, '
                             f'fewer than min_inliers={min_inliers}')
        h, w = template.shape
        self.corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
        self.center = np.array([w / 2, h / 2])

    def find(self, gray: np.ndarray) -> TargetResult:
        """Locate the template in one frame; a failure says why (no exception on bad frames)."""
        try:
            frame = as_gray(gray)
        except ValueError as err:
            return TargetResult(False, None, None, None, 0, str(err))
        template_px, frame_px = self.template.match(frame, self.ratio)
        r = estimate_homography(template_px, frame_px, self.method, self.threshold_px,
                                min_inliers=self.min_inliers, rng=self.rng)
        if not r.ok:
            return TargetResult(False, None, None, None, int(r.inliers.sum()), r.reason)
        q = np.c_[np.vstack([self.corners, self.center]), np.ones(5)] @ r.H.T
        q = q[:, :2] / q[:, 2:]
        return TargetResult(True, q[:4], q[4], r.H, int(r.inliers.sum()), '')
