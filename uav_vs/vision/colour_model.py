"""Colour models of the landmarks and the ratio histogram (chapter section 3.1, eq 18).

A landmark's model histogram M_i is a hue-saturation histogram in OpenCV's HSV
(H 0..179, S 0..255), counted in pixels: from a sample patch, the patch's own counts;
from configured colour ranges, every bin inside the ranges holds the landmark's
expected area `area_px`. The value channel is not histogrammed: each model carries
a value range that gates which pixels may belong to it (dark pixels have no reliable
hue).

The ratio histogram Rh_i(j) = min(M_i(j) / I(j), 1) (eq 18, Swain & Ballard 1991)
compares the model with the histogram I of the current image, also in pixels, so
Rh_i(j) reads as the share of the image's pixels of colour j that can belong to the
landmark: 1 for colours the rest of the image lacks, small for common ones.
"""
from dataclasses import dataclass
from typing import Mapping, Sequence

import cv2
import numpy as np

HSV_RANGES = [0, 180, 0, 256]   # OpenCV 8-bit HSV: hue 0..179, saturation 0..255


@dataclass(frozen=True)
class ColourModel:
    """One landmark's colour: H-S model histogram in pixels and the value gate."""

    name: str
    hist: np.ndarray                 # (hue_bins, saturation_bins) float32, pixels
    value: tuple[int, int] = (0, 255)

    @property
    def gated(self) -> bool:
        """True if the value range excludes some pixels."""
        return self.value != (0, 255)

    @classmethod
    def from_ranges(cls, name: str, hue: Sequence[int], saturation: Sequence[int],
                    value: Sequence[int] = (0, 255), bins: tuple[int, int] = (30, 32),
                    area_px: float = 400.0) -> 'ColourModel':
        """Model from inclusive ranges; hue lo > hi wraps through 0 (reds).

        A bin holds `area_px` (the landmark's expected area in the image) times the
        share of its integer H and S values inside the ranges.
        """
        if not (np.isfinite(area_px) and area_px > 0):
            raise ValueError(f'landmarks.{name}.area_px: expected a positive number, '
                             f'got {area_px!r}')
        h_lo, h_hi = _range(f'landmarks.{name}.hue', hue, 179)
        s_lo, s_hi = _range(f'landmarks.{name}.saturation', saturation, 255)
        v_lo, v_hi = _range(f'landmarks.{name}.value', value, 255)
        if s_lo > s_hi:
            raise ValueError(f'landmarks.{name}.saturation: lo > hi in {list(saturation)}')
        if v_lo > v_hi:
            raise ValueError(f'landmarks.{name}.value: lo > hi in {list(value)}')
        h = np.arange(180)
        in_h = (h >= h_lo) & (h <= h_hi) if h_lo <= h_hi else (h >= h_lo) | (h <= h_hi)
        s = np.arange(256)
        in_s = (s >= s_lo) & (s <= s_hi)
        hist = np.outer(_bin_share(in_h, bins[0]), _bin_share(in_s, bins[1]))
        hist = _checked(hist, name)
        return cls(name, hist * np.float32(area_px / hist.max()), (v_lo, v_hi))

    @classmethod
    def from_patch(cls, name: str, bgr: np.ndarray, mask: np.ndarray | None = None,
                   value: Sequence[int] = (0, 255), bins: tuple[int, int] = (30, 32)
                   ) -> 'ColourModel':
        """Model from a sample image patch showing the whole landmark at its usual size in
        the camera's images; counts of the gated pixels. The patch is 8-bit BGR, or BGRA
        whose alpha 0 marks pixels that are not the landmark; `mask` (non-zero =
        landmark) narrows it further."""
        v_lo, v_hi = _range(f'landmarks.{name}.value', value, 255)
        if bgr.dtype != np.uint8 or bgr.ndim != 3 or bgr.shape[2] not in (3, 4):
            raise ValueError(f'landmarks.{name}.sample: expected an 8-bit colour image, got '
                             f'{bgr.dtype} {bgr.shape}')
        if bgr.shape[2] == 4:
            alpha = bgr[..., 3]
            mask = alpha if mask is None else np.where(mask > 0, alpha, 0)
            bgr = np.ascontiguousarray(bgr[..., :3])
        hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
        gate = cv2.inRange(hsv, (0, 0, v_lo), (180, 255, v_hi))
        if mask is not None:
            gate &= (mask > 0).astype(np.uint8) * 255
        hist = cv2.calcHist([hsv], [0, 1], gate, list(bins), HSV_RANGES)
        return cls(name, _checked(hist, name), (v_lo, v_hi))


def models_from_params(params: Mapping[str, object], bins: tuple[int, int] = (30, 32),
                       samples: Mapping[str, np.ndarray] | None = None) -> list[ColourModel]:
    """Models from flat ROS-style params: `landmarks.names` and `landmarks.<name>.hue`,
    `.saturation`, optional `.value` (default [0, 255]) and `.area_px` (default 400).
    A landmark in `samples` (name -> its sample patch, see `ColourModel.from_patch`) is
    modelled from the patch and its `.value` range instead of hue and saturation.
    The order of `landmarks.names` is the landmark index everywhere."""
    names = params.get('landmarks.names')
    if (not isinstance(names, Sequence) or isinstance(names, str) or not names
            or not all(isinstance(n, str) and n for n in names)):
        raise ValueError(f'landmarks.names: expected a non-empty list of names, got {names!r}')
    if len(set(names)) != len(names):
        raise ValueError(f'landmarks.names: duplicate names in {list(names)}')
    models = []
    for name in names:
        if samples and name in samples:
            value = params.get(f'landmarks.{name}.value', (0, 255))
            models.append(ColourModel.from_patch(name, samples[name], value=value, bins=bins))
            continue
        ranges = {}
        for key in ('hue', 'saturation', 'value'):
            full = f'landmarks.{name}.{key}'
            if full not in params and key != 'value':
                raise ValueError(f'{full}: missing, expected [lo, hi]')
            ranges[key] = params.get(full, (0, 255))
        area = params.get(f'landmarks.{name}.area_px', 400.0)
        if isinstance(area, bool) or not isinstance(area, (int, float)):
            raise ValueError(f'landmarks.{name}.area_px: expected a positive number, got {area!r}')
        models.append(ColourModel.from_ranges(name, bins=bins, area_px=float(area), **ranges))
    return models


def ratio_histograms(models: np.ndarray, image: np.ndarray,
                     out: np.ndarray | None = None) -> np.ndarray:
    """Eq 18 for every landmark at once: Rh_i(j) = min(M_i(j) / I(j), 1).

    models: (n, H, S) model histograms, image: (H, S) image histogram, both in pixels.
    Written as M / max(M, I), which equals min(M / I, 1) and is 0 where M is 0.
    """
    den = np.maximum(models, image)
    np.maximum(den, np.float32(1e-12), out=den)
    return np.divide(models, den, out=out)


def _range(name: str, pair: object, top: int) -> tuple[int, int]:
    try:
        lo, hi = (int(v) for v in pair)                # type: ignore[union-attr]
        ok = all(float(v) == int(v) for v in pair)      # type: ignore[union-attr]
    except (TypeError, ValueError):
        ok = False
    if not ok or not (0 <= lo <= top and 0 <= hi <= top):
        raise ValueError(f'{name}: expected [lo, hi] integers in [0, {top}], got {pair!r}')
    return lo, hi


def _bin_share(inside: np.ndarray, bins: int) -> np.ndarray:
    """Share of each bin's integer values that are inside (histogram of a boolean axis)."""
    idx = np.arange(inside.size) * bins // inside.size
    return np.bincount(idx, inside.astype(float), bins) / np.bincount(idx, minlength=bins)


def _checked(hist: np.ndarray, name: str) -> np.ndarray:
    if not hist.max() > 0:
        raise ValueError(f'landmarks.{name}: the colour model is empty (no pixel in range)')
    return np.ascontiguousarray(hist, dtype=np.float32)
