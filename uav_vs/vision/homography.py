"""Robust plane-to-plane homography (chapter section 2.3, Algorithm 1, eq 13-14).

`estimate_homography(src, dst)` returns a `HomographyResult` whose H maps src to dst
(x' ~ H x, H[2,2] = 1). Methods:

- 'ransac': Algorithm 1. Minimal samples of s = 4 matches are solved with the
  inhomogeneous 8-unknown system of eq 14 (Gaussian elimination), many samples per
  batch; every hypothesis is scored on all matches at once with the symmetric transfer
  error d^2 = d(x', Hx)^2 + d(x, H^-1 x')^2 and ranked by the MSAC cost (inliers
  counted, weighted by their error); every new best is refitted on its inliers before
  it is compared (LO-RANSAC); the trial count follows the adaptive
  N = log(1-p) / log(1-(1-eps)^s). The winner is refitted on all its inliers (normalised
  DLT, eq 13) with a threshold shrinking from 2t to t until the inlier set is stable,
  then refined by Levenberg-Marquardt on the symmetric transfer error.
- 'lmeds': least median of squares (Rousseeuw & Leroy 1987) over the same samples,
  inliers within 2.5 robust standard deviations, same refit.
- 'opencv_ransac', 'opencv_usac' (USAC_DEFAULT), 'opencv_magsac' (USAC_MAGSAC):
  `cv2.findHomography` for comparison.

Whatever the method, a result is only `ok` if it passes the same checks: enough
inliers (count and ratio), inliers not collinear, and an H that is not degenerate
(finite, orientation preserving, inlier region mapped to a convex quad of sensible
scale). A failed estimate carries H = None and the reason.
"""
import math
import sys
from dataclasses import dataclass

import cv2
import numpy as np

SAMPLE_SIZE = 4                  # s of Algorithm 1: 4 matches fix the 8 dof of H
_BATCH = 64                      # hypotheses generated and scored per numpy call
_COLLINEAR = 1e-3                # |cross| below this (normalised coords) = collinear triplet
_TRIPLETS = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
_OPENCV = {'opencv_ransac': cv2.RANSAC, 'opencv_usac': cv2.USAC_DEFAULT,
           'opencv_magsac': cv2.USAC_MAGSAC}
METHODS = ('ransac', 'lmeds', *_OPENCV)


@dataclass(frozen=True)
class HomographyResult:
    """Outcome of a robust fit; H is None unless ok."""

    ok: bool
    H: np.ndarray | None      # 3x3, H[2,2] = 1, maps src -> dst
    inliers: np.ndarray       # (N,) bool
    trials: int               # hypotheses drawn
    rms_px: float             # symmetric transfer RMS over the inliers
    reason: str               # '' when ok, else why it failed


def adaptive_trials(p: float, eps: float, s: int = SAMPLE_SIZE) -> int:
    """Samples needed so that one is outlier-free with probability p (Algorithm 1).

    N = log(1-p) / log(1-(1-eps)^s), eps the outlier fraction. eps = 0 needs one
    sample; eps = 1 can never succeed and returns sys.maxsize.
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f'confidence p must be in (0, 1), got {p}')
    if not 0.0 <= eps <= 1.0:
        raise ValueError(f'outlier fraction eps must be in [0, 1], got {eps}')
    good = (1.0 - eps) ** s
    if good >= 1.0:
        return 1
    if good <= 0.0:
        return sys.maxsize
    return max(1, math.ceil(math.log(1.0 - p) / math.log1p(-good)))


def _apply(H: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map (N,2) points by H (...,3,3); returns (...,N,2) points and (...,N) w."""
    q = pts @ H[..., :2, :2].swapaxes(-1, -2) + H[..., None, :2, 2]
    w = pts @ H[..., 2, :2, None] + H[..., 2, 2, None, None]
    w = w[..., 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        return q / w[..., None], w


def _transfer_sq(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Squared symmetric transfer error for one H (3,3) or a stack (B,3,3).

    Points mapped behind either camera (w <= 0) get an infinite error.
    """
    fwd, w1 = _apply(H, src)
    bwd, w2 = _apply(np.linalg.inv(H), dst)
    d2 = ((dst - fwd) ** 2).sum(-1) + ((src - bwd) ** 2).sum(-1)
    return np.where((w1 > 0) & (w2 > 0) & np.isfinite(d2), d2, np.inf)


def transfer_error(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Symmetric transfer error in px, sqrt(d(x', Hx)^2 + d(x, H^-1 x')^2) (Algorithm 1)."""
    src, dst = _check_points(src, dst, minimum=0)
    return np.sqrt(_transfer_sq(np.asarray(H, float), src, dst))


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Hartley similarity: centroid to the origin, mean distance sqrt(2)."""
    c = pts.mean(0)
    d = np.linalg.norm(pts - c, axis=1).mean()
    k = math.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[k, 0.0, -k * c[0]], [0.0, k, -k * c[1]], [0.0, 0.0, 1.0]])


def _to_pixels(Hn: np.ndarray, Ts: np.ndarray, Td: np.ndarray) -> np.ndarray:
    """Undo the normalisations (H = Td^-1 Hn Ts) and scale to H[2,2] = 1."""
    H = np.linalg.inv(Td) @ Hn @ Ts
    return H / H[..., 2:3, 2:3]


def _eq14_rows(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A' (..., 2n, 8) and b (..., 2n) of eq 14 (h33 = 1) for points (..., n, 2)."""
    x, y = src[..., 0], src[..., 1]
    u, v = dst[..., 0], dst[..., 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    rx = np.stack([x, y, one, zero, zero, zero, -x * u, -y * u], -1)
    ry = np.stack([zero, zero, zero, x, y, one, -x * v, -y * v], -1)
    rows = 2 * x.shape[-1]
    A = np.stack([rx, ry], -2).reshape(*x.shape[:-1], rows, 8)
    b = np.stack([u, v], -1).reshape(*x.shape[:-1], rows)
    return A, b


def solve_inhomogeneous(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """H from eq 14 with h33 = 1: Gaussian elimination for 4 matches, pseudo-inverse above.

    Points are Hartley-normalised first, so the 8x8 system is well conditioned.
    """
    src, dst = _check_points(src, dst)
    Ts, Td = _normaliser(src), _normaliser(dst)
    A, b = _eq14_rows(_apply(Ts, src)[0], _apply(Td, dst)[0])
    h = np.linalg.solve(A, b) if len(src) == SAMPLE_SIZE else np.linalg.pinv(A) @ b
    return _to_pixels(np.append(h, 1.0).reshape(3, 3), Ts, Td)


def solve_dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised homogeneous DLT: Ah = 0 of eq 13, h the last right singular vector."""
    src, dst = _check_points(src, dst)
    Ts, Td = _normaliser(src), _normaliser(dst)
    A, b = _eq14_rows(_apply(Ts, src)[0], _apply(Td, dst)[0])
    A = np.hstack([A, -b[:, None]])
    if len(A) < 9:                            # minimal case: keep the null space in Vt
        A = np.vstack([A, np.zeros((9 - len(A), 9))])
    h = np.linalg.svd(A, full_matrices=False)[2][-1]
    return _to_pixels(h.reshape(3, 3), Ts, Td)


def refine_lm(H: np.ndarray, src: np.ndarray, dst: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Levenberg-Marquardt on the symmetric transfer error of the given matches.

    The 8 parameters are those of eq 14 in Hartley-normalised coordinates; the
    Jacobian is taken by forward differences (one vectorised residual call per
    parameter).
    """
    Ts, Td = _normaliser(src), _normaliser(dst)
    Hn = Td @ H @ np.linalg.inv(Ts)
    h = (Hn / Hn[2, 2]).ravel()[:8]

    def residuals(h: np.ndarray) -> np.ndarray:
        Hp = _to_pixels(np.append(h, 1.0).reshape(3, 3), Ts, Td)
        fwd, _ = _apply(Hp, src)
        bwd, _ = _apply(np.linalg.inv(Hp), dst)
        return np.concatenate([(dst - fwd).ravel(), (src - bwd).ravel()])

    r = residuals(h)
    cost, lam, step = r @ r, 1e-3, 1e-7
    for _ in range(iterations):
        J = np.stack([(residuals(h + step * e) - r) / step for e in np.eye(8)], 1)
        JtJ, Jtr = J.T @ J, J.T @ r
        while lam < 1e10:
            dh = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ)), -Jtr)
            r_new = residuals(h + dh)
            new_cost = r_new @ r_new
            if np.isfinite(new_cost) and new_cost < cost:
                h, r, lam = h + dh, r_new, lam * 0.1
                break
            lam *= 10.0
        else:
            break
        if cost - new_cost < 1e-10 * cost:
            cost = new_cost
            break
        cost = new_cost
    return _to_pixels(np.append(h, 1.0).reshape(3, 3), Ts, Td)


def _check_points(src: np.ndarray, dst: np.ndarray, minimum: int = SAMPLE_SIZE
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Both as float (N,2) arrays, or a one-line ValueError saying what is wrong."""
    src, dst = (np.asarray(p, float) for p in (src, dst))
    src, dst = (p.reshape(0, 2) if p.size == 0 else p for p in (src, dst))
    if src.ndim != 2 or src.shape[1:] != (2,) or src.shape != dst.shape:
        raise ValueError(f'src and dst must be matching (N,2) arrays, '
                         f'got {src.shape} and {dst.shape}')
    if len(src) < minimum:
        raise ValueError(f'need at least {minimum} correspondences, got {len(src)}')
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise ValueError('src/dst contain NaN or inf')
    return src, dst


def _draw_samples(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """`count` samples of 4 distinct indices in [0, n) (rows with a repeat are redrawn)."""
    idx = rng.integers(0, n, size=(count, SAMPLE_SIZE))
    s = np.sort(idx, axis=1)
    dup = (s[:, 1:] == s[:, :-1]).any(1)
    while dup.any():
        idx[dup] = rng.integers(0, n, size=(int(dup.sum()), SAMPLE_SIZE))
        s = np.sort(idx[dup], axis=1)
        dup[dup] = (s[:, 1:] == s[:, :-1]).any(1)
    return idx


def _hypotheses(src_n: np.ndarray, dst_n: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Eq 14 minimal solutions (B,3,3) in normalised coordinates for the usable samples.

    A sample is dropped when any of its four triplets is collinear in either image, or
    when a triplet's orientation differs between the images (no homography of a plane
    seen from one side maps those four points so: Chum's oriented constraint).
    """
    s, d = src_n[samples], dst_n[samples]                    # (B,4,2)
    def cross(p: np.ndarray) -> np.ndarray:
        a, b, c = p[:, _TRIPLETS[:, 0]], p[:, _TRIPLETS[:, 1]], p[:, _TRIPLETS[:, 2]]
        e, f = b - a, c - a
        return e[..., 0] * f[..., 1] - e[..., 1] * f[..., 0]  # (B,4)
    cs, cd = cross(s), cross(d)
    good = ((np.abs(cs) > _COLLINEAR) & (np.abs(cd) > _COLLINEAR) & (cs * cd > 0)).all(1)
    if not good.any():
        return np.empty((0, 3, 3))
    A, b = _eq14_rows(s[good], d[good])
    solvable = np.abs(np.linalg.det(A)) > 1e-12
    A, b = A[solvable], b[solvable]
    h = np.linalg.solve(A, b[..., None])[..., 0]
    return np.concatenate([h, np.ones((len(h), 1))], 1).reshape(-1, 3, 3)


def _msac_cost(d2: np.ndarray, t2: float) -> np.ndarray:
    """Truncated quadratic cost (MSAC, Torr & Zisserman 2000) along the last axis."""
    return np.minimum(d2, t2).sum(-1)


def _local_fit(H: np.ndarray, t2: float, src: np.ndarray, dst: np.ndarray,
               iterations: int = 4) -> tuple[np.ndarray, float]:
    """Refit on all inliers a few times (Algorithm 1's refit, as in LO-RANSAC); best H and cost."""
    best, best_cost = H, _msac_cost(_transfer_sq(H, src, dst), t2)
    for _ in range(iterations):
        inl = _transfer_sq(best, src, dst) < t2
        if inl.sum() <= SAMPLE_SIZE:
            break
        H = solve_dlt(src[inl], dst[inl])
        cost = _msac_cost(_transfer_sq(H, src, dst), t2)
        if not cost < best_cost:
            break
        best, best_cost = H, cost
    return best, best_cost


def _ransac(src, dst, threshold, confidence, max_trials, rng, lmeds):
    """Algorithm 1 (or LMedS): (best H, inlier threshold^2) or None, and the trials drawn.

    Hypotheses come in batches and are scored on all matches in one array operation.
    RANSAC ranks them by the MSAC cost (inlier count with inliers weighted by their
    error) and refits every new best on its inliers before comparing it.
    """
    n = len(src)
    Ts, Td = _normaliser(src), _normaliser(dst)
    src_n, dst_n = _apply(Ts, src)[0], _apply(Td, dst)[0]
    t2 = threshold ** 2
    best_H, best_score = None, np.inf
    needed, trials = max_trials, 0
    while trials < min(needed, max_trials):
        batch = min(_BATCH, min(needed, max_trials) - trials)
        trials += batch
        Hn = _hypotheses(src_n, dst_n, _draw_samples(rng, n, batch))
        if not len(Hn):
            continue
        H = _to_pixels(Hn, Ts, Td)
        d2 = _transfer_sq(H, src, dst)                          # (B,N) all at once
        score = np.median(d2, axis=1) if lmeds else _msac_cost(d2, t2)
        k = int(np.argmin(score))
        if not score[k] < best_score:
            continue
        if lmeds:
            best_H, best_score = H[k], score[k]
            count = int((d2[k] <= score[k]).sum())
        else:
            best_H, best_score = _local_fit(H[k], t2, src, dst)
            count = int((_transfer_sq(best_H, src, dst) < t2).sum())
        needed = adaptive_trials(confidence, 1.0 - count / n)
    if best_H is None:
        return None, trials
    if lmeds:   # robust standard deviation, Rousseeuw & Leroy (1987) eq 5.1.20
        sigma = 1.4826 * (1.0 + 5.0 / max(n - SAMPLE_SIZE, 1)) * math.sqrt(best_score)
        t2 = min(t2, (2.5 * sigma) ** 2)
    return (best_H, t2), trials


def _refit(H: np.ndarray, t2: float, src: np.ndarray, dst: np.ndarray,
           refine: bool) -> tuple[np.ndarray, np.ndarray]:
    """Final estimate on all inliers (Algorithm 1's refit), then LM.

    The inlier threshold is lowered from 2t to t over a few least-squares refits
    (LO+, Lebeda et al. 2012), so the result does not depend on which minimal sample
    won; the refit is then repeated at t until the inlier set is stable.
    """
    for tk2 in np.linspace(4.0 * t2, t2, 6):
        inl = _transfer_sq(H, src, dst) < tk2
        if inl.sum() <= SAMPLE_SIZE:
            return H, _transfer_sq(H, src, dst) < t2
        H = solve_dlt(src[inl], dst[inl])
    inl = _transfer_sq(H, src, dst) < t2
    for _ in range(5):
        if inl.sum() <= SAMPLE_SIZE:
            return H, inl
        H = solve_dlt(src[inl], dst[inl])
        inl, previous = _transfer_sq(H, src, dst) < t2, inl
        if (inl == previous).all():
            break
    if refine and inl.sum() > SAMPLE_SIZE:
        H = refine_lm(H, src[inl], dst[inl])
        inl = _transfer_sq(H, src, dst) < t2
    return H, inl


def _degenerate(H: np.ndarray, src: np.ndarray, dst: np.ndarray, max_scale: float) -> str:
    """Why H (fitted on these inliers) is unusable, or '' if it is sound."""
    if not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12:
        return 'H is singular or not finite'
    for name, pts in (('src', src), ('dst', dst)):
        spread = np.linalg.svd(pts - pts.mean(0), compute_uv=False)[-1] / math.sqrt(len(pts))
        if spread < 1.0:
            return f'inliers are collinear in {name} (minor spread {spread:.2f} px)'
    lo, hi = src.min(0), src.max(0)
    box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    quad, w = _apply(H, box)
    if (w <= 0).any():
        return 'inlier region maps across the horizon'
    e = np.roll(quad, -1, 0) - quad
    turn = e[:, 0] * np.roll(e, -1, 0)[:, 1] - e[:, 1] * np.roll(e, -1, 0)[:, 0]
    if not (turn > 0).all():
        return 'inlier region maps to a flipped or non-convex quad'
    nxt = np.roll(quad, -1, 0)
    area = 0.5 * (quad[:, 0] * nxt[:, 1] - nxt[:, 0] * quad[:, 1]).sum()
    area /= max(float(np.prod(hi - lo)), 1e-9)
    if not max_scale ** -2 <= area <= max_scale ** 2:
        return f'extreme scale change (area ratio {area:.3g})'
    return ''


def estimate_homography(src: np.ndarray, dst: np.ndarray, method: str = 'ransac',
                        threshold_px: float = 3.0, confidence: float = 0.995,
                        max_trials: int = 2000, min_inliers: int = 8,
                        rng: np.random.Generator | int | None = None, *,
                        min_inlier_ratio: float = 0.2, max_scale: float = 10.0,
                        refine: bool = True) -> HomographyResult:
    """Robust H with x' ~ H x from matches src (N,2) -> dst (N,2) (section 2.3, Algorithm 1).

    threshold_px bounds the symmetric transfer error of an inlier (OpenCV methods: their
    one-sided reprojection error). The estimate fails (ok False, H None) with fewer than
    max(min_inliers, min_inlier_ratio * N) inliers or a degenerate H.
    """
    if method not in METHODS:
        raise ValueError(f'unknown homography method {method!r}; use one of {METHODS}')
    if threshold_px <= 0 or max_trials < 1 or min_inliers < SAMPLE_SIZE:
        raise ValueError('need threshold_px > 0, max_trials >= 1 and min_inliers >= 4')
    src, dst = _check_points(src, dst, minimum=0)
    n = len(src)
    none = np.zeros(n, bool)
    need = max(min_inliers, math.ceil(min_inlier_ratio * n))
    if n < need:
        return HomographyResult(False, None, none, 0, math.nan,
                                f'{n} matches, fewer than the {need} inliers required')
    if method in _OPENCV:
        H, mask = cv2.findHomography(src, dst, _OPENCV[method], threshold_px,
                                     maxIters=max_trials, confidence=confidence)
        trials = 0
        inl = mask.ravel().astype(bool) if H is not None else none
    else:
        rng = np.random.default_rng(rng)
        best, trials = _ransac(src, dst, threshold_px, confidence, max_trials, rng,
                               lmeds=method == 'lmeds')
        if best is None:
            return HomographyResult(False, None, none, trials, math.nan,
                                    'no usable sample: every one collinear or orientation-flipped')
        H, inl = _refit(*best, src, dst, refine)
    if H is None:
        return HomographyResult(False, None, none, trials, math.nan, 'OpenCV found no homography')
    H = H / H[2, 2]
    count = int(inl.sum())
    rms = math.sqrt(_transfer_sq(H, src[inl], dst[inl]).mean()) if count else math.nan
    if count < need:
        return HomographyResult(False, None, inl, trials, rms,
                                f'{count} inliers of {n}, fewer than the {need} required')
    reason = _degenerate(H, src[inl], dst[inl], max_scale)
    if reason:
        return HomographyResult(False, None, inl, trials, rms, reason)
    return HomographyResult(True, H, inl, trials, rms, '')
