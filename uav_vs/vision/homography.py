"""Robust plane-to-plane homography (chapter section 2.3, Algorithm 1, eq 13-14).

`estimate_homography(src, dst)` returns a `HomographyResult` whose H maps src to dst
(x' ~ H x, H[2,2] = 1). Methods:

- 'ransac': Algorithm 1, in Hartley-normalised coordinates (no check assumes pixels:
  threshold_px is in the points' own units, pixels or metres). Minimal samples of s = 4
  matches are solved with the inhomogeneous 8-unknown system of eq 14 (Gaussian
  elimination), a batch of samples per numpy call; a sample with a collinear triplet,
  or whose triplets do not all keep (or, with mirror, all reverse) their orientation,
  is dropped. Hypotheses are scored with the symmetric transfer error
  d^2 = d(x', Hx)^2 + d(x, H^-1 x')^2 and ranked by the MSAC cost (inliers counted,
  weighted by their error). Two standard speed-ups, neither of which changes what is
  estimated: a batch is ranked on a random subset of 128 matches and only its best is
  scored on all of them (preemptive scoring), and the batches are sized by the
  adaptive trial count (the first holds 16 samples, the next ones double or hold all
  the trials still needed). A new best is refitted on all its inliers (eq 14 by least
  squares, the pseudo-inverse of section 2.3.1) as Algorithm 1 does, once more on the
  inliers of that refit while the cost drops and the inliers are still too few to end
  the search (the local optimisation of LO-RANSAC); the trial count then follows the
  adaptive N = log(1-p) / log(1-(1-eps)^s) at the refit's inlier ratio.
- 'lmeds': least median of squares (Rousseeuw & Leroy 1987) over the same samples;
  inliers are within 2.5 robust standard deviations (at most threshold_px), and the
  winner is refitted on them.
- 'opencv_ransac', 'opencv_usac' (USAC_DEFAULT), 'opencv_magsac' (USAC_MAGSAC):
  `cv2.findHomography` for comparison.

'ransac' and 'lmeds' end with `refine_robust`: a Cauchy M-estimate of H from the
symmetric transfer errors of all matches, by iteratively reweighted least squares on
eq 14, run to convergence (1e-3 px). Unlike a least-squares refit on a hard inlier
set, it hinges neither on which matches fall just inside or outside the threshold nor
on which sample won: over orders of the same matches (and seeds) its corner error on
the Oxford pairs stays within about 0.01 px, where cv2 RANSAC's (a fixed seed, so
other samples for another order) ranges over 0.3 px on boat 1->2 and 5 px on graf 1->3.

The default is 'opencv_ransac' (DEFAULT_METHOD), chosen by bench/onboard_homography.py
(SIFT matches, corner error against the true H) against two targets: no worse than cv2
RANSAC on every real pair (Oxford graf/boat 1->2..1->6) and on 100 random
homographies of real images, and within 1.5 times its time on the same matches.
'ransac' meets the first on the real pairs: better by more than 0.01 px on five
(0.71 against 0.90 px on graf 1->2, 4.01 against 4.89 on graf 1->3, 0.92 against 1.09
on boat 1->4, 9.57 against 9.77 on boat 1->6), within 0.01 px on boat 1->2, 1->3 and
1->5, and below cv2 RANSAC's median over ten match orders on all eight pairs either
solves. On the warps its median, 90th
percentile, worst and mean errors are all lower (0.48 / 0.74 / 0.98 / 0.47 px against
0.50 / 0.78 / 1.18 / 0.49), yet it is worse by more than 0.01 px on 21 of them (better
on 39). It misses the second: 1.5-1.6 times cv2 RANSAC's time on the warps (median
ratio per warp), 1.0-3.0 times on the real pairs where cv2 needs few trials and
0.1-0.5 times where it needs many (graf 1->4..1->6); the median call over the real
pairs is 2.0-3.0 ms against 1.4-1.9 ms. Every estimator reports graf 1->5 and 1->6
(5-6 true inliers) as failures.

Whatever the method, a result is only `ok` if it passes the same checks: enough
inliers (count and ratio; an inlier has d < threshold), inliers not collinear (their
minor spread under 1 % of the major), and an H that is not degenerate (finite,
orientation preserving unless mirror, inlier region mapped to a convex quad whose area
is within max_scale^2 of the inliers' own). A failed estimate carries H = None and
the reason.
"""
import math
import sys
from dataclasses import dataclass

import cv2
import numpy as np

SAMPLE_SIZE = 4                  # s of Algorithm 1: 4 matches fix the 8 dof of H
_BATCH = 64                      # most hypotheses per numpy call, or _BATCH_ERRORS / N
_BATCH_ERRORS = 1 << 14          # hypothesis-match errors per call that make a batch worth it
_FIRST_BATCH = 16                # the first batch; each next one doubles up to the most
_PRESCORE = 128                  # a batch is ranked on this many matches (all, if fewer)
_COLLINEAR = 1e-3                # |cross| below this (normalised coords) = collinear triplet
_FLAT = 1e-2                     # minor / major spread of the inliers below this = collinear
_TRIPLETS = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
_PAIR_I, _PAIR_J = np.triu_indices(SAMPLE_SIZE, 1)          # the 6 pairs of a sample
_PROBE = np.array([[-1.0, 1, 1, -1], [-1, -1, 1, 1], [1, 1, 1, 1]])  # normalised square
_CHI2_4_95 = 9.4877              # 95 % quantile of chi-square with 4 dof
_PAIRS = np.array([[1, 0], [1, 0], [0, 1], [0, 1.0]])  # (x, y, x', y') -> (|x|^2, |x'|^2)
_CAUCHY_95 = 2.3849              # Cauchy scale for 95 % efficiency at Gaussian noise, in sigma
_OPENCV = {'opencv_ransac': cv2.RANSAC, 'opencv_usac': cv2.USAC_DEFAULT,
           'opencv_magsac': cv2.USAC_MAGSAC}
METHODS = ('ransac', 'lmeds', *_OPENCV)
DEFAULT_METHOD = 'opencv_ransac'     # by bench/onboard_homography.py (module docstring)


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


def _quiet() -> np.errstate:
    """No floating-point warnings: a point mapped to infinity (w = 0) is an infinite error."""
    return np.errstate(divide='ignore', invalid='ignore', over='ignore')


def _homogeneous(pts: np.ndarray) -> np.ndarray:
    """(N,2) points as the (3,N) array of their homogeneous coordinates."""
    out = np.ones((3, len(pts)))
    out[:2] = pts.T
    return out


def _one_way_sq(H: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """d(b, H a)^2 for H (...,3,3), a (3,N) homogeneous, b (2,N): (...,N), inf unless w > 0.

    Computed in place on the one (...,3,N) product, taken as a single matrix product
    (3B,3) x (3,N): the stacks of hypotheses are large. Callers ignore floating-point
    warnings (`_quiet`): w = 0 gives inf or NaN, then infinity.
    """
    q = (H.reshape(-1, 3) @ a).reshape(*H.shape[:-1], -1)     # (...,3,N)
    w = q[..., 2:, :]
    p = q[..., :2, :]
    p /= w
    p -= b
    p *= p
    d2 = p[..., 0, :] + p[..., 1, :]
    d2[~(w[..., 0, :] > 0)] = np.inf
    return d2


def _transfer_sq(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Squared symmetric transfer error for one H (3,3) or a stack (B,3,3), H[2,2] > 0.

    Points mapped behind either camera (w <= 0) get an infinite error.
    """
    return (_one_way_sq(H, _homogeneous(src), dst.T)
            + _one_way_sq(np.linalg.inv(H), _homogeneous(dst), src.T))


def transfer_error(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Symmetric transfer error in px, sqrt(d(x', Hx)^2 + d(x, H^-1 x')^2) (Algorithm 1)."""
    src, dst = _check_points(src, dst, minimum=0)
    with _quiet():
        return np.sqrt(_transfer_sq(np.asarray(H, float), src, dst))


class _Normalised:
    """Matches in Hartley-normalised coordinates, with the maps to and from the input's.

    Each side is moved to its centroid and scaled to a mean distance of sqrt(2) from
    it (Hartley & Zisserman 2004, sec. 4.4.4). Holds what every hypothesis is scored
    with: the points (N,2), their homogeneous (3,N) forms, and the 2N x 9 matrix A of
    eq 13, built once.
    """

    def __init__(self, src: np.ndarray, dst: np.ndarray) -> None:
        both = np.concatenate([src, dst], 1)                       # (N,4)
        mean = np.full(len(src), 1.0 / len(src))                   # means as products: fast
        c = mean @ both
        both -= c
        r = mean @ np.sqrt((both * both) @ _PAIRS)                # mean distance per side
        self.ks, self.kd = (math.sqrt(2.0) / x if x > 0 else 1.0 for x in r)
        both *= [self.ks, self.ks, self.kd, self.kd]
        self.src, self.dst = both[:, :2], both[:, 2:]
        self.Ts = np.array([[self.ks, 0.0, -self.ks * c[0]], [0.0, self.ks, -self.ks * c[1]],
                            [0.0, 0.0, 1.0]])
        self.Td = np.array([[self.kd, 0.0, -self.kd * c[2]], [0.0, self.kd, -self.kd * c[3]],
                            [0.0, 0.0, 1.0]])
        self.src_h, self.dst_h = _homogeneous(self.src), _homogeneous(self.dst)
        self.A = _eq13_rows(self.src, self.dst)
        # Errors in the input's units: rows x, y of Hn (of Hn^-1) scaled by 1/kd (1/ks)
        # map onto the centred input points, so no error is rescaled after the fact.
        self.to_dst_units = np.array([[1.0 / self.kd], [1.0 / self.kd], [1.0]])
        self.to_src_units = np.array([[1.0 / self.ks], [1.0 / self.ks], [1.0]])
        self.points = (self.src_h, self.dst_h, self.src_h[:2] / self.ks, self.dst_h[:2] / self.kd)

    def from_input(self, H: np.ndarray) -> np.ndarray:
        """H in the input's units to normalised coordinates, Hn[2,2] = 1."""
        Hn = self.Td @ H @ np.linalg.inv(self.Ts)
        return Hn / Hn[2, 2]

    def to_input(self, Hn: np.ndarray) -> np.ndarray:
        """Hn (3,3) back to the input's units (H = Td^-1 Hn Ts), H[2,2] = 1."""
        Td_inv = np.diag([1.0 / self.kd, 1.0 / self.kd, 1.0])
        Td_inv[:2, 2] = -self.Td[:2, 2] / self.kd
        H = Td_inv @ Hn @ self.Ts
        return H / H[2, 2]

    def columns(self, cols: np.ndarray) -> tuple[np.ndarray, ...]:
        """`points` of the matches cols only, for `transfer_sq`."""
        return tuple(p[:, cols] for p in self.points)

    def transfer_sq(self, Hn: np.ndarray, points: tuple[np.ndarray, ...] | None = None
                    ) -> np.ndarray:
        """Squared symmetric transfer error in the input's units, of normalised Hn (...,3,3),
        at all matches or at `points` (from `columns`)."""
        src_h, dst_h, src_c, dst_c = points or self.points
        d2 = _one_way_sq(Hn * self.to_dst_units, src_h, dst_c)
        d2 += _one_way_sq(np.linalg.inv(Hn) * self.to_src_units, dst_h, src_c)
        return d2


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
    data = _Normalised(*_check_points(src, dst))
    A, b = data.A[:, :8], -data.A[:, 8]
    h = np.linalg.solve(A, b) if len(A) == 2 * SAMPLE_SIZE else np.linalg.pinv(A) @ b
    return data.to_input(np.append(h, 1.0).reshape(3, 3))


def solve_dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised homogeneous DLT: Ah = 0 of eq 13, h the unit vector minimising |Ah|.

    h is the eigenvector of the 9x9 A^T A with the smallest eigenvalue (the last right
    singular vector of A), A built from Hartley-normalised points.
    """
    data = _Normalised(*_check_points(src, dst))
    return data.to_input(_dlt(data.A))


def _dlt(A: np.ndarray) -> np.ndarray:
    """Hn minimising |A h| over |h| = 1 (eq 13, A (2N,9)), scaled to Hn[2,2] = 1."""
    h = np.linalg.eigh(A.T @ A)[1][:, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        return h.reshape(3, 3) / h[8]


def _weighted_eq14(A: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Hn minimising sum_i weight_i |A_i h|^2 with h33 = 1: eq 14 in the least-squares sense.

    A (2N,9) holds eq 13's two rows of each match, weight (N,) one value per match; the
    normal equations of A' h' = b (the pseudo-inverse solution of section 2.3.1) are
    the top-left 8x8 block of M = A^T W A against minus its last column. NaN where they
    are singular.
    """
    M = (A * np.repeat(weight, 2)[:, None]).T @ A
    h = np.ones(9)
    try:
        h[:8] = np.linalg.solve(M[:8, :8], -M[:8, 8])
    except np.linalg.LinAlgError:
        h[:] = np.nan
    return h.reshape(3, 3)


def refine_robust(H: np.ndarray, src: np.ndarray, dst: np.ndarray, threshold_px: float,
                  iterations: int = 30, tol_px: float = 1e-3) -> np.ndarray:
    """Robust refit of H on all matches: iteratively reweighted eq 14 with Cauchy weights.

    Minimises sum_i rho(d_i), rho(d) = log(1 + d^2 / c^2) the Cauchy M-estimator of
    d_i, the symmetric transfer error of Algorithm 1, by iteratively reweighted least
    squares on eq 14 (h33 = 1, Hartley-normalised points): each step solves
    min sum_i v_i |A_i h|^2 with v_i = 1 / ((1 + d_i^2 / c^2) w_i^2) from the current H,
    where w_i = (Hn x_i)_3 turns the algebraic residual of the two rows A_i of eq 13
    into the geometric one in the second image. The scale c = 2.385 sigma, with
    sigma = threshold_px / sqrt(9.49) the noise for which threshold_px bounds d for 95 %
    of inliers (four residual coordinates, chi-square with 4 dof). Stops after
    `iterations` steps, or before a step that would move the corners (+-1, +-1) around
    the matches' centroid (normalised coordinates) by less than tol_px. Matches
    mapped behind either camera (d infinite) take no part.
    """
    data = _Normalised(*_check_points(src, dst))
    Hn = data.from_input(np.asarray(H, float))
    with _quiet():
        return data.to_input(_refine(Hn, data, data.transfer_sq(Hn), threshold_px,
                                     iterations, tol_px)[0])


def _refine(Hn: np.ndarray, data: _Normalised, d2: np.ndarray, threshold: float,
            iterations: int = 30, tol_px: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """`refine_robust` on normalised data, from Hn and its squared errors d2: (Hn, d2)."""
    c2 = (_CAUCHY_95 * threshold) ** 2 / _CHI2_4_95
    for _ in range(iterations):
        w = Hn[2] @ data.src_h
        weight = 1.0 / (d2 / c2 + 1.0) / np.maximum(w * w, 1e-300)   # 0 where d2 is inf
        H_new = _weighted_eq14(data.A, weight)
        if not np.isfinite(H_new).all():
            break
        a, b = H_new @ _PROBE, Hn @ _PROBE
        if not np.abs(a[:2] / a[2] - b[:2] / b[2]).max() / data.kd >= tol_px:
            break                 # converged: keep Hn, whose errors are known
        Hn, d2 = H_new, data.transfer_sq(H_new)
    return Hn, d2


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
    dup = (idx[:, _PAIR_I] == idx[:, _PAIR_J]).any(1)
    while dup.any():
        idx[dup] = rng.integers(0, n, size=(int(dup.sum()), SAMPLE_SIZE))
        dup[dup] = (idx[dup][:, _PAIR_I] == idx[dup][:, _PAIR_J]).any(1)
    return idx


def _hypotheses(data: _Normalised, samples: np.ndarray, mirror: bool) -> np.ndarray:
    """Eq 14 minimal solutions (B,3,3) in normalised coordinates for the usable samples.

    A sample is dropped when any of its four triplets is collinear in either image, or
    when the triplets' orientations do not all change alike between the images (no
    homography maps four points so with all of them in front: Chum's oriented
    constraint). Orientation-reversing samples are kept only when mirror is True.
    """
    s, d = data.src[samples], data.dst[samples]              # (B,4,2)

    def cross(p: np.ndarray) -> np.ndarray:
        a, b, c = p[:, _TRIPLETS[:, 0]], p[:, _TRIPLETS[:, 1]], p[:, _TRIPLETS[:, 2]]
        e, f = b - a, c - a
        return e[..., 0] * f[..., 1] - e[..., 1] * f[..., 0]  # (B,4)
    cs, cd = cross(s), cross(d)
    sign = cs * cd
    good = ((np.abs(cs) > _COLLINEAR) & (np.abs(cd) > _COLLINEAR)).all(1)
    good &= (sign > 0).all(1) | (mirror & (sign < 0).all(1))
    if not good.any():
        return np.empty((0, 3, 3))
    A = data.A.reshape(-1, 2, 9)[samples[good]].reshape(-1, 8, 9)
    A, b = A[..., :8], -A[..., 8:]
    try:
        h = np.linalg.solve(A, b)[..., 0]
    except np.linalg.LinAlgError:         # a singular system in the batch: drop it
        keep = np.abs(np.linalg.det(A)) > 1e-12
        h = np.linalg.solve(A[keep], b[keep])[..., 0]
    return np.concatenate([h, np.ones((len(h), 1))], 1).reshape(-1, 3, 3)


def _msac_cost(d2: np.ndarray, t2: float) -> np.ndarray:
    """Truncated quadratic cost (MSAC, Torr & Zisserman 2000) along the last axis."""
    return np.minimum(d2, t2).sum(-1)


def _local_optimisation(Hn: np.ndarray, d2: np.ndarray, t2: float, data: _Normalised,
                        enough: float = math.inf, iterations: int = 2
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1's refit on all inliers (eq 14), repeated while the MSAC cost drops.

    The inner re-fit of LO-RANSAC (Chum et al. 2003): each least-squares solution of
    eq 14 on the inliers gives a new inlier set, refitted in turn, until the inliers
    number `enough` (those that meet the adaptive N with the trials already drawn: more
    refits could not end the search sooner, and the final refinement polishes H).
    Takes Hn and its squared errors d2; returns the best Hn and its squared errors.
    """
    cost = _msac_cost(d2, t2)
    for k in range(iterations):
        inl = d2 < t2
        count = inl.sum()
        if count <= SAMPLE_SIZE or (k and count >= enough):
            break
        H_new = _weighted_eq14(data.A, inl.astype(float))
        if not np.isfinite(H_new).all():
            break
        d2_new = data.transfer_sq(H_new)
        cost_new = _msac_cost(d2_new, t2)
        if not cost_new < cost:
            break
        Hn, d2, cost = H_new, d2_new, cost_new
    return Hn, d2


def _enough(p: float, n: int, trials: int, s: int = SAMPLE_SIZE) -> float:
    """Fewest inliers of n for which N of Algorithm 1 is at most trials (the inverse of
    `adaptive_trials`): n (1 - (1-p)^(1/trials))^(1/s)."""
    return n * (-math.expm1(math.log1p(-p) / trials)) ** (1.0 / s)


def _ransac(data: _Normalised, threshold: float, confidence: float, max_trials: int,
            rng: np.random.Generator, lmeds: bool, mirror: bool
            ) -> tuple[tuple[np.ndarray, np.ndarray, float] | None, int]:
    """Algorithm 1 (or LMedS): ((best Hn, its squared errors, inlier threshold) or None,
    trials drawn).

    Hypotheses come in batches, each scored in one array operation: the first batch
    has _FIRST_BATCH samples, the next ones double, or hold all the trials still needed
    at once, up to `most`. RANSAC ranks a batch by the MSAC cost on a random subset of
    _PRESCORE matches (all if fewer), scores its best on all matches, and runs the
    local optimisation on every new best before the adaptive trial count is updated
    from its inlier ratio.
    """
    n = len(data.src)
    t2 = threshold ** 2
    best_H, best_score = None, np.inf
    needed, trials, batch = max_trials, 0, _FIRST_BATCH
    most = max(_BATCH, _BATCH_ERRORS // n)
    pre = (data.columns(rng.integers(0, n, _PRESCORE)) if n > _PRESCORE and not lmeds
           else None)
    while trials < needed:
        size = min(batch, needed - trials)
        trials = trials + size
        batch = min(2 * batch, most)
        Hn = _hypotheses(data, _draw_samples(rng, n, size), mirror)
        if not len(Hn):
            continue
        if lmeds:
            d2 = data.transfer_sq(Hn)                           # (B,N) all at once
            score = np.median(d2, axis=1)
            k = int(np.argmin(score))
            if not score[k] < best_score:
                continue
            best_H, best_d2, best_score = Hn[k], d2[k], score[k]
            count = int((d2[k] <= score[k]).sum())
        else:
            if pre is None:
                d2 = data.transfer_sq(Hn)                       # (B,N) all at once
                k = int(np.argmin(_msac_cost(d2, t2)))
                d2k = d2[k]
            else:                 # the batch's best on the subset, then on all matches
                k = int(np.argmin(_msac_cost(data.transfer_sq(Hn, pre), t2)))
                d2k = data.transfer_sq(Hn[k])
            if not _msac_cost(d2k, t2) < best_score:
                continue
            best_H, best_d2 = _local_optimisation(Hn[k], d2k, t2, data,
                                                  _enough(confidence, n, trials))
            best_score, count = _msac_cost(best_d2, t2), int((best_d2 < t2).sum())
        needed = min(needed, adaptive_trials(confidence, 1.0 - count / n))
        batch = min(max(batch, needed - trials), most)     # what is left, in one go
    if best_H is None:
        return None, trials
    if lmeds:   # robust standard deviation, Rousseeuw & Leroy (1987) eq 5.1.20
        sigma = 1.4826 * (1.0 + 5.0 / max(n - SAMPLE_SIZE, 1)) * math.sqrt(best_score)
        threshold = min(threshold, 2.5 * sigma)
        best_H, best_d2 = _local_optimisation(best_H, best_d2, threshold ** 2, data)
    return (best_H, best_d2, threshold), trials


def _spread(xy: np.ndarray) -> tuple[float, float]:
    """Minor and major spread (up to one common scale) of (2,N) points about their mean."""
    d = xy - xy.mean(1)[:, None]
    (a, b), (_, c) = (d @ d.T).tolist()
    mid, half = (a + c) / 2.0, math.hypot((a - c) / 2.0, b)
    return math.sqrt(max(mid - half, 0.0)), math.sqrt(mid + half)


def _degenerate(H: np.ndarray, src: np.ndarray, dst: np.ndarray, max_scale: float,
                mirror: bool) -> str:
    """Why H (fitted on these inliers) is unusable, or '' if it is sound.

    Every check is relative to the data's own scale, so it holds in any unit. The points
    are taken as rows x and y: numpy reduces an (N,2) array down its columns slowly.
    """
    if not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12 * abs(H).max() ** 3:
        return 'H is singular or not finite'
    src, dst = np.ascontiguousarray(src.T), np.ascontiguousarray(dst.T)
    for name, xy in (('src', src), ('dst', dst)):
        minor, major = _spread(xy)
        if not minor > _FLAT * major:
            return (f'inliers are collinear in {name} '
                    f'(minor spread {minor / max(major, 1e-300):.2g} of the major)')
    (x0, y0), (x1, y1) = src.min(1), src.max(1)
    x, y, w = (H @ [[x0, x1, x1, x0], [y0, y0, y1, y1], [1.0, 1.0, 1.0, 1.0]]).tolist()
    if not min(w) > 0:
        return 'inlier region maps across the horizon'
    x, y = [a / c for a, c in zip(x, w)], [b / c for b, c in zip(y, w)]
    nxt = (1, 2, 3, 0)
    ex = [x[j] - x[i] for i, j in enumerate(nxt)]
    ey = [y[j] - y[i] for i, j in enumerate(nxt)]
    turn = [ex[i] * ey[j] - ey[i] * ex[j] for i, j in enumerate(nxt)]
    if not (min(turn) > 0 or (mirror and max(turn) < 0)):
        return 'inlier region maps to a flipped or non-convex quad'
    area = 0.5 * abs(sum(x[i] * y[j] - x[j] * y[i] for i, j in enumerate(nxt)))
    (u0, v0), (u1, v1) = dst.min(1), dst.max(1)
    area /= max((u1 - u0) * (v1 - v0), 1e-300)
    if not max_scale ** -2 <= area <= max_scale ** 2:
        return f'inlier region maps out of proportion to the inliers (area ratio {area:.3g})'
    return ''


def _fit(src: np.ndarray, dst: np.ndarray, method: str, threshold: float, confidence: float,
         max_trials: int, rng: np.random.Generator | int | None, mirror: bool, refine_from: int
         ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, int, str]:
    """H (input units, H[2,2] = 1), its inliers, all squared errors and the trials drawn,
    or H None and why. 'ransac' and 'lmeds' end with `refine_robust` when refine_from > 0
    and at least refine_from of their matches are inliers."""
    none = np.zeros(len(src), bool)
    with _quiet():
        if method in _OPENCV:
            H, mask = cv2.findHomography(src, dst, _OPENCV[method], threshold,
                                         maxIters=max_trials, confidence=confidence)
            if H is None:
                return None, none, none, 0, 'OpenCV found no homography'
            H = H / H[2, 2]
            return H, mask.ravel().astype(bool), _transfer_sq(H, src, dst), 0, ''
        data = _Normalised(src, dst)
        best, trials = _ransac(data, threshold, confidence, max_trials,
                               np.random.default_rng(rng), method == 'lmeds', mirror)
        if best is None:
            return (None, none, none, trials,
                    'no usable sample: every one collinear or orientation-flipped')
        Hn, d2, threshold = best
        inl = d2 < threshold ** 2
        if refine_from and inl.sum() >= refine_from:   # too few inliers: rejected, not refined
            Hn, d2 = _refine(Hn, data, d2, threshold)
            inl = d2 < threshold ** 2
        return data.to_input(Hn), inl, d2, trials, ''


def estimate_homography(src: np.ndarray, dst: np.ndarray, method: str = DEFAULT_METHOD,
                        threshold_px: float = 3.0, confidence: float = 0.995,
                        max_trials: int = 2000, min_inliers: int = 8,
                        rng: np.random.Generator | int | None = None, *,
                        min_inlier_ratio: float = 0.2, max_scale: float = 10.0,
                        refine: bool = True, mirror: bool = False) -> HomographyResult:
    """Robust H with x' ~ H x from matches src (N,2) -> dst (N,2) (section 2.3, Algorithm 1).

    threshold_px bounds the symmetric transfer error of an inlier, in the points' units
    (px for image points, m for plane points in metres; OpenCV methods: the one-sided
    error d(x', Hx) in dst's units, so plane metres to pixels keeps a threshold in px). With
    refine, 'ransac' and 'lmeds' end with `refine_robust`; without, they return
    Algorithm 1's refit on all inliers. mirror accepts orientation-reversing maps (a
    plane seen from behind, corners listed the other way round, ENU ground coordinates
    seen from above: the image's y axis points down). The estimate fails
    (ok False, H None) with fewer than max(min_inliers, min_inlier_ratio * N) inliers,
    before or after the refinement, or a degenerate H.
    """
    if method not in METHODS:
        raise ValueError(f'unknown homography method {method!r}; use one of {METHODS}')
    if threshold_px <= 0 or max_trials < 1 or min_inliers < SAMPLE_SIZE:
        raise ValueError('need threshold_px > 0, max_trials >= 1 and min_inliers >= 4')
    src, dst = _check_points(src, dst, minimum=0)
    n = len(src)
    need = max(min_inliers, math.ceil(min_inlier_ratio * n))
    if n < need:
        return HomographyResult(False, None, np.zeros(n, bool), 0, math.nan,
                                f'{n} matches, fewer than the {need} inliers required')
    H, inl, d2, trials, reason = _fit(src, dst, method, threshold_px, confidence, max_trials,
                                      rng, mirror, need if refine else 0)
    if H is None:
        return HomographyResult(False, None, inl, trials, math.nan, reason)
    count = int(inl.sum())
    rms = math.sqrt(d2[inl].mean()) if count else math.nan
    if count < need:
        return HomographyResult(False, None, inl, trials, rms,
                                f'{count} inliers of {n}, fewer than the {need} required')
    reason = _degenerate(H, src[inl], dst[inl], max_scale, mirror)
    if reason:
        return HomographyResult(False, None, inl, trials, rms, reason)
    return HomographyResult(True, H, inl, trials, rms, '')
