"""Camera calibration from images of a board: what a real ground station needs before its
cameras can triangulate (chapter section 3.1, whose cameras are calibrated).

A board (`Board`: a chessboard, a ChArUco board or a circle grid, its size in metres) is
found in each image by OpenCV's own detectors (`detect`), and the intrinsics K and the
lens distortion D of one camera are solved from every view that shows it with
cv2.calibrateCamera (`calibrate_camera`). Detection and solving are separate steps, so
points found by a detector of one's own (`Detection`) calibrate just as well. Views
that would spoil the solution are dropped and named, each with its reason: blurred (the
board's edges too soft), too oblique (the board's normal too far from the optical
axis), or an outlier (its reprojection error far above the others'). How much of the
image the board's points covered is reported: a lens model is only known where it was
seen.

Distortion models (`MODELS`): 'pinhole' (none), 'k1' (one radial coefficient),
'plumb_bob' (k1, k2, p1, p2, k3: OpenCV's default and ROS's `plumb_bob`) and
'rational' (k1..k6, p1, p2: ROS's `rational_polynomial`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np
import yaml

BOARD_KINDS = ('chessboard', 'charuco', 'circles', 'acircles')
MODELS = {
    'pinhole': (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
                | cv2.CALIB_ZERO_TANGENT_DIST, 5),
    'k1': (cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, 5),
    'plumb_bob': (0, 5),
    'rational': (cv2.CALIB_RATIONAL_MODEL, 8),
}
ROS_DISTORTION_MODEL = {'pinhole': 'plumb_bob', 'k1': 'plumb_bob', 'plumb_bob': 'plumb_bob',
                        'rational': 'rational_polynomial'}
IMAGE_SUFFIXES = frozenset({'.png', '.jpg', '.jpeg', '.bmp', '.tif', '.tiff', '.pgm', '.ppm'})
COVERAGE_GRID = 10      # the image cut into 10 x 10 cells for the coverage figure
MIN_POINTS = 6          # a view with fewer of the board's points is no view


class CalibrationInputError(ValueError):
    """Input that cannot be calibrated; its text is one line for the user."""


@dataclass(frozen=True)
class Board:
    """A calibration board. chessboard, charuco: `rows` x `cols` squares of side `square`
    (the inner corners are the points); circles, acircles (asymmetric): `rows` x `cols`
    circles, `square` apart (for acircles, between neighbours on a row's diagonal, as
    OpenCV's sample board). charuco: markers of side `marker` from `dictionary`,
    `inverted` when printed white on black. Units: metres."""

    kind: str
    rows: int
    cols: int
    square: float
    marker: float = 0.0
    dictionary: str = 'DICT_4X4_50'
    inverted: bool = False

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise CalibrationInputError(f'board kind: expected one of {", ".join(BOARD_KINDS)}, '
                                   f'got {self.kind!r}')
        least = 2 if self.kind in ('chessboard', 'charuco') else 1
        if not (isinstance(self.rows, int) and isinstance(self.cols, int)
                and min(self.rows, self.cols) > least):
            raise CalibrationInputError(f'board rows, columns: expected integers above {least}, '
                                   f'got {self.rows} x {self.cols}')
        if not (isinstance(self.square, (int, float)) and self.square > 0):
            raise CalibrationInputError(f'board square: expected a size in metres above 0, got '
                                   f'{self.square!r}')
        if self.kind == 'charuco':
            if not 0 < self.marker < self.square:
                raise CalibrationInputError(f'board marker: expected a size in metres between 0 '
                                       f'and the square ({self.square:g}), got {self.marker!r}')
            if not hasattr(cv2.aruco, self.dictionary):
                raise CalibrationInputError(f'board dictionary: {self.dictionary!r} is not an '
                                       f'ArUco dictionary (e.g. DICT_4X4_50, DICT_5X5_100)')

    @classmethod
    def load(cls, path: Path) -> Board:
        """A board from a YAML file: kind, rows, cols, square, and for charuco marker,
        dictionary, inverted."""
        try:
            spec = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError) as err:
            raise CalibrationInputError(f'board file {path}: {err}') from None
        if not isinstance(spec, dict):
            raise CalibrationInputError(f'board file {path}: expected a mapping of kind, rows, '
                                   f'cols, square, ...')
        unknown = set(spec) - {'kind', 'rows', 'cols', 'square', 'marker', 'dictionary',
                               'inverted'}
        if unknown:
            raise CalibrationInputError(f'board file {path}: unknown keys '
                                        f'{", ".join(sorted(unknown))}')
        try:
            return cls(**spec)
        except TypeError as err:
            raise CalibrationInputError(f'board file {path}: {err}') from None

    @property
    def point_symmetric(self) -> bool:
        """True when the board turned half round shows the same pattern, so that a detector
        cannot tell its first point from its last: a chessboard whose rows and columns of
        squares are both odd or both even, any symmetric circle grid, an asymmetric one
        with an even number of rows. Cameras on opposite sides of such a board number
        its points from opposite ends; ChArUco boards never are."""
        if self.kind == 'chessboard':
            return self.rows % 2 == self.cols % 2
        return self.kind == 'circles' or (self.kind == 'acircles' and self.rows % 2 == 0)

    @property
    def pattern(self) -> tuple[int, int]:
        """OpenCV's pattern size (points per row, per column)."""
        if self.kind in ('chessboard', 'charuco'):
            return self.cols - 1, self.rows - 1
        return self.cols, self.rows

    def object_points(self) -> np.ndarray:
        """(N, 3) float32: every point of the board in its own frame (z = 0), the order
        of the ids a Detection gives."""
        if self.kind == 'charuco':
            return np.asarray(self.charuco().getChessboardCorners(), np.float32).reshape(-1, 3)
        nx, ny = self.pattern
        if self.kind == 'acircles':
            grid = [((2 * x + y % 2) * self.square / 2, y * self.square / 2)
                    for y in range(ny) for x in range(nx)]
        else:
            grid = [(x * self.square, y * self.square) for y in range(ny) for x in range(nx)]
        return np.array([(x, y, 0.0) for x, y in grid], np.float32)

    def charuco(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker,
                                      dictionary)


@dataclass(frozen=True)
class Detection:
    """The board's points found in one image: `ids` index Board.object_points(),
    `points` their (N, 2) pixels; `sharpness` how crisp the board's edges are (the
    variance of the Laplacian over the board, NaN if not measured)."""

    ids: np.ndarray
    points: np.ndarray
    sharpness: float = math.nan


def detect(board: Board, image: np.ndarray, min_points: int = MIN_POINTS) -> Detection | None:
    """The board in one image (grey or BGR), or None if not found (or fewer than
    `min_points` of its points)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if board.kind == 'chessboard':
        found, corners = cv2.findChessboardCornersSB(
            gray, board.pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY)
        if found:
            corners = refine_corners(gray, corners.reshape(-1, 2), board.pattern)
        ids = np.arange(board.pattern[0] * board.pattern[1])
    elif board.kind in ('circles', 'acircles'):
        grid = cv2.CALIB_CB_SYMMETRIC_GRID if board.kind == 'circles' else \
            cv2.CALIB_CB_ASYMMETRIC_GRID
        found, corners = cv2.findCirclesGrid(gray, board.pattern, flags=grid)
        ids = np.arange(board.pattern[0] * board.pattern[1])
    else:
        params = cv2.aruco.DetectorParameters()
        params.detectInvertedMarker = board.inverted
        detector = cv2.aruco.CharucoDetector(board.charuco(), detectorParams=params)
        corners, found_ids, _, _ = detector.detectBoard(gray)
        found = found_ids is not None
        ids = None if found_ids is None else found_ids.ravel()
    if not found or corners is None or len(corners) < min_points:
        return None
    points = np.asarray(corners, np.float32).reshape(-1, 2)
    return Detection(np.asarray(ids, np.int32), points, sharpness(gray, points))


SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
MAX_HALF_WINDOW = 7          # px, cv2.cornerSubPix's half window on large squares
AGREE_PX = 0.15              # a corner takes the wider window's answer within this


def refine_corners(gray: np.ndarray, corners: np.ndarray, pattern: tuple[int, int]
                   ) -> np.ndarray:
    """A chessboard's corners (N, 2) moved to where the image's gradients cross
    (cv2.cornerSubPix): findChessboardCornersSB alone lets a tilted board's corners lean
    with the perspective (0.1-0.2 px RMS on rendered boards, against 0.05-0.07 px
    refined), which the calibration takes for a longer focal length.

    The window is half as wide as the board's narrowest square in the image (2-7 px); on
    small squares (a board seen across the flight area, 5-10 px) one pixel wider is more
    exact where it holds, but may slide onto a neighbouring corner's edges, so each corner
    takes the wider window's answer only where the two agree within AGREE_PX (on rendered
    boards: 0.06 px RMS for the board on the ground 7 m away, 0.10 px with the narrow
    window alone)."""
    grid = corners.reshape(pattern[1], pattern[0], 2)
    narrowest = min(np.linalg.norm(np.diff(grid, axis=a), axis=2).min() for a in (0, 1))
    half = int(np.clip(narrowest / 2, 2, MAX_HALF_WINDOW))
    narrow = _subpix(gray, corners, half)
    if half == MAX_HALF_WINDOW:
        return narrow
    wide = _subpix(gray, corners, half + 1)
    agree = np.linalg.norm(wide - narrow, axis=1) < AGREE_PX
    return np.where(agree[:, None], wide, narrow)


def _subpix(gray: np.ndarray, corners: np.ndarray, half: int) -> np.ndarray:
    return cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2).astype(np.float32).copy(),
                            (half, half), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2)


def sharpness(gray: np.ndarray, points: np.ndarray) -> float:
    """Variance of the Laplacian inside the hull of the board's points: a blurred view
    of a board has soft edges and a small variance."""
    hull = cv2.convexHull(points.astype(np.float32)).astype(np.int32)
    mask = np.zeros(gray.shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, hull, 255)
    if not mask.any():
        return math.nan
    laplacian = cv2.Laplacian(gray, cv2.CV_64F)
    return float(laplacian[mask > 0].var())


@dataclass(frozen=True)
class Intrinsics:
    """One camera's calibration and every figure that judges it."""

    K: np.ndarray                   # 3x3
    D: np.ndarray                   # distortion coefficients, OpenCV's order
    model: str                      # one of MODELS
    size: tuple[int, int]           # width, height [px]
    rms: float                      # reprojection error over every point used [px]
    view_errors: dict[str, float]   # per view used: its RMS reprojection error [px]
    dropped: dict[str, str]         # per view left out: why
    coverage: float                 # share of the image's 10x10 cells holding a point
    rvecs: dict[str, np.ndarray] = field(default_factory=dict)   # board -> camera, per view
    tvecs: dict[str, np.ndarray] = field(default_factory=dict)

    def report(self, name: str) -> list[str]:
        """The calibration's figures, one line each."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        lines = [f'{name}: {self.size[0]}x{self.size[1]}, model {self.model}, '
                 f'{len(self.view_errors)} views used, RMS {self.rms:.3f} px, '
                 f'coverage {100 * self.coverage:.0f} % of the image',
                 f'  fx {fx:.3f}  fy {fy:.3f}  cx {cx:.3f}  cy {cy:.3f} px',
                 '  D ' + ' '.join(f'{d:.6g}' for d in self.D)]
        lines += [f'  view {view}: {err:.3f} px' for view, err in self.view_errors.items()]
        lines += [f'  dropped {view}: {why}' for view, why in self.dropped.items()]
        return lines


@dataclass(frozen=True)
class Limits:
    """When a view is dropped, and how many must remain."""

    min_views: int = 3              # fewer views left: no calibration
    blur_ratio: float = 0.1         # sharpness below this times the views' median: blurred
    max_tilt_deg: float = 75.0      # board normal this far from the optical axis: oblique
    outlier_factor: float = 3.0     # view RMS above this times the median: an outlier
    outlier_floor_px: float = 0.5   # ... and above this


def calibrate_camera(board: Board, views: dict[str, Detection], size: tuple[int, int],
                     model: str = 'plumb_bob', limits: Limits = Limits()) -> Intrinsics:
    """K and D of one camera from the board's detections in views named by their keys
    (file names, frame numbers), all of one image `size` (width, height)."""
    if model not in MODELS:
        raise CalibrationInputError(f'model: expected one of {", ".join(MODELS)}, got {model!r}')
    flags, _ = MODELS[model]
    dropped: dict[str, str] = {}
    used = {}
    sharp = [d.sharpness for d in views.values() if math.isfinite(d.sharpness)]
    least = limits.blur_ratio * float(np.median(sharp)) if sharp else 0.0
    for name, det in views.items():
        if det.sharpness < least:
            dropped[name] = (f'blurred (sharpness {det.sharpness:.0f}, median of the views '
                             f'{least / limits.blur_ratio:.0f})')
        else:
            used[name] = det
    objects = board.object_points()
    while True:
        if len(used) < limits.min_views:
            raise CalibrationInputError(
                f'too few views: {len(used)} usable of {len(views)} with the board '
                f'(at least {limits.min_views} needed)'
                + (f'; dropped: {"; ".join(f"{k} {v}" for k, v in dropped.items())}'
                   if dropped else ''))
        names = list(used)
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(
            [objects[used[n].ids] for n in names], [used[n].points for n in names], size,
            None, None, flags=flags)
        errors = {n: _view_rms(objects[used[n].ids], used[n].points, r, t, K, D)
                  for n, r, t in zip(names, rvecs, tvecs)}
        bad = _bad_views(names, errors, rvecs, limits)
        if not bad:
            break
        for n, why in bad.items():
            dropped[n] = why
            del used[n]
    points = np.vstack([used[n].points for n in names])
    return Intrinsics(K, D.ravel(), model, tuple(size), float(rms), errors, dropped,
                      coverage(points, size), dict(zip(names, rvecs)), dict(zip(names, tvecs)))


def _view_rms(objects: np.ndarray, points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
              K: np.ndarray, D: np.ndarray) -> float:
    projected, _ = cv2.projectPoints(objects, rvec, tvec, K, D)
    return float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - points) ** 2, axis=1))))


def _bad_views(names: list[str], errors: dict[str, float], rvecs, limits: Limits
               ) -> dict[str, str]:
    """The views to drop after one solution: too oblique, then outliers (the worst
    first: one outlier drags the others' errors up)."""
    bad = {}
    for n, rvec in zip(names, rvecs):
        normal = cv2.Rodrigues(rvec)[0][:, 2]
        tilt = math.degrees(math.acos(min(1.0, abs(float(normal[2])))))
        if tilt > limits.max_tilt_deg:
            bad[n] = f'too oblique (board {tilt:.0f} deg from facing the camera)'
    if bad:
        return bad
    median = float(np.median(list(errors.values())))
    worst = max(errors, key=errors.get)
    if errors[worst] > max(limits.outlier_factor * median, limits.outlier_floor_px):
        bad[worst] = (f'outlier (RMS {errors[worst]:.2f} px, median of the views '
                      f'{median:.2f} px)')
    return bad


def coverage(points: np.ndarray, size: tuple[int, int]) -> float:
    """Share of the image's COVERAGE_GRID x COVERAGE_GRID cells with a point in them."""
    w, h = size
    cells = np.floor(points / [w / COVERAGE_GRID, h / COVERAGE_GRID]).astype(int)
    inside = (cells >= 0).all(axis=1) & (cells < COVERAGE_GRID).all(axis=1)
    return len({tuple(c) for c in cells[inside]}) / COVERAGE_GRID ** 2


# ------------------------------------------------------------------ images and videos
def read_images(sources: Iterable[Path], every: int = 1, colour: bool = False
                ) -> Iterator[tuple[str, np.ndarray]]:
    """(name, grey image, or BGR with `colour`) of every image file, every image in a
    folder (sorted), and every `every`-th frame of every video ('<video>#<frame>')."""
    for source in map(Path, sources):
        if source.is_dir():
            files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not files:
                raise CalibrationInputError(f'{source}: no image files in the folder')
            for path in files:
                yield path.name, _read_image(path, colour)
        elif source.suffix.lower() in IMAGE_SUFFIXES:
            yield source.name, _read_image(source, colour)
        else:
            yield from read_video(source, every, colour)


def _read_image(path: Path, colour: bool = False) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise CalibrationInputError(f'{path}: cannot be read as an image')
    return image


def read_video(path: Path, every: int = 1, colour: bool = False
               ) -> Iterator[tuple[str, np.ndarray]]:
    """Every `every`-th frame of a video, grey (or BGR with `colour`), named
    '<file>#<frame index>'."""
    if not Path(path).is_file():
        raise CalibrationInputError(f'{path}: no such file')
    capture = cv2.VideoCapture(str(path))
    try:
        index = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if index % every == 0:
                yield (f'{Path(path).name}#{index}',
                       frame if colour else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
            index += 1
        if index == 0:
            raise CalibrationInputError(f'{path}: cannot be decoded as an image or a video')
    finally:
        capture.release()


def detect_all(board: Board, images: Iterable[tuple[str, np.ndarray]]
               ) -> tuple[dict[str, Detection], tuple[int, int], int]:
    """The board in every image: (detections by name, image size, images read). All the
    images must have one size; at least one must show the board."""
    found, size, count = {}, None, 0
    for name, image in images:
        count += 1
        shape = (image.shape[1], image.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise CalibrationInputError(f'{name} is {shape[0]}x{shape[1]}, the images before it '
                                   f'{size[0]}x{size[1]}: one camera, one image size')
        det = detect(board, image)
        if det is not None:
            found[name] = det
    if count == 0:
        raise CalibrationInputError('no images given')
    if not found:
        raise CalibrationInputError(f'no board found in any of the {count} images (a {board.kind} '
                               f'of {board.rows}x{board.cols}: check the board description)')
    return found, size, count


# ------------------------------------------------------------------ output
def camera_info_yaml(name: str, intrinsics: Intrinsics) -> str:
    """The camera_info YAML that camera_calibration writes and camera_info_manager loads."""
    K, (w, h) = intrinsics.K, intrinsics.size
    D = list(intrinsics.D[:MODELS[intrinsics.model][1]])
    P = np.hstack([K, np.zeros((3, 1))])

    def matrix(rows: int, cols: int, values) -> dict:
        return {'rows': rows, 'cols': cols, 'data': [float(v) for v in np.ravel(values)]}

    return yaml.safe_dump({
        'image_width': int(w), 'image_height': int(h), 'camera_name': name,
        'camera_matrix': matrix(3, 3, K),
        'distortion_model': ROS_DISTORTION_MODEL[intrinsics.model],
        'distortion_coefficients': matrix(1, len(D), D),
        'rectification_matrix': matrix(3, 3, np.eye(3)),
        'projection_matrix': matrix(3, 4, P)}, sort_keys=False)


def read_camera_info(path: Path) -> Intrinsics:
    """The intrinsics of a camera_info YAML file (camera_info_yaml's, or camera_calibration's)."""
    try:
        info = yaml.safe_load(Path(path).read_text())
        K = np.array(info['camera_matrix']['data'], float).reshape(3, 3)
        D = np.array(info['distortion_coefficients']['data'], float)
        size = (int(info['image_width']), int(info['image_height']))
        kind = info['distortion_model']
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as err:
        raise CalibrationInputError(f'camera_info file {path}: {err}') from None
    models = {'plumb_bob': 'plumb_bob', 'rational_polynomial': 'rational'}
    if kind not in models:
        raise CalibrationInputError(f'camera_info file {path}: distortion_model {kind!r}, '
                                    f'expected plumb_bob or rational_polynomial')
    return Intrinsics(K, D, models[kind], size, math.nan, {}, {}, math.nan)
