"""Template alignment by the generalized Lucas-Kanade algorithm (chapter section 2.1).

A template T is aligned with an image I by the warp W(x; mu) that minimises the SSD
of eq 1 (with w(x) = 1). Two Gauss-Newton solvers are given:

- forward additive Lucas-Kanade (eq 2-5): the image gradient is warped onto the
  template, the steepest-descent images nabla(I) dW/dmu and the Hessian H (eq 5) are
  rebuilt every iteration, and mu <- mu + dmu (eq 4);
- inverse compositional image alignment, ICIA (Baker & Matthews, "Lucas-Kanade 20
  Years On: A Unifying Framework", IJCV 56(3), 2004): the roles of T and I are swapped
  in eq 2, so the steepest-descent images and H depend on the template alone and are
  computed once, and the update is composed with the inverse, W <- W(mu) o W(dmu)^-1.

Warps are translation (2 parameters), affine (6) and homography (8), parameterised as
in Baker & Matthews: W(x; 0) is the identity. A warp is given and returned as a 3x3
matrix M that maps template pixels (x right, y down, (0, 0) the top-left pixel) to
image pixels; a template cut from an image at (x0, y0) starts from
M = [[1, 0, x0], [0, 1, y0], [0, 0, 1]]. Internally the parameters live in coordinates
centred on the template and scaled by its half-size s, which keeps H well conditioned
and makes s * |dmu| a step in pixels. Solving coarse to fine over image pyramids
(section 2.1.2) extends the capture range.

Intensities are grey levels as given (0-255 for 8-bit images).
"""
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

_SCALE_DOWN = np.diag([0.5, 0.5, 1.0])   # pixel coordinates one pyramid level up
_MIN_LEVEL_SIDE = 16                      # coarsest template side allowed, px


class Warp(ABC):
    """A warp family W(x; mu): parameters <-> 3x3 matrix, and the steepest-descent
    images nabla(I) dW/dmu of eq 3-5."""

    name: str
    n_params: int

    @abstractmethod
    def matrix(self, mu: np.ndarray) -> np.ndarray:
        """The 3x3 matrix of W(.; mu)."""

    @abstractmethod
    def params(self, M: np.ndarray) -> np.ndarray:
        """mu of the member of the family closest to the 3x3 (or 2x3) matrix M."""

    @abstractmethod
    def steepest_descent(self, gx: np.ndarray, gy: np.ndarray, x: np.ndarray, y: np.ndarray,
                         mu: np.ndarray) -> np.ndarray:
        """nabla(I) dW/dmu (N, n_params) for gradients (gx, gy) at the points (x, y)."""


def _homogeneous(M: np.ndarray) -> np.ndarray:
    M = np.asarray(M, float)
    if M.shape == (2, 3):
        return np.vstack([M, [0.0, 0.0, 1.0]])
    return M / M[2, 2]


class Translation(Warp):
    """W(x; mu) = x + (mu1, mu2)."""

    name, n_params = 'translation', 2

    def matrix(self, mu: np.ndarray) -> np.ndarray:
        return np.array([[1.0, 0.0, mu[0]], [0.0, 1.0, mu[1]], [0.0, 0.0, 1.0]])

    def params(self, M: np.ndarray) -> np.ndarray:
        return _homogeneous(M)[:2, 2].copy()

    def steepest_descent(self, gx, gy, x, y, mu):
        return np.column_stack([gx, gy])


class Affine(Warp):
    """W(x; mu) = [[1 + mu1, mu3, mu5], [mu2, 1 + mu4, mu6]] (x, y, 1)^T."""

    name, n_params = 'affine', 6

    def matrix(self, mu: np.ndarray) -> np.ndarray:
        return np.array([[1.0 + mu[0], mu[2], mu[4]], [mu[1], 1.0 + mu[3], mu[5]],
                         [0.0, 0.0, 1.0]])

    def params(self, M: np.ndarray) -> np.ndarray:
        M = _homogeneous(M)
        return np.array([M[0, 0] - 1.0, M[1, 0], M[0, 1], M[1, 1] - 1.0, M[0, 2], M[1, 2]])

    def steepest_descent(self, gx, gy, x, y, mu):
        return np.column_stack([gx * x, gy * x, gx * y, gy * y, gx, gy])


class Homography(Warp):
    """The affine matrix with a third row (mu7, mu8, 1), W(x; mu) its projective map."""

    name, n_params = 'homography', 8

    def matrix(self, mu: np.ndarray) -> np.ndarray:
        return np.array([[1.0 + mu[0], mu[2], mu[4]], [mu[1], 1.0 + mu[3], mu[5]],
                         [mu[6], mu[7], 1.0]])

    def params(self, M: np.ndarray) -> np.ndarray:
        M = _homogeneous(M)
        return np.array([M[0, 0] - 1.0, M[1, 0], M[0, 1], M[1, 1] - 1.0, M[0, 2], M[1, 2],
                         M[2, 0], M[2, 1]])

    def steepest_descent(self, gx, gy, x, y, mu):
        w = mu[6] * x + mu[7] * y + 1.0
        gx, gy = gx / w, gy / w
        wx = ((1.0 + mu[0]) * x + mu[2] * y + mu[4]) / w
        wy = (mu[1] * x + (1.0 + mu[3]) * y + mu[5]) / w
        g = gx * wx + gy * wy
        return np.column_stack([gx * x, gy * x, gx * y, gy * y, gx, gy, -g * x, -g * y])


WARPS: dict[str, Warp] = {w.name: w for w in (Translation(), Affine(), Homography())}


@dataclass(frozen=True)
class AlignParams:
    """Solver settings."""

    max_iterations: int = 50    # Gauss-Newton iterations per pyramid level
    epsilon: float = 1e-3       # stop when s * |dmu| is below this, px of the level solved
    levels: int = 0             # pyramid levels above full resolution (section 2.1.2);
                                # fewer if the template would shrink below 16 px
    min_eig: float = 1e-2       # smallest eigenvalue of H / (pixels * s^2), (grey/px)^2
    min_overlap: float = 0.5    # fraction of the template that must land in the image


@dataclass
class AlignResult:
    """Outcome of one alignment. `M` maps template pixels to image pixels."""

    M: np.ndarray               # 3x3 warp matrix
    params: np.ndarray          # mu of M in template pixel coordinates
    iterations: int             # Gauss-Newton iterations, all levels
    rms: float                  # RMS of I(W(x)) - T(x) at M, grey levels
    converged: bool             # the update fell below epsilon at full resolution
    status: str                 # 'converged', 'max_iterations', 'singular' or 'lost'


def corner_error(M: np.ndarray, M_true: np.ndarray, shape: tuple[int, int]) -> float:
    """Largest image distance, px, between the template's corners mapped by M and M_true."""
    h, w = shape[:2]
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    a = cv2.perspectiveTransform(corners[None], _homogeneous(M))[0]
    b = cv2.perspectiveTransform(corners[None], _homogeneous(M_true))[0]
    return float(np.linalg.norm(a - b, axis=1).max())


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dI/dx, dI/dy in grey levels per pixel (Scharr)."""
    return (cv2.Scharr(img, cv2.CV_32F, 1, 0, scale=1 / 32),
            cv2.Scharr(img, cv2.CV_32F, 0, 1, scale=1 / 32))


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [np.asarray(img, np.float32)]
    for _ in range(levels):
        out.append(cv2.pyrDown(out[-1]))
    return out


def _usable_levels(shape: tuple[int, int], wanted: int) -> int:
    """Pyramid levels that keep the template at least _MIN_LEVEL_SIDE px on a side."""
    side, levels = min(shape[:2]), 0
    while levels < wanted and side // 2 >= _MIN_LEVEL_SIDE:
        side, levels = side // 2, levels + 1
    return levels


def _solve(H: np.ndarray, b: np.ndarray, n_pixels: int, s: float, min_eig: float
           ) -> np.ndarray | None:
    """H^-1 b (eq 4), or None when H is too close to singular to trust."""
    if np.linalg.eigvalsh(H)[0] < min_eig * n_pixels * s * s:
        return None
    return np.linalg.solve(H, b)


class _Level:
    """The template at one pyramid level: its inner pixels (the Scharr gradient needs a
    neighbour on each side) in pixel and in normalised coordinates."""

    def __init__(self, template: np.ndarray, warp: Warp, params: AlignParams) -> None:
        h, w = template.shape
        self.warp, self.min_overlap = warp, params.min_overlap
        self.t = template[1:-1, 1:-1].ravel()
        self.size = (w - 2, h - 2)
        cx, cy, self.s = (w - 1) / 2, (h - 1) / 2, max(w, h) / 2
        ys, xs = np.mgrid[1:h - 1, 1:w - 1]
        self.xy = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
        self.xn, self.yn = (self.xy[0] - cx) / self.s, (self.xy[1] - cy) / self.s
        self.norm = np.array([[1 / self.s, 0, -cx / self.s], [0, 1 / self.s, -cy / self.s],
                              [0, 0, 1]])
        self.unnorm = np.linalg.inv(self.norm)
        self.corners = np.array([[1, w - 2, w - 2, 1], [1, 1, h - 2, h - 2], [1, 1, 1, 1]], float)

    def to_norm(self, M: np.ndarray) -> np.ndarray:
        return self.norm @ M @ self.unnorm

    def to_pixels(self, W: np.ndarray) -> np.ndarray:
        return self.unnorm @ W @ self.norm

    def steepest_descent(self, gx: np.ndarray, gy: np.ndarray, mu: np.ndarray) -> np.ndarray:
        """nabla(I) dW/dmu per pixel, (N, n_params), by the chain rule through s."""
        return self.warp.steepest_descent(self.s * gx, self.s * gy, self.xn, self.yn, mu)

    def sample(self, img: np.ndarray, M: np.ndarray
               ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """img at W(x) for the inner pixels, (N, channels), and which of them land inside
        the image (None: all). (None, None) when too few do."""
        h, w = img.shape[:2]
        inside = None
        if not np.all(_inside(M @ self.corners, w, h)):
            inside = _inside(M @ self.xy, w, h)
            if inside.mean() < self.min_overlap:
                return None, None
        M1 = M @ [[1, 0, 1], [0, 1, 1], [0, 0, 1]]
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        if not _OPENCV_WARPS_EXACTLY:
            out = bilinear_warp(img, M1, self.size)
        elif M1[2, 0] == 0 and M1[2, 1] == 0:
            out = cv2.warpAffine(img, M1[:2], self.size, flags=flags,
                                 borderMode=cv2.BORDER_REPLICATE)
        else:
            out = cv2.warpPerspective(img, M1, self.size, flags=flags,
                                      borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(len(self.t), -1), inside


def bilinear_warp(img: np.ndarray, M: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """img at M (x, y, 1) for every pixel of a size = (w, h) output, bilinear in exact
    coordinates, border replicated: cv2.warpPerspective with WARP_INVERSE_MAP as OpenCV 5
    computes it, where OpenCV 4 rounds the coordinates to 1/32 px."""
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w]
    p = M @ np.stack([xs.ravel(), ys.ravel(), np.ones(w * h)])
    rows, cols = img.shape[:2]
    u = np.clip(p[0] / p[2], 0, cols - 1)
    v = np.clip(p[1] / p[2], 0, rows - 1)
    x0 = np.minimum(u.astype(int), max(cols - 2, 0))
    y0 = np.minimum(v.astype(int), max(rows - 2, 0))
    fx, fy = u - x0, v - y0
    x1, y1 = np.minimum(x0 + 1, cols - 1), np.minimum(y0 + 1, rows - 1)
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    out = top * (1 - fy) + bottom * fy
    return out.astype(img.dtype).reshape(h, w, *img.shape[2:])


def _warps_exactly() -> bool:
    """Whether cv2.warpAffine interpolates at the exact coordinate: a ramp shifted by
    1/64 px reads 1/64 more (OpenCV 5; OpenCV 4 rounds the shift to 0 or 1/32)."""
    ramp = np.tile(np.arange(8, dtype=np.float32), (8, 1))
    out = cv2.warpAffine(ramp, np.array([[1, 0, 2 + 1 / 64], [0, 1, 2]]), (2, 2),
                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return abs(float(out[0, 0]) - (2 + 1 / 64)) < 1e-4


_OPENCV_WARPS_EXACTLY = _warps_exactly()


def _inside(p: np.ndarray, w: int, h: int) -> np.ndarray:
    """Which homogeneous points p (3, N) land in a w x h image (where bilinear
    interpolation needs no border)."""
    u, v = p[0] / p[2], p[1] / p[2]
    return (p[2] > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)


def _levels(cls: type[_Level], template: np.ndarray, warp: Warp, params: AlignParams
            ) -> list[_Level]:
    """cls built on every pyramid level of the template, full resolution first."""
    template = np.asarray(template, np.float32)
    return [cls(t, warp, params)
            for t in _pyramid(template, _usable_levels(template.shape, params.levels))]


_LevelSolver = Callable[[_Level, np.ndarray, np.ndarray, AlignParams],
                        tuple[np.ndarray, int, str]]


def _coarse_to_fine(levels: list[_Level], images: list[np.ndarray], M0: np.ndarray,
                    solve_level: _LevelSolver, params: AlignParams) -> AlignResult:
    """Run solve_level from the coarsest level to full resolution (section 2.1.2)."""
    warp = levels[0].warp
    M = warp.matrix(warp.params(M0))
    total = 0
    for k in reversed(range(len(levels))):
        S = np.linalg.matrix_power(_SCALE_DOWN, k)
        Mk, iterations, status = solve_level(levels[k], images[k], S @ M @ np.linalg.inv(S),
                                             params)
        total += iterations
        if status in ('converged', 'max_iterations') or k == 0:
            M = np.linalg.inv(S) @ Mk @ S
    M = M / M[2, 2]
    sampled, inside = levels[0].sample(images[0], M)
    if sampled is None:
        rms = float('nan')
    else:
        r = sampled[:, 0] - levels[0].t
        rms = float(np.sqrt(np.mean(np.square(r if inside is None else r[inside]))))
    return AlignResult(M, warp.params(M), total, rms, status == 'converged', status)


def _forward_additive_level(level: _Level, stack: np.ndarray, M: np.ndarray,
                            params: AlignParams) -> tuple[np.ndarray, int, str]:
    """Forward additive L-K (eq 2-5) at one level; stack holds I, dI/dx, dI/dy."""
    warp = level.warp
    mu = warp.params(level.to_norm(M))
    for k in range(1, params.max_iterations + 1):
        Mk = level.to_pixels(warp.matrix(mu))
        sampled, inside = level.sample(stack, Mk)
        if sampled is None:
            return Mk, k, 'lost'
        sd = level.steepest_descent(sampled[:, 1], sampled[:, 2], mu)
        error = level.t - sampled[:, 0]
        if inside is not None:
            sd, error = sd[inside], error[inside]
        dmu = _solve(sd.T @ sd, sd.T @ error, len(error), level.s, params.min_eig)
        if dmu is None:
            return Mk, k, 'singular'
        mu = mu + dmu
        if level.s * np.linalg.norm(dmu) < params.epsilon:
            return level.to_pixels(warp.matrix(mu)), k, 'converged'
    return level.to_pixels(warp.matrix(mu)), params.max_iterations, 'max_iterations'


def align_lk(template: np.ndarray, image: np.ndarray, M0: np.ndarray, warp: str = 'affine',
             params: AlignParams = AlignParams()) -> AlignResult:
    """Align template with image by forward additive Lucas-Kanade (eq 1-5), from M0.

    Each iteration warps the image and its gradient with the current W(x; mu), forms
    the steepest-descent images nabla(I) dW/dmu and the Hessian H (eq 5), solves eq 4
    for dmu and adds it to mu.
    """
    levels = _levels(_Level, template, WARPS[warp], params)
    stacks = [np.dstack([img, *_gradients(img)])
              for img in _pyramid(image, len(levels) - 1)]
    return _coarse_to_fine(levels, stacks, M0, _forward_additive_level, params)


class _IcLevel(_Level):
    """A template level with the ICIA precomputation: the steepest-descent images
    nabla(T) dW/dmu at mu = 0 and the inverse of their Hessian (eq 5 on the template;
    None when it is singular)."""

    def __init__(self, template: np.ndarray, warp: Warp, params: AlignParams) -> None:
        super().__init__(template, warp, params)
        gx, gy = (g[1:-1, 1:-1].ravel() for g in _gradients(template))
        self.sd = self.steepest_descent(gx, gy, np.zeros(warp.n_params))
        self.H_inv = _solve(self.sd.T @ self.sd, np.eye(warp.n_params), len(self.t), self.s,
                            params.min_eig)


def _inverse_compositional_level(level: _IcLevel, image: np.ndarray, M: np.ndarray,
                                 params: AlignParams) -> tuple[np.ndarray, int, str]:
    """ICIA (Baker & Matthews 2004, fig. 4) at one level."""
    warp = level.warp
    if level.H_inv is None:
        return M, 0, 'singular'
    W = warp.matrix(warp.params(level.to_norm(M)))
    for k in range(1, params.max_iterations + 1):
        Mk = level.to_pixels(W)
        sampled, inside = level.sample(image, Mk)
        if sampled is None:
            return Mk, k, 'lost'
        error = sampled[:, 0] - level.t
        if inside is None:
            dmu = level.H_inv @ (level.sd.T @ error)
        else:
            sd = level.sd[inside]
            dmu = _solve(sd.T @ sd, sd.T @ error[inside], len(sd), level.s, params.min_eig)
            if dmu is None:
                return Mk, k, 'singular'
        W = W @ np.linalg.inv(warp.matrix(dmu))
        W /= W[2, 2]
        if level.s * np.linalg.norm(dmu) < params.epsilon:
            return level.to_pixels(W), k, 'converged'
    return level.to_pixels(W), params.max_iterations, 'max_iterations'


class InverseCompositional:
    """ICIA for one template: the steepest-descent images and Hessian are computed once
    here (per pyramid level), so each `align` costs an image warp and one pass of
    (nabla(T) dW/dmu)^T over the error image per iteration."""

    def __init__(self, template: np.ndarray, warp: str = 'affine',
                 params: AlignParams = AlignParams()) -> None:
        self.params = params
        self.levels = _levels(_IcLevel, template, WARPS[warp], params)

    def align(self, image: np.ndarray, M0: np.ndarray) -> AlignResult:
        """Align the template with image from M0: minimise
        sum [T(W(x; dmu)) - I(W(x; mu))]^2 over dmu, then W <- W(mu) o W(dmu)^-1."""
        return _coarse_to_fine(self.levels, _pyramid(image, len(self.levels) - 1), M0,
                               _inverse_compositional_level, self.params)


def align_ic(template: np.ndarray, image: np.ndarray, M0: np.ndarray, warp: str = 'affine',
             params: AlignParams = AlignParams()) -> AlignResult:
    """Align template with image by ICIA (Baker & Matthews 2004) from M0; for many
    images of one template build an `InverseCompositional` once instead."""
    return InverseCompositional(template, warp, params).align(image, M0)
