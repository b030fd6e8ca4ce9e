"""Colour-landmark detection by ratio-histogram backprojection and CamShift
(chapter section 3.1, eq 18-19).

Per frame, `LandmarkDetector.detect`:
1. samples every `downscale`-th pixel of the frame once, converts that to HSV and
   takes the image's H-S histogram I (in full-resolution pixels, optionally smoothed
   over frames);
2. recomputes every landmark's ratio histogram Rh_i = min(M_i / I, 1) (eq 18);
3. for each tracked landmark, converts and backprojects only its search region (the
   last window plus a margin), runs CamShift there (Bradski 1998), and takes the
   centroid from the moments of the backprojection inside the final window (eq 19);
4. for each lost landmark (every `reacquire_interval` frames), searches the whole
   shrunken frame for the densest patch of its colour and confirms it at full
   resolution as in step 3.

Only the search regions are converted to HSV: at 640x480 a full-frame cvtColor
costs about as much as four 60x60 regions converted and backprojected.

A landmark is found when its mass (sum of probabilities in the window, in pixels)
reaches `min_mass_px` and its confidence (mean probability over the window, 0..1)
reaches `min_confidence`. Landmarks are matched across cameras by identity: index i
is the i-th configured colour everywhere (section 3.1).
"""
from dataclasses import dataclass, fields
from typing import Mapping, Sequence

import cv2
import numpy as np

from uav_vs.vision.colour_model import HSV_RANGES, ColourModel, ratio_histograms

Rect = tuple[int, int, int, int]    # x, y, width, height in pixels

_LIMITS = {  # DetectorParams field: (low, high or None, integer)
    'hue_bins': (1, 180, True), 'saturation_bins': (1, 256, True),
    'histogram_smoothing': (0.0, 0.99, False),
    'downscale': (1, 16, True), 'search_margin': (0.0, 10.0, False),
    'min_search_margin_px': (0, None, True), 'min_mass_px': (0.0, None, False),
    'min_confidence': (0.0, 1.0, False), 'reacquire_interval': (1, None, True),
    'max_iterations': (1, 1000, True), 'epsilon_px': (0.0, None, False)}


@dataclass(frozen=True)
class DetectorParams:
    """Detector settings; ROS parameters `camshift.<field>` (config/ground_trinocular.yaml)."""

    hue_bins: int = 30                 # model / image histogram bins over H 0..179
    saturation_bins: int = 32          # ... and over S 0..255
    histogram_smoothing: float = 0.5   # I <- a I_prev + (1 - a) I_frame; 0 = this frame only
    downscale: int = 4                 # pixel step of the image histogram and the search
    search_margin: float = 0.25        # search region = window + this fraction of its size
    min_search_margin_px: int = 16     # ... and at least this many pixels on each side
    min_mass_px: float = 20.0          # found: backprojected mass in the window, pixels
    min_confidence: float = 0.2        # found: mean probability over the window, 0..1
    reacquire_interval: int = 1        # frames between whole-image searches of a lost landmark
    max_iterations: int = 10           # CamShift iterations per frame
    epsilon_px: float = 0.5            # CamShift stops when the window moves less than this

    def __post_init__(self) -> None:
        for f in fields(self):
            low, high, integer = _LIMITS[f.name]
            v = getattr(self, f.name)
            ok = (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                  and np.isfinite(v) and (not integer or float(v) == int(v))
                  and v >= low and (high is None or v <= high))
            if not ok:
                what = 'an integer' if integer else 'a number'
                raise ValueError(f'camshift.{f.name}: expected {what} in '
                                 f'[{low}, {"inf" if high is None else high}], got {v!r}')
            object.__setattr__(self, f.name, int(v) if integer else float(v))

    @classmethod
    def from_params(cls, params: Mapping[str, object], prefix: str = 'camshift.'
                    ) -> 'DetectorParams':
        """From flat ROS-style params; keys not given keep their defaults."""
        names = {f.name for f in fields(cls)}
        given = {k[len(prefix):]: v for k, v in params.items() if k.startswith(prefix)}
        for key in given:
            if key not in names:
                raise ValueError(f'{prefix}{key}: unknown parameter '
                                 f'(known: {", ".join(sorted(names))})')
        return cls(**given)

    @property
    def bins(self) -> tuple[int, int]:
        return self.hue_bins, self.saturation_bins


@dataclass(frozen=True)
class Detection:
    """One landmark in one frame; centroid in raw (distorted) pixels of the input image."""

    name: str
    found: bool
    centroid: tuple[float, float]      # (x, y), NaN when not found
    mass: float                        # sum of backprojected probability in the window, px
    confidence: float                  # mean probability over the window, 0..1
    window: Rect | None                # final CamShift window, None when lost


class LandmarkDetector:
    """Tracks n colour landmarks in one camera's images (section 3.1, eq 18-19)."""

    def __init__(self, models: Sequence[ColourModel], params: DetectorParams = DetectorParams()):
        if not models:
            raise ValueError('landmarks.names: at least one landmark is needed')
        for m in models:
            if m.hist.shape != params.bins:
                raise ValueError(f'landmarks.{m.name}: model histogram has {m.hist.shape} bins, '
                                 f'camshift.hue_bins/saturation_bins give {params.bins}')
        self.models = list(models)
        self.params = params
        self._model_hists = np.stack([m.hist for m in models])
        self.ratio_hists = np.empty_like(self._model_hists)   # eq 18 of the last frame
        self._criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
                          params.max_iterations, params.epsilon_px)
        self._lo_v = min(m.value[0] for m in models)
        self._hi_v = max(m.value[1] for m in models)
        self.reset()

    def reset(self, windows: Sequence[Rect | None] | None = None) -> None:
        """Forget the image histogram and every window, or start from the given
        windows (x, y, w, h per landmark, None = search for it)."""
        n = len(self.models)
        if windows is not None and len(windows) != n:
            raise ValueError(f'windows: expected {n} (one per landmark), got {len(windows)}')
        windows = windows if windows is not None else [None] * n
        self.windows: list[Rect | None] = [None if w is None else tuple(int(v) for v in w)
                                           for w in windows]
        self.search_regions: list[Rect | None] = [None] * n   # full-res regions of the last frame
        self._since_search = [self.params.reacquire_interval] * n
        self._image_hist: np.ndarray | None = None
        self._shape: tuple[int, int] | None = None

    def detect(self, bgr: np.ndarray) -> list[Detection]:
        """Detect every landmark in a BGR8 frame; one Detection per model, in model order."""
        if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
            raise ValueError(f'image: expected HxWx3 uint8 BGR, got {bgr.shape} {bgr.dtype}')
        if self._shape is not None and self._shape != bgr.shape[:2]:
            self.reset()
        self._shape = bgr.shape[:2]
        small_hsv = self._image_histogram(bgr)
        ratios = ratio_histograms(self._model_hists, self._image_hist, out=self.ratio_hists)
        out = []
        for i, model in enumerate(self.models):
            det = None
            self.search_regions[i] = None
            if self.windows[i] is not None:
                det = self._track(bgr, i, ratios[i], self.windows[i])
            if (det is None or not det.found) and self._due_search(i):
                seed = self._search(small_hsv, i, ratios[i])
                if seed is not None:
                    det = self._track(bgr, i, ratios[i], seed)
            if det is None or not det.found:
                det = Detection(model.name, False, (np.nan, np.nan),
                                det.mass if det else 0.0, det.confidence if det else 0.0, None)
            self.windows[i] = det.window
            out.append(det)
        return out

    def draw(self, bgr: np.ndarray, detections: Sequence[Detection]) -> np.ndarray:
        """Debug image: search regions (grey), windows and centroids with name and confidence."""
        img = bgr.copy()
        for region in self.search_regions:
            if region is not None:
                x, y, w, h = region
                cv2.rectangle(img, (x, y), (x + w - 1, y + h - 1), (128, 128, 128), 1)
        for d in detections:
            if not d.found:
                continue
            x, y, w, h = d.window
            cv2.rectangle(img, (x, y), (x + w - 1, y + h - 1), (0, 255, 255), 2)
            c = (int(round(d.centroid[0])), int(round(d.centroid[1])))
            cv2.drawMarker(img, c, (0, 0, 255), cv2.MARKER_CROSS, 10, 1)
            cv2.putText(img, f'{d.name} {d.confidence:.2f}', (x, max(y - 4, 10)),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 255), 1, cv2.LINE_AA)
        return img

    # -- per-frame steps -----------------------------------------------------------

    def _image_histogram(self, bgr: np.ndarray) -> np.ndarray:
        """I of eq 18 from the sampled frame, in full-resolution pixels; returns its HSV."""
        s = self.params.downscale
        h, w = bgr.shape[:2]
        small = cv2.resize(bgr, (w // s, h // s), interpolation=cv2.INTER_NEAREST) if s > 1 else bgr
        hsv = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
        mask = (cv2.inRange(hsv, (0, 0, self._lo_v), (180, 255, self._hi_v))
                if (self._lo_v, self._hi_v) != (0, 255) else None)
        hist = cv2.calcHist([hsv], [0, 1], mask, list(self.params.bins), HSV_RANGES)
        hist *= (h * w) / (small.shape[0] * small.shape[1])
        a = self.params.histogram_smoothing
        if self._image_hist is None or a == 0:
            self._image_hist = hist
        else:
            self._image_hist = a * self._image_hist + (1 - a) * hist
        return hsv

    def _backproject(self, hsv: np.ndarray, i: int, ratio: np.ndarray) -> np.ndarray:
        """Probability image (uint8, 255 = 1) of landmark i over an HSV region."""
        prob = cv2.calcBackProject([hsv], [0, 1], ratio, HSV_RANGES, 255)
        lo, hi = self.models[i].value
        if self.models[i].gated:
            cv2.bitwise_and(prob, cv2.inRange(hsv, (0, 0, lo), (180, 255, hi)), dst=prob)
        return prob

    def _track(self, bgr: np.ndarray, i: int, ratio: np.ndarray, window: Rect) -> Detection:
        """CamShift in the window's search region, centroid by eq 19 inside the final window."""
        p = self.params
        H, W = bgr.shape[:2]
        x, y, w, h = window
        m = max(int(p.search_margin * max(w, h)), p.min_search_margin_px)
        x0, y0 = max(x - m, 0), max(y - m, 0)
        x1, y1 = min(x + w + m, W), min(y + h + m, H)
        self.search_regions[i] = (x0, y0, x1 - x0, y1 - y0)
        hsv = cv2.cvtColor(bgr[y0:y1, x0:x1], cv2.COLOR_BGR2HSV)
        prob = self._backproject(hsv, i, ratio)
        local = _clip((x - x0, y - y0, w, h), x1 - x0, y1 - y0)
        box, _ = cv2.CamShift(prob, local, self._criteria)
        name = self.models[i].name
        if box[1][0] <= 0 or box[1][1] <= 0:
            return Detection(name, False, (np.nan, np.nan), 0.0, 0.0, None)
        wx, wy, ww, wh = _box_window(box, x1 - x0, y1 - y0)
        mo = cv2.moments(prob[wy:wy + wh, wx:wx + ww])
        mass = mo['m00'] / 255.0
        confidence = mass / (ww * wh)
        found = mo['m00'] > 0 and mass >= p.min_mass_px and confidence >= p.min_confidence
        centroid = ((x0 + wx + mo['m10'] / mo['m00'], y0 + wy + mo['m01'] / mo['m00'])
                    if found else (np.nan, np.nan))
        return Detection(name, found, centroid, mass, confidence, (x0 + wx, y0 + wy, ww, wh))

    def _due_search(self, i: int) -> bool:
        self._since_search[i] += 1
        if self._since_search[i] < self.params.reacquire_interval:
            return False
        self._since_search[i] = 0
        return True

    def _search(self, small_hsv: np.ndarray, i: int, ratio: np.ndarray) -> Rect | None:
        """Whole-image search on the sampled frame: CamShift from the densest 3x3 patch;
        returns the window in full-resolution pixels, or None if the colour is absent."""
        prob = self._backproject(small_hsv, i, ratio)
        density = cv2.boxFilter(prob, cv2.CV_32F, (3, 3))
        _, peak, _, (px, py) = cv2.minMaxLoc(density)
        if peak <= 0:
            return None
        sh, sw = prob.shape
        seed = _clip((px - 1, py - 1, 3, 3), sw, sh)
        _, (x, y, w, h) = cv2.CamShift(prob, seed, self._criteria)
        if w <= 0 or h <= 0:
            return None
        s = self.params.downscale
        return x * s, y * s, w * s, h * s


def centroids(detections: Sequence[Detection]) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) centroids (NaN rows when not found) and (n,) confidences, in model order."""
    xy = np.array([d.centroid if d.found else (np.nan, np.nan) for d in detections], float)
    conf = np.array([d.confidence for d in detections], float)
    return xy.reshape(-1, 2), conf


def _box_window(box: tuple, width: int, height: int) -> Rect:
    """Final window: the pixels touched by the ellipse inscribed in CamShift's rotated
    box (axes 4 sigma of the blob's second moments), with half a pixel for an
    anti-aliased rim, clipped to the image.

    cv2.CamShift's own window is sized from the box's larger projected side only and
    cuts a round blob by up to 1 - 1/sqrt(2) when its (arbitrary) angle is near 45
    degrees, which would bias eq 19.
    """
    (cx, cy), (w, h), angle = box
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    ex = 0.5 * np.hypot(w * c, h * s) + 0.5
    ey = 0.5 * np.hypot(w * s, h * c) + 0.5
    x0, y0 = int(np.floor(cx - ex)), int(np.floor(cy - ey))
    x1, y1 = int(np.ceil(cx + ex)), int(np.ceil(cy + ey))
    return _clip((x0, y0, x1 - x0 + 1, y1 - y0 + 1), width, height)


def _clip(rect: Rect, width: int, height: int) -> Rect:
    """Clip a rectangle to the image, keeping at least 1x1 pixel."""
    x, y, w, h = rect
    x = min(max(x, 0), width - 1)
    y = min(max(y, 0), height - 1)
    return x, y, max(min(w, width - x), 1), max(min(h, height - y), 1)
