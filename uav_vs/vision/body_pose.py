"""Vehicle pose from triangulated landmarks and their known body layout (section 3.1.1, eq 26).

Frames: `world` is ENU (z up) and the layout is given in `base_link` FLU (x forward,
y left, z up). The chapter's helicopter frame has z down, but eq 17 / eq 26 are the
same rotation by the yaw angle about the vertical, so with pitch and roll ~ 0 each
landmark i gives (c = cos yaw, s = sin yaw, t = base_link origin in world):

    x_h c - y_h s + t_x = x_w
    y_h c + x_h s + t_y = y_w
                    t_z = z_w - z_h

Stacked for every landmark this is A c = b (eq 26), solved by least squares (eq 25)
from >= 2 landmarks. (c, s) are then re-normalised to a rotation: yaw = atan2(s, c),
and t is recomputed with that unit rotation.

`method='rigid'` fits the full rotation (Kabsch/Umeyama SVD, no scale) from >= 3
non-collinear landmarks, for when pitch and roll are not negligible.
"""
from dataclasses import dataclass

import numpy as np

METHODS = ('yaw', 'rigid')


@dataclass(frozen=True)
class BodyPose:
    """base_link pose in world: x_w = R x_h + position."""

    position: np.ndarray      # (3,) m, world ENU; NaN when not ok
    yaw: float                # rad in (-pi, pi], about world z (ENU, 0 = facing +x)
    R: np.ndarray             # (3, 3) base_link -> world rotation
    quaternion: np.ndarray    # (4,) x, y, z, w of R
    residual_rms: float       # m, RMS over used landmarks of |R x_h + t - x_w|
    residuals: np.ndarray     # (n,) m, per landmark; NaN where not used
    n_used: int               # landmarks with a finite world position
    ok: bool
    reason: str               # why not ok (or a note on the method used); '' otherwise
    method: str = ''          # the fit used: 'yaw' (eq 26) or 'rigid'; '' when not ok


def solve_pose(layout: np.ndarray, world_points: np.ndarray, method: str = 'yaw') -> BodyPose:
    """Pose of base_link from landmarks: layout (n,3) in base_link, world_points (n,3) with NaN
    rows for landmarks not triangulated (eq 26, or the rigid SVD alignment)."""
    if method not in METHODS:
        raise ValueError(f'method: expected one of {METHODS}, got {method!r}')
    layout = np.asarray(layout, np.float64)
    world = np.asarray(world_points, np.float64)
    if layout.ndim != 2 or layout.shape[1] != 3 or world.shape != layout.shape:
        raise ValueError(f'layout and world_points: expected two (n, 3) arrays, '
                         f'got {layout.shape} and {world.shape}')
    used = np.all(np.isfinite(world), axis=1)
    n = int(used.sum())
    if n < 2:
        return _failed(layout.shape[0], n, f'{n} landmark(s) triangulated, need >= 2')
    lay, w = layout[used], world[used]

    note = ''
    if method == 'rigid':
        centred = lay - lay.mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        if n >= 3 and sv[1] > 1e-6 * sv[0]:
            R = _kabsch(lay, w)
        else:
            note = 'rigid alignment needs >= 3 non-collinear landmarks; eq 26 (yaw only) used'
            method = 'yaw'
    if method == 'yaw':
        R = _yaw_rotation(lay, w)
        if R is None:
            return _failed(layout.shape[0], n, 'landmarks used coincide in x-y of base_link: '
                                               'yaw is undetermined')

    position = (w - lay @ R.T).mean(axis=0)
    residuals = np.full(layout.shape[0], np.nan)
    residuals[used] = np.linalg.norm(lay @ R.T + position - w, axis=1)
    return BodyPose(position, float(np.arctan2(R[1, 0], R[0, 0])), R, quaternion_xyzw(R),
                    float(np.sqrt(np.mean(residuals[used] ** 2))), residuals, n, True, note,
                    method)


def _yaw_rotation(lay: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """Eq 26: least-squares (cos, sin, t) then cos/sin re-normalised; None if degenerate."""
    n = lay.shape[0]
    A = np.zeros((3 * n, 5))
    A[0::3, 0], A[0::3, 1], A[0::3, 2] = lay[:, 0], -lay[:, 1], 1.0
    A[1::3, 0], A[1::3, 1], A[1::3, 3] = lay[:, 1], lay[:, 0], 1.0
    A[2::3, 4] = 1.0
    b = np.column_stack([w[:, 0], w[:, 1], w[:, 2] - lay[:, 2]]).ravel()
    c, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 5 or np.hypot(c[0], c[1]) == 0:
        return None
    yaw = np.arctan2(c[1], c[0])
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])


def _kabsch(lay: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |R (l - l_mean) - (w - w_mean)|^2 (Kabsch/Umeyama, det +1)."""
    H = (lay - lay.mean(axis=0)).T @ (w - w.mean(axis=0))
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix."""
    m = R
    tr = np.trace(m)
    cand = np.array([1 + tr, 1 + m[0, 0] - m[1, 1] - m[2, 2],
                     1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2]])
    k = int(np.argmax(cand))
    s = 2.0 * np.sqrt(cand[k])
    if k == 0:
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif k == 1:
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif k == 2:
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    return -q if q[3] < 0 else q


def _failed(n: int, n_used: int, reason: str) -> BodyPose:
    nan3 = np.full(3, np.nan)
    return BodyPose(nan3, float('nan'), np.full((3, 3), np.nan), np.full(4, np.nan),
                    float('nan'), np.full(n, np.nan), n_used, False, reason)
