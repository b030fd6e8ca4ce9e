"""Image features for tracking and matching (chapter section 2 and 2.2).

- `robust_corners`: Harris / Shi-Tomasi good features to track, detected again with
  every detection window and kept only if their position stays put as the window
  grows and their minimum eigenvalue is large enough (the robustness test of section 2).
- `hough_lines`: straight lines (r, theta) by the Hough transform over Canny edges.
- `detect_and_describe` / `match`: SIFT (section 2.2.1) or ORB, the free alternative
  to SURF (2.2.2); FLANN matching (kd-tree for float descriptors, LSH for binary ones)
  with Lowe's ratio test.
"""
import cv2
import numpy as np
from scipy.spatial import cKDTree

KINDS = ('sift', 'orb')            # OpenCV 5's main modules have no AKAZE/SURF
_KDTREE, _LSH = 1, 6                                        # FLANN index algorithms
_SUBPIX = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)


def as_gray(image: np.ndarray) -> np.ndarray:
    """8-bit single-channel view of image, or a ValueError naming the problem."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or image.dtype != np.uint8 or min(image.shape) < 8:
        raise ValueError(f'expected an 8-bit grey or BGR image, got {image.dtype} {image.shape}')
    return image


def _corners_at(gray: np.ndarray, block: int, max_corners: int, quality: float,
                min_distance: int, use_harris: bool) -> np.ndarray:
    """Corners (N,2) detected with one detection window, refined sub-pixel in it."""
    pts = cv2.goodFeaturesToTrack(gray, max_corners, quality, min_distance,
                                  blockSize=block, useHarrisDetector=use_harris)
    if pts is None:
        return np.empty((0, 2), np.float32)
    return cv2.cornerSubPix(gray, pts, (block, block), (-1, -1), _SUBPIX)[:, 0]


def robust_corners(gray: np.ndarray, max_corners: int = 300, quality: float = 0.01,
                   min_distance: int = 8, block_sizes: tuple[int, ...] = (3, 5, 7, 9),
                   max_shift_px: float = 1.0, min_eigenvalue: float = 1e-3,
                   use_harris: bool = False) -> np.ndarray:
    """Corners (N,2) that are stable across detection windows (section 2).

    Corners are detected (Shi-Tomasi minimum eigenvalue, or Harris with use_harris)
    once per block size, each set refined sub-pixel in a window that grows with the
    block. A corner of the first (smallest) block size is kept if, at every larger
    size, the nearest corner detected lies within max_shift_px of it (maximum
    difference criterion) and the minimum eigenvalue of its structure tensor, at the
    largest block size, is at least min_eigenvalue (cv2.cornerMinEigenVal units: ~0.09
    for a 180-level step). Returns the kept corners' positions at the first size.
    """
    gray = as_gray(gray)
    if not block_sizes or any(b >= c for b, c in zip(block_sizes, block_sizes[1:])):
        raise ValueError(f'block_sizes must be increasing, got {block_sizes}')
    first, *larger = (_corners_at(gray, b, max_corners, quality, min_distance, use_harris)
                      for b in block_sizes)
    keep = np.ones(len(first), bool)
    for pts in larger:
        keep &= cKDTree(pts).query(first)[0] <= max_shift_px
    eig = cv2.cornerMinEigenVal(gray, block_sizes[-1], 3)
    xy = np.clip(np.round(first).astype(int), 0, [gray.shape[1] - 1, gray.shape[0] - 1])
    keep &= eig[xy[:, 1], xy[:, 0]] >= min_eigenvalue
    return first[keep]


def hough_lines(gray: np.ndarray, canny_low: int = 50, canny_high: int = 150,
                votes: int = 100, rho_px: float = 1.0, theta_rad: float = np.pi / 180,
                max_lines: int = 50) -> np.ndarray:
    """Lines (N,2) as (r, theta), x cos(theta) + y sin(theta) = r, strongest first (section 2).

    Edges come from Canny (whose gradients are Sobel derivatives); each edge pixel votes
    for the sinusoid of the lines through it and accumulator peaks are the lines.
    """
    edges = cv2.Canny(as_gray(gray), canny_low, canny_high)
    lines = cv2.HoughLines(edges, rho_px, theta_rad, votes)
    if lines is None:
        return np.empty((0, 2))
    return lines[:max_lines, 0].astype(float)


def _detector(kind: str, max_features: int) -> cv2.Feature2D:
    if kind == 'sift':
        return cv2.SIFT_create(nfeatures=max_features)
    if kind == 'orb':
        return cv2.ORB_create(nfeatures=max_features)
    raise ValueError(f'unknown feature kind {kind!r}; use one of {KINDS}')


def detect_and_describe(gray: np.ndarray, kind: str = 'sift', max_features: int = 0
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N,2) float64 and descriptors (N,D) (section 2.2).

    max_features 0 keeps every SIFT keypoint; ORB needs a cap (0 -> 5000).
    """
    detector = _detector(kind, max_features or (5000 if kind == 'orb' else 0))
    kps, desc = detector.detectAndCompute(as_gray(gray), None)
    xy = np.array([k.pt for k in kps], float).reshape(-1, 2)
    if desc is None:
        desc = np.empty((0, 128), np.float32) if kind == 'sift' else np.empty((0, 32), np.uint8)
    return xy, desc


def make_matcher(kind: str) -> cv2.FlannBasedMatcher:
    """FLANN: randomised kd-trees for SIFT (Beis & Lowe best-bin-first), LSH for binary."""
    if kind == 'sift':
        return cv2.FlannBasedMatcher({'algorithm': _KDTREE, 'trees': 5}, {'checks': 64})
    if kind == 'orb':
        return cv2.FlannBasedMatcher({'algorithm': _LSH, 'table_number': 6, 'key_size': 12,
                                      'multi_probe_level': 1}, {'checks': 64})
    raise ValueError(f'unknown feature kind {kind!r}; use one of {KINDS}')


def match(desc1: np.ndarray, desc2: np.ndarray | None, kind: str = 'sift', ratio: float = 0.75,
          matcher: cv2.DescriptorMatcher | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Indices (idx1, idx2) of matches passing Lowe's ratio test (section 2.2.1).

    A descriptor of image 1 is matched to its nearest neighbour in image 2 only if that
    is closer than ratio times the second nearest. desc2 None: match against the
    descriptors already added to (and trained in) `matcher`.
    """
    empty = np.empty(0, int)
    if len(desc1) == 0 or (desc2 is not None and len(desc2) < 2):
        return empty, empty
    matcher = matcher or make_matcher(kind)
    pairs = matcher.knnMatch(desc1, k=2) if desc2 is None else matcher.knnMatch(desc1, desc2, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    return (np.array([m.queryIdx for m in good], int), np.array([m.trainIdx for m in good], int))


class DescribedImage:
    """An image described once (section 2.2) and indexed by FLANN, to match frames against:
    a target template, a keyframe to relocalise on."""

    def __init__(self, gray: np.ndarray, kind: str = 'sift', max_features: int = 0) -> None:
        self.kind, self.max_features = kind, max_features
        self.xy, desc = detect_and_describe(gray, kind, max_features)
        self._index = make_matcher(kind)
        if len(desc):
            self._index.add([desc])
            self._index.train()

    def match(self, gray: np.ndarray, ratio: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints of `gray` matched to this image's by the ratio test: (this image's
        (M,2), the frame's (M,2)), pixels."""
        if len(self.xy) < 2:
            return np.empty((0, 2)), np.empty((0, 2))
        xy, desc = detect_and_describe(gray, self.kind, self.max_features)
        i_frame, i_self = match(desc, None, self.kind, ratio, matcher=self._index)
        return self.xy[i_self], xy[i_frame]
