"""Robust plane-to-plane homography (chapter section 2.3, Algorithm 1, eq 13-14).

`estimate_homography(src, dst)` returns a `HomographyResult` whose H maps src to dst
(x' ~ H x, H[2,2] = 1). Methods:

- 'ransac': Algorithm 1. Minimal samples of s = 4 matches are solved with the
  inhomogeneous 8-unknown system of eq 14, a batch of samples per numpy call, and every
  hypothesis of a batch is scored on all matches at once with the symmetric transfer
  error d^2 = d(x', Hx)^2 + d(x, H^-1 x')^2, ranked by the MSAC cost (inliers counted,
  weighted by their error). A new best is refitted on all its inliers (eq 13,
  normalised DLT) as Algorithm 1 does, and the trial count follows the adaptive
  N = log(1-p) / log(1-(1-eps)^s). Batches start at 8 samples and double up to 64
  (more when there are few matches), so data that needs few trials stops early.
- 'lmeds': least median of squares (Rousseeuw & Leroy 1987) over the same samples;
  inliers are within 2.5 robust standard deviations (at most threshold_px), and the
  winner is refitted on them.
- 'opencv_ransac', 'opencv_usac' (USAC_DEFAULT), 'opencv_magsac' (USAC_MAGSAC):
  `cv2.findHomography` for comparison.

The default is 'ransac': on the Oxford graf/boat matches (bench/onboard_homography.py)
it is the only estimator no worse than cv2 RANSAC on any pair and gives the same H
whatever the seed or match order, worth its ~8 ms a call (MAGSAC 1.2 ms, USAC 2.5 ms,
cv2 RANSAC 7 ms): USAC and MAGSAC are worse on graf 1->2 (1.05, 1.09 vs 0.90 px), cv2
RANSAC's error varies with the match order (graf 1->3 up to 6.3 px) and LMedS fails
graf 1->4 (65 % outliers) for half of the orders; all report graf 1->5, 1->6 as failures.

'ransac' and 'lmeds' end with `refine_robust`, the non-linear (geometric) solution of
eq 13: a Cauchy M-estimate of H from the symmetric transfer errors of all matches,
found by Levenberg-Marquardt. Unlike a least-squares refit on a hard inlier set, its
optimum does not hinge on which matches fall just inside or outside the threshold, nor
on which sample won.

Whatever the method, a result is only `ok` if it passes the same checks: enough
inliers (count and ratio; an inlier has d < threshold), inliers not collinear, and an
H that is not degenerate (finite, orientation preserving, inlier region mapped to a
convex quad of sensible scale). A failed estimate carries H = None and the reason.
"""
import math
import sys
from dataclasses import dataclass

import cv2
import numpy as np

SAMPLE_SIZE = 4                  # s of Algorithm 1: 4 matches fix the 8 dof of H
_BATCH = 64                      # most hypotheses per numpy call, or _BATCH_ERRORS / N
_BATCH_ERRORS = 1 << 14          # hypothesis-match errors per call that make a batch worth it
_FIRST_BATCH = 8                 # the first batch; each next one doubles up to the most
_COLLINEAR = 1e-3                # |cross| below this (normalised coords) = collinear triplet
_TRIPLETS = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
_CHI2_4_95 = 9.4877              # 95 % quantile of chi-square with 4 dof
_CAUCHY_95 = 2.3849              # Cauchy scale for 95 % efficiency at Gaussian noise, in sigma
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


def _one_way_sq(H: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """d(b, H a)^2 for H (...,3,3) and points (N,2): (...,N), inf where w <= 0."""
    x, y = a[:, 0], a[:, 1]
    h = H[..., None]
    w = h[..., 2, 0, :] * x + h[..., 2, 1, :] * y + h[..., 2, 2, :]
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        du = (h[..., 0, 0, :] * x + h[..., 0, 1, :] * y + h[..., 0, 2, :]) / w - b[:, 0]
        dv = (h[..., 1, 0, :] * x + h[..., 1, 1, :] * y + h[..., 1, 2, :]) / w - b[:, 1]
        d2 = du * du + dv * dv
    return np.where((w > 0) & np.isfinite(d2), d2, np.inf)


def _transfer_sq(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Squared symmetric transfer error for one H (3,3) or a stack (B,3,3), H[2,2] > 0.

    Points mapped behind either camera (w <= 0) get an infinite error.
    """
    return _one_way_sq(H, src, dst) + _one_way_sq(np.linalg.inv(H), dst, src)


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


def _eq13_rows(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """A (..., 2n, 9) of eq 13 for points (..., n, 2); eq 14 is A[..., :8] h' = -A[..., 8]."""
    A = np.zeros((*src.shape[:-1], 2, 9))
    A[..., 0, 0:2] = A[..., 1, 3:5] = src
    A[..., 0, 2] = A[..., 1, 5] = 1.0
    A[..., 0, 6:8] = -src * dst[..., 0:1]
    A[..., 1, 6:8] = -src * dst[..., 1:2]
    A[..., :, 8] = -dst
    return A.reshape(*src.shape[:-2], -1, 9)


def solve_inhomogeneous(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """H from eq 14 with h33 = 1: Gaussian elimination for 4 matches, pseudo-inverse above.

    Points are Hartley-normalised first, so the 8x8 system is well conditioned.
    """
    src, dst = _check_points(src, dst)
    Ts, Td = _normaliser(src), _normaliser(dst)
    A = _eq13_rows(_apply(Ts, src)[0], _apply(Td, dst)[0])
    A, b = A[:, :8], -A[:, 8]
    h = np.linalg.solve(A, b) if len(src) == SAMPLE_SIZE else np.linalg.pinv(A) @ b
    return _to_pixels(np.append(h, 1.0).reshape(3, 3), Ts, Td)


def solve_dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised homogeneous DLT: Ah = 0 of eq 13, h the unit vector minimising |Ah|.

    h is the eigenvector of the 9x9 A^T A with the smallest eigenvalue (the last right
    singular vector of A), A built from Hartley-normalised points.
    """
    src, dst = _check_points(src, dst)
    Ts, Td = _normaliser(src), _normaliser(dst)
    A = _eq13_rows(_apply(Ts, src)[0], _apply(Td, dst)[0])
    h = np.linalg.eigh(A.T @ A)[1][:, 0]
    return _to_pixels(h.reshape(3, 3), Ts, Td)


def _linearise(Hn: np.ndarray, src: np.ndarray, dst: np.ndarray, ks: float, kd: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (N,4) in px, their Jacobian (N,4,8) in h, and zoom weights (N,).

    Hn (Hn[2,2] = 1, entries h) maps normalised points src -> dst; ks, kd are the scales
    of the normalisations. The residuals are (x' - pi(Hn x)) / kd and
    (x - pi(G x')) / ks, pi the perspective division and G = Hn^-1; with w = (Hn x)_3,
    d pi(Hn x) / dh_ij = [I | -pi(Hn x)][:, i] x_j / w, and as dG = -G dHn G,
    d pi(G x') / dh_ij = -([I | -pi(G x')] G)[:, i] p_j / p_3 with p = G x'.
    The zoom weight is 8 / (4 + |J|^2 + |J^-1|^2) (Frobenius norms), J the 2x2 Jacobian
    of the pixel map x -> H x at the match: with independent noise sigma per coordinate
    in both images, d^2 has expectation (4 + |J|^2 + |J^-1|^2) sigma^2 to first order,
    8 sigma^2 where J = I.
    """
    n = len(src)
    G = np.linalg.inv(Hn)
    w = src @ Hn[2, :2] + Hn[2, 2]
    a = np.concatenate([src, np.ones((n, 1))], 1) / w[:, None]  # x / w
    u = a @ Hn[:2].T                                           # pi(Hn x)
    p = dst @ G[:, :2].T + G[:, 2]
    b = p / p[:, 2:]                                           # p / p_3
    v = b[:, :2]                                               # pi(G x')
    M = G[None, :2] - v[:, :, None] * G[2]                     # [I | -v] G, (N,2,3)
    a, b = a / kd, b / ks
    J = np.zeros((n, 4, 8))
    J[:, 0, 0:3] = J[:, 1, 3:6] = -a
    J[:, :2, 6:8] = u[:, :, None] * a[:, None, :2]
    J[:, 2:, 0:3] = M[:, :, 0:1] * b[:, None, :]
    J[:, 2:, 3:6] = M[:, :, 1:2] * b[:, None, :]
    J[:, 2:, 6:8] = M[:, :, 2:3] * b[:, None, :2]
    r = np.concatenate([(dst - u) / kd, (src - v) / ks], 1)
    A2, h2 = Hn[:2, :2], Hn[2, :2]                             # J = (A2 - u h2^T) ks / (kd w)
    adj = np.array([[A2[1, 1], -A2[0, 1]], [-A2[1, 0], A2[0, 0]]])
    fro2 = (A2 ** 2).sum() - 2.0 * u @ (A2 @ h2) + (u ** 2).sum(1) * (h2 @ h2)
    det = np.linalg.det(A2) - u @ (adj.T @ h2)                 # matrix determinant lemma
    s2 = (ks / (kd * w)) ** 2
    return r, J, 8.0 / (4.0 + s2 * fro2 + fro2 / (s2 * det ** 2))


def refine_robust(H: np.ndarray, src: np.ndarray, dst: np.ndarray, threshold_px: float,
                  iterations: int = 100, tol_px: float = 1e-2) -> np.ndarray:
    """Robust non-linear refinement of H on all matches (geometric solution of eq 13).

    Minimises sum_i log(1 + z_i d_i^2 / c^2), a Cauchy M-estimator of d_i, the symmetric
    transfer error of Algorithm 1, with z_i the zoom weight of `_linearise`: it scales
    d_i^2 to what the same noise would give where H neither magnifies nor shrinks, so a
    match in a zoomed region is not taken for an outlier. The scale c = 2.385 sigma,
    with sigma = threshold_px / sqrt(9.49) the noise for which threshold_px bounds d for
    95 % of inliers (four residual coordinates, chi-square with 4 dof).
    Levenberg-Marquardt on the 8 parameters of eq 14 in Hartley-normalised coordinates:
    each step uses the Gauss-Newton Hessian of the robust cost, the Cauchy curvature
    along each residual included where it is positive (Triggs et al. 2000), and z_i of
    the current H. Stops when a step moves the corners of the matches' bounding box by
    less than tol_px. Matches mapped behind either camera by the starting H take no part.
    """
    src, dst = _check_points(src, dst)
    Ts, Td = _normaliser(src), _normaliser(dst)
    ks, kd = Ts[0, 0], Td[0, 0]
    src_n, dst_n = _apply(Ts, src)[0], _apply(Td, dst)[0]
    Hn = Td @ np.asarray(H, float) @ np.linalg.inv(Ts)
    Hn = Hn / Hn[2, 2]
    c2 = (_CAUCHY_95 * threshold_px) ** 2 / _CHI2_4_95

    def transfer_sq(Hn: np.ndarray) -> np.ndarray:
        return (_one_way_sq(Hn, src_n, dst_n) / kd ** 2
                + _one_way_sq(np.linalg.inv(Hn), dst_n, src_n) / ks ** 2)

    use = np.isfinite(transfer_sq(Hn))
    if use.sum() < SAMPLE_SIZE:
        return _to_pixels(Hn, Ts, Td)
    src_n, dst_n = src_n[use], dst_n[use]
    lo, hi = src_n.min(0), src_n.max(0)
    box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    lam = 1e-3
    for _ in range(iterations):
        r, J, z = _linearise(Hn, src_n, dst_n, ks, kd)
        r2 = (r ** 2).sum(1)
        e = z * r2 / c2
        w = z / (1.0 + e)                                     # IRLS weight of d^2
        curv = np.minimum(2.0 * z * w / (c2 * (1.0 + e)), w / np.maximum(r2, 1e-300))
        Jr = np.einsum('nki,nk->ni', J, r)
        J = J.reshape(-1, 8)
        A = J.T @ (np.repeat(w, 4)[:, None] * J) - Jr.T @ (curv[:, None] * Jr)
        g = Jr.T @ w
        now = np.log1p(e).sum()
        while lam < 1e10:
            dh = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
            H_new = Hn + np.append(dh, 0.0).reshape(3, 3)
            if np.log1p(z * transfer_sq(H_new) / c2).sum() < now:
                lam *= 0.1
                break
            lam *= 10.0
        else:
            break
        moved = np.abs(_apply(H_new, box)[0] - _apply(Hn, box)[0]).max() / kd
        Hn = H_new
        if moved < tol_px:
            break
    return _to_pixels(Hn, Ts, Td)


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
    A = _eq13_rows(s[good], d[good])
    A, b = A[..., :8], -A[..., 8:]
    solvable = np.abs(np.linalg.det(A)) > 1e-12
    h = np.linalg.solve(A[solvable], b[solvable])[..., 0]
    return np.concatenate([h, np.ones((len(h), 1))], 1).reshape(-1, 3, 3)


def _msac_cost(d2: np.ndarray, t2: float) -> np.ndarray:
    """Truncated quadratic cost (MSAC, Torr & Zisserman 2000) along the last axis."""
    return np.minimum(d2, t2).sum(-1)


def _refit_inliers(H: np.ndarray, d2: np.ndarray, t2: float, src: np.ndarray,
                   dst: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1's refit on all inliers (eq 13), repeated while the MSAC cost drops.

    Takes H and its squared errors d2; returns the best H and its squared errors.
    """
    cost = _msac_cost(d2, t2)
    for _ in range(iterations):
        inl = d2 < t2
        if inl.sum() <= SAMPLE_SIZE:
            break
        H_new = solve_dlt(src[inl], dst[inl])
        d2_new = _transfer_sq(H_new, src, dst)
        cost_new = _msac_cost(d2_new, t2)
        if not cost_new < cost:
            break
        H, d2, cost = H_new, d2_new, cost_new
    return H, d2


def _ransac(src: np.ndarray, dst: np.ndarray, threshold: float, confidence: float,
            max_trials: int, rng: np.random.Generator, lmeds: bool
            ) -> tuple[tuple[np.ndarray, float] | None, int]:
    """Algorithm 1 (or LMedS): ((best H, inlier threshold) or None, trials drawn).

    Hypotheses come in batches and are scored on all matches in one array operation.
    RANSAC ranks them by the MSAC cost and refits every new best on its inliers
    before the adaptive trial count is updated from its inlier ratio.
    """
    n = len(src)
    Ts, Td = _normaliser(src), _normaliser(dst)
    src_n, dst_n = _apply(Ts, src)[0], _apply(Td, dst)[0]
    t2 = threshold ** 2
    best_H, best_score = None, np.inf
    needed, trials, batch = max_trials, 0, _FIRST_BATCH
    most = max(_BATCH, _BATCH_ERRORS // n)
    while trials < needed:
        size = min(batch, needed - trials)
        trials, batch = trials + size, min(2 * batch, most)
        Hn = _hypotheses(src_n, dst_n, _draw_samples(rng, n, size))
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
            best_H, d2k = _refit_inliers(H[k], d2[k], t2, src, dst)
            best_score, count = _msac_cost(d2k, t2), int((d2k < t2).sum())
        needed = min(needed, adaptive_trials(confidence, 1.0 - count / n))
    if best_H is None:
        return None, trials
    if lmeds:   # robust standard deviation, Rousseeuw & Leroy (1987) eq 5.1.20
        sigma = 1.4826 * (1.0 + 5.0 / max(n - SAMPLE_SIZE, 1)) * math.sqrt(best_score)
        threshold = min(threshold, 2.5 * sigma)
        best_H = _refit_inliers(best_H, _transfer_sq(best_H, src, dst), threshold ** 2,
                                src, dst)[0]
    return (best_H, threshold), trials


def _degenerate(H: np.ndarray, src: np.ndarray, dst: np.ndarray, max_scale: float) -> str:
    """Why H (fitted on these inliers) is unusable, or '' if it is sound."""
    if not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12:
        return 'H is singular or not finite'
    for name, pts in (('src', src), ('dst', dst)):
        d = pts - pts.mean(0)
        spread = math.sqrt(max(np.linalg.eigvalsh(d.T @ d / len(pts))[0], 0.0))
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
    one-sided reprojection error). With refine, 'ransac' and 'lmeds' end with
    `refine_robust`; without, they return Algorithm 1's refit on all inliers. The
    estimate fails (ok False, H None) with fewer than max(min_inliers,
    min_inlier_ratio * N) inliers, before or after the refinement, or a degenerate H.
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
        H, threshold = best
        inl = _transfer_sq(H, src, dst) < threshold ** 2
        if refine and inl.sum() >= need:      # too few inliers: rejected, not refined
            H = refine_robust(H, src, dst, threshold)
            inl = _transfer_sq(H, src, dst) < threshold ** 2
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
