"""Ground landmark detection (chapter section 3.1, eq 18-19): 4 landmarks, 640x480.

Cases `ground/detection` (frames rendered by the project's simulator,
uav_vs.sim.ground_scene, for each camera of config/ground_trinocular.yaml along the
figure-eight; detector built from that file as camshift_node builds it) and
`ground/detection_megamind` (real frames of OpenCV's Megamind.avi, cropped to
640x480). Ours (`LandmarkDetector`, tracking state) against the OpenCV-sample way:
full-frame cvtColor + calcBackProject + CamShift per landmark, same frames, same
process. `agree_px` is the median / max distance between the two centroids;
`truth_err_px` the distance of ours from the true projected landmark centres, over
the landmarks not occluded (>= 99 % of the sphere visible). The shaded discs
(`synthetic_frames`, `render_discs`) are the detector's unit-test scenes
(test/test_landmarks.py).
"""
from dataclasses import fields
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from bench.common import report, timeit
from uav_vs.datasets import shared_data_dir
from uav_vs.sim.ground_scene import GroundScene, figure_eight
from uav_vs.vision.colour_model import HSV_RANGES, ColourModel, models_from_params
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file
from uav_vs.vision.landmarks import DetectorParams, LandmarkDetector, Rect, centroids

ASSETS = Path(__file__).resolve().parents[1] / 'uav_vs' / 'sim' / 'assets'
SIZE = (640, 480)
RATE_HZ = 30.0
SCENE_FRAMES = 200        # per camera: 6.7 s of the figure-eight at 30 Hz

# name: (BGR at full light, hue range, saturation range, value range)
COLOURS = {
    'red': ((40, 30, 215), (170, 8), (120, 255), (60, 255)),
    'green': ((50, 190, 40), (45, 75), (120, 255), (60, 255)),
    'blue': ((215, 100, 25), (100, 125), (120, 255), (60, 255)),
    'yellow': ((30, 210, 225), (22, 38), (120, 255), (60, 255)),
}

# Megamind.avi, first shot (frames 1-97), cropped at (40, 24) to 640x480: four
# regions tracked as landmarks (x, y, w, h in the first frame of the crop).
MEGAMIND_CROP = (40, 24)
MEGAMIND_REGIONS = {'dress': (155, 310, 180, 170), 'candle': (405, 365, 85, 110),
                    'lamp': (485, 290, 35, 70), 'tablecloth': (500, 365, 100, 40)}


def colour_models(bins: tuple[int, int] = (30, 32)) -> list[ColourModel]:
    """The synthetic scene's four landmark models, from colour ranges."""
    return [ColourModel.from_ranges(n, hue=c[1], saturation=c[2], value=c[3], bins=bins)
            for n, c in COLOURS.items()]


def background() -> np.ndarray:
    """A real aerial photo, 640x480."""
    return cv2.resize(cv2.imread(str(ASSETS / 'aero1.jpg')), SIZE, interpolation=cv2.INTER_AREA)


def render_discs(bg: np.ndarray, centres: np.ndarray, colours: Sequence[Sequence[int]],
                 radius: float, rng: np.random.Generator, noise: float = 3.0,
                 visible: Sequence[bool] | None = None) -> np.ndarray:
    """Anti-aliased discs with sub-pixel centres (x, y), shaded like lit spheres
    (brightness 0.65..1 across the disc, hue and saturation unchanged), plus
    Gaussian sensor noise. Pixel (u, v) covers the square centred on (u, v)."""
    img = bg.astype(np.float32)
    r = int(np.ceil(radius)) + 2
    for k, (c, bgr) in enumerate(zip(centres, colours)):
        if visible is not None and not visible[k]:
            continue
        x0, y0 = int(np.floor(c[0])) - r, int(np.floor(c[1])) - r
        v, u = np.mgrid[y0:y0 + 2 * r + 2, x0:x0 + 2 * r + 2].astype(np.float32)
        dx, dy = u - c[0], v - c[1]
        alpha = np.clip(radius + 0.5 - np.hypot(dx, dy), 0, 1)[..., None]
        shade = (0.825 - 0.175 * (dx + dy) / (radius * np.sqrt(2)))[..., None]
        patch = img[y0:y0 + 2 * r + 2, x0:x0 + 2 * r + 2]
        patch[:] = (1 - alpha) * patch + alpha * shade * np.float32(bgr)
    img += rng.normal(0, noise, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def disc_path(n_frames: int, size: tuple[int, int] = SIZE) -> np.ndarray:
    """(n_frames, 4, 2) sub-pixel centres: one disc per image quadrant on a Lissajous
    path (never overlapping for radius <= 50 px), up to ~8 px per frame."""
    w, h = size
    t = np.arange(n_frames)[:, None] / 30.0
    phase = np.arange(4)[None, :] * 1.3
    cx = np.array([0.25, 0.75, 0.25, 0.75]) * w
    cy = np.array([0.25, 0.25, 0.75, 0.75]) * h
    x = cx + 0.14 * w * np.cos(2.0 * t + phase)
    y = cy + 0.14 * h * np.sin(2.6 * t + 2 * phase)
    return np.stack([x, y], axis=-1) + 0.37 * np.arange(4)[:, None]


def synthetic_frames(n_frames: int, radius: float = 10.0, seed: int = 0
                     ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(frame, true centres (4, 2)) along `disc_path`."""
    rng = np.random.default_rng(seed)
    bg = background()
    colours = [c[0] for c in COLOURS.values()]
    for centres in disc_path(n_frames):
        yield render_discs(bg, centres, colours, radius, rng), centres


def scene_detector(params: dict[str, object]) -> LandmarkDetector:
    """The detector camshift_node builds from the flat params of its params file."""
    names = {f'camshift.{f.name}' for f in fields(DetectorParams)}
    detector_params = DetectorParams.from_params({k: v for k, v in params.items() if k in names})
    return LandmarkDetector(models_from_params(params, detector_params.bins), detector_params)


def scene_frames(scene: GroundScene, camera: int, layout: np.ndarray, n_frames: int
                 ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Camera `camera`'s rendered frames along the figure-eight at RATE_HZ, the true
    projected landmark centres (n_frames, n, 2) and each landmark's visible fraction."""
    cam = scene.cameras[camera]
    frames, truth, visible = [], [], []
    for k in range(n_frames):
        pose = figure_eight(k / RATE_HZ)
        images, info = scene.render(pose)
        frames.append(images[camera])
        truth.append(cam.project(layout @ pose.R.T + pose.position))
        visible.append(info.visible[camera])
    return frames, np.array(truth), np.array(visible)


def megamind_frames(path: Path) -> list[np.ndarray]:
    """Frames 1-97 of Megamind.avi (its first shot), cropped to 640x480."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    x, y = MEGAMIND_CROP
    while len(frames) < 98:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(np.ascontiguousarray(frame[y:y + SIZE[1], x:x + SIZE[0]]))
    if len(frames) < 98:
        raise RuntimeError(f'{path}: expected at least 98 frames, read {len(frames)}')
    return frames[1:]


def megamind_models(first: np.ndarray, bins: tuple[int, int] = (30, 32)) -> list[ColourModel]:
    """Models from patches of the first frame (S >= 60, V >= 32 as the OpenCV sample)."""
    models = []
    for name, (x, y, w, h) in MEGAMIND_REGIONS.items():
        patch = first[y:y + h, x:x + w]
        mask = cv2.inRange(cv2.cvtColor(patch, cv2.COLOR_BGR2HSV), (0, 60, 32), (180, 255, 255))
        models.append(ColourModel.from_patch(name, patch, mask, value=(32, 255), bins=bins))
    return models


class OpenCvSample:
    """The OpenCV camshift.py way: full-frame HSV, full-frame backprojection of a fixed
    histogram and CamShift per landmark; centroid = CamShift's box centre. Given the
    detector's models (value gates) and its eq 18 ratio histograms of the first frame."""

    def __init__(self, models: Sequence[ColourModel], hists: np.ndarray,
                 windows: Sequence[Rect], max_iter: int = 10):
        self.gates = [m.value for m in models]
        self.hists = [np.ascontiguousarray(h) for h in hists]
        self.windows = list(windows)
        self.criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, max_iter, 1)

    def detect(self, bgr: np.ndarray) -> np.ndarray:
        hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
        out = np.full((len(self.hists), 2), np.nan)
        for i, hist in enumerate(self.hists):
            prob = cv2.calcBackProject([hsv], [0, 1], hist, HSV_RANGES, 255)
            lo, hi = self.gates[i]
            prob &= cv2.inRange(hsv, (0, 0, lo), (180, 255, hi))
            box, window = cv2.CamShift(prob, self.windows[i], self.criteria)
            if window[2] > 0 and window[3] > 0:
                self.windows[i] = window
                out[i] = box[0]
        return out


def megamind_pair(first: np.ndarray) -> tuple[LandmarkDetector, OpenCvSample]:
    """Our detector and the reference, both starting from MEGAMIND_REGIONS on `first`.

    The film's colours share hues with their surroundings, so eq 18 gives them lower
    probabilities than designed landmarks get: min_confidence is lowered to 0.05.
    """
    windows = list(MEGAMIND_REGIONS.values())
    ours = LandmarkDetector(megamind_models(first), DetectorParams(min_confidence=0.05))
    ours.detect(first)
    ref = OpenCvSample(ours.models, ours.ratio_hists, windows)
    ours.reset(windows)
    return ours, ref


def compare(frames: Sequence[np.ndarray], ours: LandmarkDetector, ref: OpenCvSample
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run ours, then the reference, over the frames (both already initialised).

    Returns per-frame ms of each (the first 5 frames, warm-up, left out), our
    centroids (n_frames, n, 2; NaN when not found) and the reference's.
    """
    xy, ref_xy = [], []
    it = iter(frames)
    ms = timeit(lambda: xy.append(centroids(ours.detect(next(it)))[0]), len(frames), 0)
    it = iter(frames)
    ref_ms = timeit(lambda: ref_xy.append(ref.detect(next(it))), len(frames), 0)
    return ms[5:], ref_ms[5:], np.array(xy), np.array(ref_xy)


def _agreement(xy: np.ndarray, ref_xy: np.ndarray) -> dict:
    d = np.linalg.norm(xy - ref_xy, axis=-1)
    return {'agree_px_median': round(float(np.nanmedian(d)), 3),
            'agree_px_max': round(float(np.nanmax(d)), 3),
            'found_rate': round(float(np.mean(np.isfinite(xy[..., 0]))), 4)}


def detection_cases() -> None:
    """Report ground/detection (simulator) and ground/detection_megamind (real video)."""
    params = read_params_file(default_config_path())
    cfg = load_ground_config(params)
    scene = GroundScene(cfg)
    runs = []
    for camera in range(len(cfg.cameras)):    # one camera's frames in memory at a time
        frames, truth, visible = scene_frames(scene, camera, cfg.layout, SCENE_FRAMES)
        ours = scene_detector(params)
        ours.detect(frames[0])
        ref = OpenCvSample(ours.models, ours.ratio_hists, ours.windows)
        ms, ref_ms, xy, ref_xy = compare(frames, ours, ref)
        err = np.where(visible >= 0.99, np.linalg.norm(xy - truth, axis=-1), np.nan)
        runs.append((ms, ref_ms, xy, ref_xy, err))
        del frames
    ms, ref_ms, xy, ref_xy, err = (np.concatenate(parts) for parts in zip(*runs))
    report('ground', 'ground/detection', ms, 'opencv_sample_fullframe', ref_ms,
           **_agreement(xy, ref_xy), truth_err_px_median=round(float(np.nanmedian(err)), 3),
           truth_err_px_max=round(float(np.nanmax(err)), 3))

    data = shared_data_dir()
    if data is None:
        print('ground/detection_megamind skipped: third-party data not found', flush=True)
        return
    frames = megamind_frames(data / 'opencv' / 'Megamind.avi')
    ours, ref = megamind_pair(frames[0])
    ms, ref_ms, xy, ref_xy = compare(frames, ours, ref)
    report('ground', 'ground/detection_megamind', ms, 'opencv_sample_fullframe', ref_ms,
           **_agreement(xy, ref_xy))


def main() -> None:
    detection_cases()


if __name__ == '__main__':
    main()
