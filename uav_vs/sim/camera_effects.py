"""What a real camera does to the image it captures: the simulated world's sensor effects.

The scenes (uav_vs.sim.ground_scene, onboard_scene; chapter sections 3 and 4) render
the exact image of the true geometry; these effects degrade it as a real sensor and
its link would, each seeded by the np.random.Generator it is given, each switched on
its own:

- `GaussianNoise`: additive sensor noise, a precomputed field shifted at random per frame;
- `jpeg_roundtrip`: the blocking and ringing of a JPEG link at a quality;
- `motion_blur`: the scene's image-plane motion during the exposure, a linear kernel;
- `LensDistortion`: what a lens of intrinsics K and distortion D (eq 15, OpenCV's model,
  as `Camera`) makes of an ideal pinhole image;
- `Exposure`: auto-exposure gain and offset drifting slowly, clipped to 0..255;
- `FrameDrops`: frames lost with a probability;
- `Latency`: the capture-to-publication delay, so the stamp is earlier than publication;
- `CameraLags`: ground cameras not triggered together, each capturing a little after
  the first;
- `Occlusion`: something passing between a ground camera and a landmark, covering part
  of it.

`CameraEffects` chains the image effects in the order light meets them: motion blur
(during the exposure), exposure gain, sensor noise, JPEG (the link).
"""
from dataclasses import dataclass

import cv2
import numpy as np

from uav_vs.sim.random_processes import OrnsteinUhlenbeck
from uav_vs.vision.camera import Camera

_NOISE_MARGIN = 64          # px of noise field beyond the image, for the per-frame shift


class GaussianNoise:
    """Zero-mean Gaussian noise of `sigma` grey levels, added to every channel.

    A field of (height + 64, width + 64, 3) normal samples, rounded to integers, is drawn
    once; each frame adds a window of it at a random offset (cheap, and no two
    consecutive frames share their noise).
    """

    def __init__(self, sigma: float, shape: tuple[int, int], rng: np.random.Generator) -> None:
        self.sigma = sigma
        self._rng = rng
        h, w = shape
        self._field = np.round(rng.normal(0.0, sigma, (h + _NOISE_MARGIN, w + _NOISE_MARGIN, 3))
                               ).astype(np.int16)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if self.sigma <= 0:
            return image
        h, w = image.shape[:2]
        dy, dx = self._rng.integers(0, _NOISE_MARGIN, 2)
        noise = self._field[dy:dy + h, dx:dx + w]
        return cv2.add(image, noise, dtype=cv2.CV_8U)


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """The image after JPEG encoding at `quality` (1..100) and decoding."""
    ok, buf = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError('jpeg: cannot encode the image')
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)


def motion_kernel(displacement: np.ndarray) -> np.ndarray:
    """Normalised linear blur kernel of a point that moves by `displacement` (dx, dy) px
    during the exposure: the segment, centred on the kernel, sampled at the midpoints of
    steps of at most 1/4 px and splatted bilinearly. Odd size, so it does not shift the
    image."""
    d = np.asarray(displacement, np.float64)
    length = float(np.hypot(*d))
    half = int(np.ceil(length / 2)) + 1
    size = 2 * half + 1
    kernel = np.zeros((size, size), np.float64)
    n = max(int(np.ceil(4 * length)), 1)
    for s in (np.arange(n) + 0.5) / n - 0.5:
        x, y = half + s * d[0], half + s * d[1]
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return (kernel / kernel.sum()).astype(np.float32)


def motion_blur(image: np.ndarray, velocity_px: np.ndarray, exposure: float) -> np.ndarray:
    """The image blurred along the scene's image-plane velocity (px/s) over an exposure
    of `exposure` s (one kernel for the whole frame); unchanged below 0.1 px of motion."""
    displacement = np.asarray(velocity_px, np.float64) * exposure
    if not np.all(np.isfinite(displacement)) or np.hypot(*displacement) < 0.1:
        return image
    kernel = motion_kernel(displacement)
    # Only the kernel's non-zero rows and columns, anchored at its centre: a near
    # horizontal or vertical motion costs a thin kernel.
    rows, cols = np.flatnonzero(kernel.any(axis=1)), np.flatnonzero(kernel.any(axis=0))
    half = kernel.shape[0] // 2
    crop = kernel[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    return cv2.filter2D(image, -1, crop, anchor=(half - int(cols[0]), half - int(rows[0])),
                        borderType=cv2.BORDER_REPLICATE)


class LensDistortion:
    """Turns ideal pinhole images of intrinsics K into the images of the lens K, D.

    Each output (distorted) pixel takes the ideal image at `Camera.undistort` of itself
    (the inverse of eq 15's distortion, OpenCV's model), by cv2.remap; pixels whose ideal
    point falls outside the ideal image are black.
    """

    def __init__(self, camera: Camera) -> None:
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        ideal = camera.undistort(np.column_stack([u.ravel(), v.ravel()]).astype(np.float64))
        self.map = ideal.reshape(camera.height, camera.width, 2).astype(np.float32)

    def __call__(self, ideal_image: np.ndarray) -> np.ndarray:
        return cv2.remap(ideal_image, self.map, None, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT)


class Exposure:
    """Auto-exposure that hunts: out = gain * in + offset, clipped to 0..255.

    Gain (around 1) and offset (grey levels, around 0) are independent Ornstein-Uhlenbeck
    processes of stationary standard deviations `gain_sigma`, `offset_sigma` and time
    constant `time_constant` s, stepped by each frame's interval: they drift slowly.
    """

    def __init__(self, gain_sigma: float, offset_sigma: float, time_constant: float,
                 rng: np.random.Generator) -> None:
        self.drift = OrnsteinUhlenbeck([gain_sigma, offset_sigma], time_constant, rng)

    @property
    def gain(self) -> float:
        return 1.0 + float(self.drift.state[0])

    @property
    def offset(self) -> float:
        return float(self.drift.state[1])

    def step(self, dt: float) -> None:
        """Advance the drift by dt s."""
        self.drift.step(dt)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        out = image.astype(np.float32) * self.gain + self.offset
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class FrameDrops:
    """Each frame is lost, independently, with probability `probability`."""

    def __init__(self, probability: float, rng: np.random.Generator) -> None:
        self.probability = probability
        self._rng = rng

    def dropped(self) -> bool:
        return bool(self._rng.random() < self.probability)


class Latency:
    """Capture-to-publication delay: `latency` s, plus or minus a uniform `jitter` s.

    `offset(capture)` is how long after `capture` (s) the frame is published. The
    publication times never go backwards (a frame is not published before the one
    captured before it), as on a real link.
    """

    def __init__(self, latency: float, jitter: float, rng: np.random.Generator) -> None:
        if not 0 <= jitter <= latency:
            raise ValueError(f'jitter {jitter:g} s must be in [0, latency {latency:g} s]')
        self.latency, self.jitter = latency, jitter
        self._rng = rng
        self._last = -np.inf

    def offset(self, capture: float) -> float:
        delay = self.latency + self.jitter * (2 * self._rng.random() - 1)
        delay = max(delay, self._last - capture)
        self._last = capture + delay
        return delay


class CameraLags:
    """Cameras that are not triggered together (section 3's rig assumes they are): the
    first captures at the frame's instant, each other camera `lag_k + e` s later, lag_k
    drawn once in [0, lag] (its trigger or clock offset), e in [0, jitter] per frame.
    Each frame is stamped with its own capture instant, as a camera driver stamps it.
    """

    def __init__(self, n_cameras: int, lag: float, jitter: float,
                 rng: np.random.Generator) -> None:
        self.lags = np.concatenate([[0.0], rng.uniform(0.0, lag, n_cameras - 1)])
        self.jitter = jitter
        self._rng = rng

    def sample(self) -> np.ndarray:
        """Each camera's capture instant after the frame's, s (the first's is 0)."""
        e = self.jitter * self._rng.random(len(self.lags))
        e[0] = 0.0
        return self.lags + e


def cap_offset(fraction: float) -> float:
    """Distance from a unit disc's centre of the chord that cuts off `fraction` of its
    area (the cap beyond it): the root of (acos d - d sqrt(1 - d^2)) / pi = fraction."""
    d = np.linspace(-1.0, 1.0, 2001)
    cap = (np.arccos(d) - d * np.sqrt(1.0 - d * d)) / np.pi     # decreasing in d
    return float(np.interp(fraction, cap[::-1], d[::-1]))


class Occlusion:
    """Something between a camera and the vehicle (a cable, a pole, a passing hand): each
    landmark, on its own with `probability` per frame, has a dark straight-edged object
    laid over `fraction` of its disc from a random side. The image the camera sees is
    the scene's with the occluder in front, so it is drawn before every other effect."""

    COLOUR = (38, 40, 42)        # BGR: a dark, unsaturated object

    def __init__(self, probability: float, fraction: float, rng: np.random.Generator) -> None:
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f'fraction {fraction:g} must be in [0, 1]')
        self.probability = probability
        self.offset = cap_offset(fraction)
        self._rng = rng

    def __call__(self, image: np.ndarray, discs: np.ndarray) -> tuple[np.ndarray, int]:
        """`image` with the occluders of this frame drawn over the landmarks' discs
        ((n, 3): centre u, v and radius in px, NaN where not in view), and how many."""
        out, count = image, 0
        for u, v, r in discs:
            if not (np.isfinite(r) and r > 0) or self._rng.random() >= self.probability:
                continue
            angle = self._rng.uniform(0.0, 2 * np.pi)
            n = np.array([np.cos(angle), np.sin(angle)])       # towards the object
            t = np.array([-n[1], n[0]])                         # along its edge
            c, far = np.array([u, v]), 2.0 * r + 2.0
            near = self.offset * r       # the object's edge: the chord cutting off the fraction
            corners = [c + n * near - t * far, c + n * near + t * far,
                       c + n * far + t * far, c + n * far - t * far]
            if out is image:
                out = image.copy()
            cv2.fillConvexPoly(out, np.round(np.array(corners) * 16).astype(np.int32),
                               self.COLOUR, cv2.LINE_AA, shift=4)
            count += 1
        return out, count


@dataclass(frozen=True)
class EffectsConfig:
    """Which image effects a camera has, and their settings (0 or False: off)."""

    noise_sigma: float = 0.0          # grey levels
    jpeg_quality: int = 0             # 1..100; 0: no JPEG artefacts
    exposure_time: float = 0.0        # s, for motion blur; 0: none
    gain_sigma: float = 0.0           # exposure drift: gain around 1
    offset_sigma: float = 0.0         # exposure drift: grey levels
    drift_time_constant: float = 5.0  # s
    drop_probability: float = 0.0


class CameraEffects:
    """One camera's image effects in capture order: blur, exposure, noise, JPEG; and drops."""

    def __init__(self, config: EffectsConfig, shape: tuple[int, int], seed: np.random.SeedSequence
                 ) -> None:
        noise_rng, exposure_rng, drop_rng = (np.random.default_rng(s) for s in seed.spawn(3))
        self.config = config
        self.noise = GaussianNoise(config.noise_sigma, shape, noise_rng) \
            if config.noise_sigma > 0 else None
        self.exposure = Exposure(config.gain_sigma, config.offset_sigma,
                                 config.drift_time_constant, exposure_rng) \
            if config.gain_sigma > 0 or config.offset_sigma > 0 else None
        self.drops = FrameDrops(config.drop_probability, drop_rng)

    def __call__(self, image: np.ndarray, velocity_px: np.ndarray, dt: float
                 ) -> np.ndarray | None:
        """The captured frame of an exact render, or None if it is dropped. `velocity_px`:
        the scene's image-plane velocity (px/s); dt: time since the previous frame, s."""
        c = self.config
        if self.exposure is not None:
            self.exposure.step(dt)
        if self.drops.dropped():
            return None
        if c.exposure_time > 0:
            image = motion_blur(image, velocity_px, c.exposure_time)
        if self.exposure is not None:
            image = self.exposure(image)
        if self.noise is not None:
            image = self.noise(image)
        if c.jpeg_quality > 0:
            image = jpeg_roundtrip(image, c.jpeg_quality)
        return image
