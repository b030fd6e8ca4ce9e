"""Camera pose from a world plane and its image (chapter section 4.1, eq 27).

The plane is Z = 0 of the world frame. A plane point (X, Y, 0) projects by eq 27 as
s x = K [r1 r2 r3 t] (X, Y, 0, 1)^T = K [r1 r2 t] (X, Y, 1)^T, so the plane-to-image
homography is H = K [r1 r2 t]:

- `plane_homography(K, R, t)`: H from a pose;
- `pose_from_plane_homography(K, H)`: the pose back from any H of that form (closed form);
- `refine_plane_pose(K, plane_xy, pixels)`: the pose that best explains measured
  plane <-> image correspondences (Levenberg-Marquardt on the reprojection error of
  eq 27), started from a given pose or from the homography of the correspondences;
  by cv2.solvePnPRefineLM (`method='opencv'`, the default) or by this module's own
  Levenberg-Marquardt (`method='lm'`).

R, t are world-to-camera (x_c = R x_w + t, as `Camera`); pixels are ideal
(undistorted: `Camera.undistort`), plane coordinates in metres.
"""
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RefinedPose:
    """Outcome of `refine_plane_pose`: world-to-camera R, t and the fit."""

    R: np.ndarray            # 3x3 world-to-camera rotation
    t: np.ndarray            # (3,) world-to-camera translation, m
    rms_px: float            # RMS reprojection error over the correspondences, px
    iterations: int | None   # Levenberg-Marquardt steps taken (None: cv2 does not say)


# Pose refinements: 'lm', the eq 27 least squares by this module's Levenberg-Marquardt;
# 'opencv', the same cost by cv2.solvePnPRefineLM. They reach the same optimum (to 1e-6);
# cv2's is 2-3 times faster (bench onboard/pose_refine_*), so it is the default.
REFINERS = ('lm', 'opencv')
DEFAULT_REFINER = 'opencv'


def plane_homography(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """H = K [r1 r2 t] (eq 27 with Z = 0), normalised so H[2,2] = 1 when possible."""
    H = K @ np.column_stack([R[:, 0], R[:, 1], t])
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H


def pose_from_plane_homography(K: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera R, t from a plane-to-image homography (section 4.1, eq 27).

    K^-1 H = lambda [r1 r2 t]: lambda from the mean norm of the first two columns, its
    sign so that the plane point seen at the principal point lies in front of the
    camera (positive depth), r3 = r1 x r2, and [r1 r2 r3] projected onto the nearest
    rotation by SVD.
    """
    G = np.linalg.solve(K, H)
    lam = 2.0 / (np.linalg.norm(G[:, 0]) + np.linalg.norm(G[:, 1]))
    centre = np.linalg.solve(H, np.array([K[0, 2], K[1, 2], 1.0]))
    lam *= np.sign(centre[2]) or 1.0   # depth of that point is lam / centre[2]
    r1, r2, t = lam * G[:, 0], lam * G[:, 1], lam * G[:, 2]
    U, _, Vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return R, t


def refine_plane_pose(K: np.ndarray, plane_xy: np.ndarray, pixels: np.ndarray,
                      R: np.ndarray | None = None, t: np.ndarray | None = None,
                      iterations: int = 20, tol: float = 1e-10,
                      method: str = DEFAULT_REFINER) -> RefinedPose:
    """Pose minimising the reprojection error of plane points (section 4.1, eq 27).

    plane_xy (N,2) are X, Y on the plane Z = 0, m ((N,3) with Z = 0 is taken too);
    pixels (N,2) their ideal pixels; N >= 4, not all on one line. Minimises
    sum_i |x_i - pi(K (R X_i + t))|^2 over the 6 pose parameters by Levenberg-Marquardt
    with the analytic Jacobian: each step perturbs R by a rotation vector on the left
    (R <- exp([w]x) R) and t additively, and stops after `iterations` steps or when the
    step (|w| rad + |dt| / mean depth) is below tol. Starts from R, t when given (both or
    neither), else from the DLT homography of the correspondences decomposed by
    `pose_from_plane_homography`. `method` is one of REFINERS: 'lm' is the above,
    'opencv' runs cv2.solvePnPRefineLM from the same start, to the same iteration cap
    and tolerance (it stops by its own criteria too, ~1e-6 deg from the optimum), and
    refuses a K with skew, which OpenCV's camera model leaves out.
    Raises ValueError (one line) on malformed input.
    """
    if method not in REFINERS:
        raise ValueError(f'method: expected one of {", ".join(REFINERS)}, got {method!r}')
    K, xyz, px = _check(K, plane_xy, pixels)
    if (R is None) != (t is None):
        raise ValueError('give both R and t as the starting pose, or neither')
    if R is None:
        H, _ = cv2.findHomography(xyz[:, :2], px, 0)
        if H is None or not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12:
            raise ValueError('plane_xy: degenerate correspondences (collinear points?)')
        R, t = pose_from_plane_homography(K, H)
    R, t = np.asarray(R, float).reshape(3, 3), np.asarray(t, float).reshape(3)
    if method == 'opencv':
        if K[0, 1] != 0.0:
            raise ValueError(f'method opencv: cv2.solvePnPRefineLM ignores the skew of K '
                             f'(K[0,1] = {K[0, 1]:g}); use lm')
        return _refine_opencv(K, xyz, px, R, t, iterations, tol)
    r, J = linearise(K, R, t, xyz, px)
    cost, lam, steps = float(r @ r), 1e-3, 0
    while steps < iterations and lam < 1e12:
        A, g = J.T @ J, J.T @ r
        d = np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-12)), -g)
        R_new, t_new = cv2.Rodrigues(d[:3])[0] @ R, t + d[3:]
        r_new, J_new = linearise(K, R_new, t_new, xyz, px)
        cost_new = float(r_new @ r_new)
        if not cost_new < cost:
            lam *= 10.0
            continue
        steps += 1
        R, t, r, J, cost, lam = R_new, t_new, r_new, J_new, cost_new, max(lam / 10.0, 1e-12)
        depth = max(float(np.mean(xyz @ R[2] + t[2])), 1e-9)
        if np.linalg.norm(d[:3]) + np.linalg.norm(d[3:]) / depth < tol:
            break
    return RefinedPose(R, t, float(np.sqrt(cost / len(px))), steps)


def _refine_opencv(K: np.ndarray, xyz: np.ndarray, px: np.ndarray, R: np.ndarray,
                   t: np.ndarray, iterations: int, tol: float) -> RefinedPose:
    """refine_plane_pose by cv2.solvePnPRefineLM (ideal pixels: no distortion)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, tol)
    rvec, tvec = cv2.solvePnPRefineLM(xyz, px, K, None, cv2.Rodrigues(R)[0],
                                      t.reshape(3, 1).copy(), criteria)
    R, t = cv2.Rodrigues(rvec)[0], tvec.ravel()
    q = xyz @ (K @ R).T + K @ t
    err = q[:, :2] / q[:, 2:] - px
    return RefinedPose(R, t, float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))), None)


def linearise(K: np.ndarray, R: np.ndarray, t: np.ndarray, xyz: np.ndarray, px: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) of eq 27 and their Jacobian (2N,6) in (w, dt), w the left rotation.

    With Xr = R X and x_c = Xr + t: dx_c/dw = -[Xr]x, dx_c/dt = I, chained with the
    derivative of (u, v) = ((fx x + s y) / z + cx, fy y / z + cy).
    """
    Xr = xyz @ R.T
    x, y, z = (Xr + t).T
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    iz = 1.0 / z
    a, b, c = fx * iz, s * iz, -(fx * x + s * y) * iz * iz      # du/dx_c
    e, f = fy * iz, -fy * y * iz * iz                          # dv/dx_c (dv/dx = 0)
    r = np.empty((len(z), 2))
    r[:, 0] = (fx * x + s * y) * iz + cx - px[:, 0]
    r[:, 1] = fy * y * iz + cy - px[:, 1]
    X, Y, Z = Xr.T
    J = np.empty((len(z), 2, 6))
    J[:, 0] = np.column_stack([c * Y - b * Z, a * Z - c * X, b * X - a * Y, a, b, c])
    J[:, 1] = np.column_stack([f * Y - e * Z, -f * X, e * X, np.zeros_like(z), e, f])
    return r.ravel(), J.reshape(-1, 6)


def _check(K: np.ndarray, plane_xy: np.ndarray, pixels: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K (3,3), plane points as (N,3) with Z = 0 and pixels (N,2); ValueError if malformed."""
    K = np.asarray(K, float)
    xy, px = np.asarray(plane_xy, float), np.asarray(pixels, float)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f'K: expected a finite 3x3 matrix, got shape {K.shape}')
    if xy.ndim != 2 or xy.shape[1] not in (2, 3) or px.shape != (len(xy), 2):
        raise ValueError(f'plane_xy and pixels: expected (N,2) (or (N,3) with Z = 0) and (N,2), '
                         f'got {xy.shape} and {px.shape}')
    if len(xy) < 4:
        raise ValueError(f'need at least 4 plane <-> image correspondences, got {len(xy)}')
    if not (np.isfinite(xy).all() and np.isfinite(px).all()):
        raise ValueError('plane_xy/pixels contain NaN or inf')
    if xy.shape[1] == 3:
        if np.any(np.abs(xy[:, 2]) > 1e-9 * max(1.0, np.abs(xy[:, :2]).max())):
            raise ValueError('plane_xy: points must lie on the plane Z = 0')
        xy = xy[:, :2]
    return K, np.column_stack([xy, np.zeros(len(xy))]), px
