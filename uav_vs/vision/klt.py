"""Sparse pyramidal Lucas-Kanade feature tracking (chapter sections 2.1.1-2.1.2).

Each feature is a small window tracked by translation (eq 6-12, sparse L-K), solved
coarse to fine over an image pyramid (Bouguet's pyramidal L-K, section 2.1.2) by
`cv2.calcOpticalFlowPyrLK`. A track is kept only if tracking it back from the new
frame lands within `fb_max_error_px` of where it started (forward-backward check).
New features are good-features-to-track (Shi-Tomasi minimum eigenvalue, section 2)
detected on a coarser pyramid level, away from the tracks that survive.

Points are (N, 2) float32 pixel coordinates (x right, y down) in the image as given.
"""
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class KltParams:
    """Tracking and detection settings (pixels refer to the full-resolution image)."""

    win_size: int = 15               # L-K window side, px (section 2.1.1)
    max_level: int = 3               # deepest pyramid level L_m (section 2.1.2)
    max_iterations: int = 20         # L-K iterations per level
    epsilon: float = 0.03            # L-K stop when the update is below this, px
    min_eig_threshold: float = 1e-3  # reject windows whose gradient matrix is this flat
    fb_max_error_px: float = 0.5     # forward-backward disagreement allowed, px
    quality_level: float = 0.01      # GFTT: min eigenvalue relative to the strongest corner
    min_distance_px: float = 20.0    # GFTT: spacing between features, and from old tracks
    block_size: int = 5              # GFTT: eigenvalue window, px at the detection level
    detect_level: int = 1            # pyramid level that features are detected on (0 = full)


class KltTracker:
    """Pyramidal L-K with a forward-backward check, and GFTT re-seeding."""

    def __init__(self, params: KltParams = KltParams()) -> None:
        self.params = params
        p = params
        self._lk = dict(winSize=(p.win_size, p.win_size), maxLevel=p.max_level,
                        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                  p.max_iterations, p.epsilon),
                        minEigThreshold=p.min_eig_threshold)
        self._scale = 2 ** p.detect_level

    def track(self, prev_gray: np.ndarray, gray: np.ndarray, pts: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """Track `pts` (N,2) from prev_gray into gray; return (new points (N,2), ok (N,) bool).

        ok means: found both ways, back-tracked to within fb_max_error_px of the start,
        and inside the image.
        """
        p0 = np.ascontiguousarray(pts, np.float32).reshape(-1, 1, 2)
        if len(p0) == 0:
            return np.empty((0, 2), np.float32), np.zeros(0, bool)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, p0, None, **self._lk)
        p0r, st0, _ = cv2.calcOpticalFlowPyrLK(gray, prev_gray, p1, None, **self._lk)
        p1 = p1.reshape(-1, 2)
        fb = np.abs(p0r - p0).reshape(-1, 2).max(axis=1)
        h, w = gray.shape[:2]
        ok = ((st1.ravel() == 1) & (st0.ravel() == 1) & (fb < self.params.fb_max_error_px)
              & (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1))
        return p1, ok

    def detect(self, gray: np.ndarray, max_count: int, avoid: np.ndarray | None = None,
               region: np.ndarray | None = None) -> np.ndarray:
        """Up to max_count new GFTT features (M,2), at least min_distance_px from `avoid`.

        `region` (uint8, image size) limits detection to its non-zero pixels. Detection
        runs on pyramid level `detect_level`, so locations are good to about
        2**detect_level px: enough, because a track follows whatever window it starts on.
        """
        p, s = self.params, self._scale
        if max_count <= 0:
            return np.empty((0, 2), np.float32)
        small = gray
        for _ in range(p.detect_level):
            small = cv2.pyrDown(small)
        h, w = small.shape
        mask = None
        if region is not None:
            mask = np.ascontiguousarray(region[::s, ::s][:h, :w])
        if avoid is not None and len(avoid):
            mask = np.full((h, w), 255, np.uint8) if mask is None else mask
            r = max(1, int(round(p.min_distance_px / s)))
            for x, y in np.rint(np.asarray(avoid) / s).astype(int):
                cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        corners = cv2.goodFeaturesToTrack(small, max_count, p.quality_level,
                                          p.min_distance_px / s, mask=mask,
                                          blockSize=p.block_size)
        if corners is None:
            return np.empty((0, 2), np.float32)
        return (corners.reshape(-1, 2) * s).astype(np.float32)

    def top_up(self, gray: np.ndarray, pts: np.ndarray, target: int,
               region: np.ndarray | None = None) -> np.ndarray:
        """New features to bring len(pts) up to `target` (re-seeding), away from pts."""
        return self.detect(gray, target - len(pts), pts, region)
