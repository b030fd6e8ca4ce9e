"""Extrinsics of a rig of cameras that see one board together (chapter section 3.1: the
ground station's R, t of eq 16), in the world frame a board lying on the ground fixes.

Each camera's intrinsics are known (uav_vs.vision.calibration). Every view of the board
by a camera gives the board's pose in that camera (cv2.solvePnP); the views two cameras
share give their relative pose, chained from the first camera through the others, and
a joint refinement (scipy.optimize.least_squares, with an analytic sparse Jacobian)
moves every camera pose and every board pose to minimise the reprojection error of
every board point in every camera, the intrinsics held fixed or refined with them. The
world frame (REP-103: ENU, z up) is the board's in one view where it lies flat on the
ground: origin at its first point, x along its first row, z up out of the board.
`neighbour_errors` checks a rig against the board itself.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import cv2
import numpy as np
import yaml
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from uav_vs.vision.calibration import (MODELS, Board, CalibrationInputError, Detection,
                                       Intrinsics)
from uav_vs.vision.camera import Camera
from uav_vs.vision.triangulation import triangulate

# the board's frame (z into the board, away from a camera above it) to the world (z up)
BOARD_TO_WORLD = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class RigCamera:
    """One camera of the rig: its intrinsics and its world-to-camera pose x_c = R x_w + t."""

    name: str
    intrinsics: Intrinsics
    R: np.ndarray
    t: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass(frozen=True)
class Rig:
    cameras: list[RigCamera]
    rms: float                          # over every board point of every view [px]
    camera_rms: dict[str, float]        # per camera [px]
    shared_views: dict[str, int]        # per camera: views it shares with another camera
    views: int                          # views with the board in two cameras or more
    latency: dict[str, float] | None = None   # per camera, s after the first's (rig_timing)

    def report(self) -> list[str]:
        lines = [f'rig: {len(self.cameras)} cameras, {self.views} shared views, RMS '
                 f'{self.rms:.3f} px']
        for cam in self.cameras:
            x, y, z = cam.center
            lines.append(f'  {cam.name}: at ({x:.3f}, {y:.3f}, {z:.3f}) m, '
                         f'{self.shared_views[cam.name]} shared views, RMS '
                         f'{self.camera_rms[cam.name]:.3f} px')
            if self.latency is not None and cam is not self.cameras[0]:
                lines.append(f'    latency {1000 * self.latency[cam.name]:+.1f} ms after '
                             f'{self.cameras[0].name}')
            K = cam.intrinsics.K
            lines.append(f'    fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy '
                         f'{K[1, 2]:.2f} px, D {np.array2string(cam.intrinsics.D, precision=5)}')
        return lines

    def cameras_yaml(self) -> str:
        """The `cameras` block of config/ground_trinocular.yaml (under ros__parameters)."""
        block: dict = {'names': [c.name for c in self.cameras]}
        for c in self.cameras:
            w, h = c.intrinsics.size
            block[c.name] = {'width': int(w), 'height': int(h), 'frame_id': f'{c.name}_optical',
                             'K': [float(v) for v in c.intrinsics.K.ravel()],
                             'D': [float(v) for v in c.intrinsics.D],
                             'R': [float(v) for v in c.R.ravel()],
                             't': [float(v) for v in c.t]}
            if self.latency is not None:
                block[c.name]['latency'] = round(float(self.latency[c.name]), 4)
        return yaml.safe_dump({'cameras': block}, sort_keys=False, width=100)


def board_pose(board: Board, det: Detection, intr: Intrinsics) -> np.ndarray:
    """4x4 board -> camera transform of one view (IPPE for the planar board, refined)."""
    objects = board.object_points()[det.ids].astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(objects, det.points.astype(np.float64), intr.K, intr.D,
                                  flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationInputError('the board pose of a view could not be solved')
    rvec, tvec = cv2.solvePnPRefineLM(objects, det.points.astype(np.float64), intr.K, intr.D,
                                      rvec, tvec)
    return _matrix(rvec.ravel(), tvec.ravel())


def calibrate_rig(board: Board, detections: dict[str, dict[str, Detection]],
                  intrinsics: dict[str, Intrinsics], ground_view: str,
                  refine_intrinsics: bool = False,
                  motion: dict[str, dict[str, np.ndarray]] | None = None,
                  solver: str = 'scipy') -> Rig:
    """R, t of every camera (keys of `detections`, the first one the reference) from the
    views (by key) each saw, the world fixed by `ground_view`, a view in which the board
    lies on the ground. Every view takes part in the refinement, a camera's own views
    too (they tie its lens); `refine_intrinsics` frees K and the model's distortion
    coefficients there, starting from `intrinsics`.

    `motion` (camera -> view -> (N, 2) px/s, the velocity of each detected point) frees
    a time shift per camera but the first: its points are taken where they were that
    much later, `detections + motion * shift`, and `Rig.latency` holds the shifts
    (uav_vs.vision.rig_timing iterates this to a camera's latency).

    `solver`: 'scipy' (our bundle adjustment, `_refine`) or 'opencv' (OpenCV 5's
    cv2.calibrateMultiview, its own initialisation and refinement of the same
    reprojection errors; no `motion`)."""
    if solver not in SOLVERS:
        raise CalibrationInputError(f'solver: expected one of {", ".join(SOLVERS)}, got '
                                    f'{solver!r}')
    if solver == 'opencv' and not hasattr(cv2, 'calibrateMultiviewExtended'):
        raise CalibrationInputError(f"solver 'opencv' needs OpenCV 5's calibrateMultiview "
                                    f'(this is OpenCV {cv2.__version__})')
    if solver == 'opencv' and motion is not None:
        raise CalibrationInputError("solver 'opencv' cannot measure latencies: use 'scipy'")
    names = list(detections)
    if len(names) < 2:
        raise CalibrationInputError('a rig needs two cameras or more')
    if board.point_symmetric:
        raise CalibrationInputError(
            f'a {board.kind} board of {board.rows} x {board.cols} looks the same turned half '
            f'round, so cameras on opposite sides number its points from opposite ends: use '
            f'a ChArUco board, or a chessboard with an odd number of squares one way and an '
            f'even number the other (e.g. 7 x 10)')
    poses = {c: {v: board_pose(board, d, intrinsics[c]) for v, d in detections[c].items()}
             for c in names}
    counts: dict[str, int] = {}
    for c in names:
        counts[c] = sum(any(v in poses[o] for o in names if o != c) for v in poses[c])
    lonely = [c for c in names if counts[c] == 0]
    if lonely:
        raise CalibrationInputError(f'{", ".join(lonely)} never shares a view of the board '
                                    f'with another camera')
    in_ref = _chain(names, poses)
    views = sorted({v for c in names for v in poses[c]
                    if sum(v in poses[o] for o in names) >= 2})
    if ground_view not in {v for c in names for v in poses[c]}:
        raise CalibrationInputError(f'ground view {ground_view!r}: no camera saw the board '
                                    f'in it')
    boards = {}
    for v in sorted({v for c in names for v in poses[c]}):
        c = next(c for c in names if v in poses[c])
        boards[v] = np.linalg.inv(in_ref[c]) @ poses[c][v]
    if solver == 'opencv':
        in_ref, intrinsics, boards, residuals = _multiview(board, detections, intrinsics, names,
                                                           list(boards), refine_intrinsics)
        shifts = [0.0] * len(names)
    else:
        in_ref, intrinsics, boards, residuals, shifts = _refine(
            board, detections, intrinsics, names, in_ref, boards, refine_intrinsics, motion)
    # world -> ref: world point -> board frame of the ground view -> ref frame
    world_to_board = np.eye(4)
    world_to_board[:3, :3] = BOARD_TO_WORLD.T
    ref_from_world = boards[ground_view] @ world_to_board
    cameras = []
    for c in names:
        T = in_ref[c] @ ref_from_world
        cameras.append(RigCamera(c, intrinsics[c], T[:3, :3], T[:3, 3]))
    rms = {c: float(np.sqrt(np.mean(r ** 2))) for c, r in residuals.items()}
    every = np.concatenate(list(residuals.values()))
    return Rig(cameras, float(np.sqrt(np.mean(every ** 2))), rms, counts, len(views),
               None if motion is None else dict(zip(names, shifts)))


def _chain(names: list[str], poses: dict[str, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """ref -> camera transform of every camera, by the views shared with cameras already
    placed (breadth first from the reference), each pair's estimates averaged."""
    placed = {names[0]: np.eye(4)}
    queue = deque([names[0]])
    while queue:
        a = queue.popleft()
        for b in names:
            if b in placed:
                continue
            shared = [v for v in poses[a] if v in poses[b]]
            if not shared:
                continue
            # b <- a for each shared view: T_b_board inv(T_a_board)
            estimates = [poses[b][v] @ np.linalg.inv(poses[a][v]) for v in shared]
            placed[b] = _mean_transform(estimates) @ placed[a]
            queue.append(b)
    missing = [c for c in names if c not in placed]
    if missing:
        raise CalibrationInputError(f'{", ".join(missing)} shares no view with the cameras '
                                    f'linked to {names[0]}')
    return placed


def _mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """The chordal mean of the rotations (projected back onto SO(3)) and the median of
    the translations."""
    U, _, Vt = np.linalg.svd(sum(T[:3, :3] for T in transforms))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, np.median([T[:3, 3] for T in transforms], axis=0)
    return out


FREE_DISTORTION = {'pinhole': 0, 'k1': 1, 'plumb_bob': 5, 'rational': 8}
SOLVERS = ('scipy', 'opencv')


def _multiview(board: Board, detections, intrinsics, names, views, refine_intrinsics):
    """The rig by cv2.calibrateMultiviewExtended (OpenCV 5): ref -> camera transforms,
    intrinsics, board -> ref transform of each view, each camera's residuals (px)."""
    objects = board.object_points().astype(np.float32)
    mask = np.zeros((len(names), len(views)), np.uint8)
    pixels = []
    for ci, c in enumerate(names):
        row = []
        for vi, v in enumerate(views):
            seen = np.full((len(objects), 2), -1.0, np.float32)    # -1: not seen
            if v in detections[c]:
                seen[detections[c][v].ids] = detections[c][v].points
                mask[ci, vi] = 1
            row.append(seen)
        pixels.append(row)
    fixed = [cv2.CALIB_FIX_INTRINSIC if not refine_intrinsics else
             MODELS[intrinsics[c].model][0] for c in names]
    _, Ks, Ds, Rs, Ts, _, rvecs, tvecs, _ = cv2.calibrateMultiviewExtended(
        [objects] * len(views), pixels, [intrinsics[c].size for c in names], mask,
        np.full(len(names), cv2.CALIB_MODEL_PINHOLE, np.uint8),
        [intrinsics[c].K.astype(np.float64) for c in names],
        [intrinsics[c].D.reshape(1, -1).astype(np.float64) for c in names], None, None,
        flagsForIntrinsics=np.array(fixed, np.int32), flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    in_ref = {}
    for c, R, t in zip(names, Rs, Ts):
        T = np.eye(4)
        T[:3, :3] = R if np.shape(R) == (3, 3) else cv2.Rodrigues(R)[0]
        T[:3, 3] = np.ravel(t)
        in_ref[c] = T
    refined = {c: replace(intrinsics[c], K=np.asarray(K), D=np.ravel(D))
               for c, K, D in zip(names, Ks, Ds)}
    boards = {v: _matrix(np.ravel(r), np.ravel(t)) for v, r, t in zip(views, rvecs, tvecs)
              if r is not None and np.size(r) == 3}
    residuals = {}
    for c in names:
        errors = []
        for v, det in detections[c].items():
            T = in_ref[c] @ boards[v]
            px, _ = cv2.projectPoints(objects[det.ids].astype(np.float64),
                                      cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], refined[c].K,
                                      refined[c].D)
            errors.append(np.linalg.norm(px.reshape(-1, 2) - det.points, axis=1))
        residuals[c] = np.concatenate(errors)
    return in_ref, refined, boards, residuals


def _refine(board: Board, detections, intrinsics, names, in_ref, boards, refine_intrinsics,
            motion=None):
    """Bundle adjustment: every camera pose (but the reference's), every board pose and,
    with `refine_intrinsics`, every camera's fx, fy, cx, cy and free distortion
    coefficients, and with `motion` every camera's time shift (but the reference's),
    moved together to minimise every reprojection error of every view.

    The Jacobian is analytic and sparse: cv2.projectPoints gives the derivatives of each
    view's pixels by its pose and the camera's intrinsics, cv2.composeRT those of the
    composed pose by the camera's and the board's."""
    objects = board.object_points().astype(np.float64)
    views = list(boards)
    n_cam = len(names)
    index = {v: k for k, v in enumerate(views)}
    free = [FREE_DISTORTION[intrinsics[c].model] if refine_intrinsics else 0 for c in names]
    n_intr = [4 + f if refine_intrinsics else 0 for f in free]
    pose_at = [-1] + [6 * k for k in range(n_cam - 1)]
    intr_at = np.concatenate([[0], np.cumsum(n_intr)])[:-1] + 6 * (n_cam - 1)
    shift_at = 6 * (n_cam - 1) + sum(n_intr) - 1       # + camera index (not the reference)
    board_at = shift_at + 1 + (n_cam - 1 if motion is not None else 0)
    obs = [(ci, index[v], detections[c][v]) for ci, c in enumerate(names)
           for v in views if v in detections[c]]
    rates = [motion[names[ci]][views[vi]].reshape(-1) if motion is not None and ci else None
             for ci, vi, _ in obs]
    x0 = [_vector(in_ref[c]) for c in names[1:]]
    for ci, c in enumerate(names):
        if n_intr[ci]:
            K, D = intrinsics[c].K, intrinsics[c].D
            x0.append(np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], D[:free[ci]]]))
    if motion is not None:
        x0.append(np.zeros(n_cam - 1))
    x0 = np.concatenate(x0 + [_vector(boards[v]) for v in views])
    sizes = [2 * len(det.ids) for *_, det in obs]
    starts = np.concatenate([[0], np.cumsum(sizes)])

    def lenses(x):
        out = []
        for ci, c in enumerate(names):
            K, D = intrinsics[c].K.copy(), intrinsics[c].D.astype(np.float64).copy()
            if n_intr[ci]:
                q = x[intr_at[ci]:intr_at[ci] + n_intr[ci]]
                K[0, 0], K[1, 1], K[0, 2], K[1, 2] = q[:4]
                D[:free[ci]] = q[4:]
            out.append((K, D))
        return out

    def project(x, with_jacobian: bool):
        """Every residual and, with_jacobian, the sparse Jacobian's (rows, cols, values)."""
        lens = lenses(x)
        res, rows, cols, vals = [], [], [], []
        for (ci, vi, det), rate, row in zip(obs, rates, starts):
            at = board_at + 6 * vi
            rb, tb = x[at:at + 3], x[at + 3:at + 6]
            if ci == 0:
                r, t = rb, tb
            else:
                rc, tc = x[pose_at[ci]:pose_at[ci] + 3], x[pose_at[ci] + 3:pose_at[ci] + 6]
                r, t, *d = cv2.composeRT(rb, tb, rc, tc)     # camera after board
            px, J = cv2.projectPoints(objects[det.ids], r, t, *lens[ci])
            seen = det.points.reshape(-1)
            res.append(px.reshape(-1) - (seen if rate is None else seen + rate * x[shift_at + ci]))
            if not with_jacobian:
                continue
            J_pose = J[:, :6]                                  # by the composed r, t
            blocks = []
            if ci == 0:
                blocks.append((board_at + 6 * vi, J_pose))
            else:
                dr_drb, dr_dtb, dr_drc, dr_dtc, dt_drb, dt_dtb, dt_drc, dt_dtc = d
                by_board = np.block([[dr_drb, dr_dtb], [dt_drb, dt_dtb]])
                by_camera = np.block([[dr_drc, dr_dtc], [dt_drc, dt_dtc]])
                blocks += [(board_at + 6 * vi, J_pose @ by_board),
                           (pose_at[ci], J_pose @ by_camera)]
            if n_intr[ci]:
                blocks.append((intr_at[ci], np.hstack([J[:, 6:10], J[:, 10:10 + free[ci]]])))
            if rate is not None:
                blocks.append((shift_at + ci, -rate[:, None]))
            n = J.shape[0]
            for col, block in blocks:
                r_idx, c_idx = np.meshgrid(np.arange(row, row + n),
                                           col + np.arange(block.shape[1]), indexing='ij')
                rows.append(r_idx.ravel())
                cols.append(c_idx.ravel())
                vals.append(block.ravel())
        fun = np.concatenate(res)
        return fun, (rows, cols, vals)

    def jacobian(x):
        _, (rows, cols, vals) = project(x, True)
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(starts[-1], x0.size))

    # lsmr solved to machine precision: its default, inexact steps take hundreds of
    # iterations on this problem, exact ones a few tens
    fit = least_squares(lambda x: project(x, False)[0], x0, jac=jacobian, method='trf',
                        x_scale='jac', loss='soft_l1', f_scale=1.0,
                        tr_options={'atol': 1e-12, 'btol': 1e-12})
    x = fit.x
    cams = [np.eye(4)] + [_matrix(x[k:k + 3], x[k + 3:k + 6]) for k in pose_at[1:]]
    bds = [_matrix(x[board_at + 6 * k:board_at + 6 * k + 3],
                   x[board_at + 6 * k + 3:board_at + 6 * k + 6]) for k in range(len(views))]
    refined = {c: replace(intrinsics[c], K=K, D=D) for c, (K, D) in zip(names, lenses(x))}
    errors: dict[str, list] = {c: [] for c in names}
    for (ci, _, _), row, size in zip(obs, starts, sizes):
        errors[names[ci]].append(np.linalg.norm(fit.fun[row:row + size].reshape(-1, 2), axis=1))
    shifts = [0.0] + ([float(s) for s in x[shift_at + 1:shift_at + n_cam]]
                      if motion is not None else [0.0] * (n_cam - 1))
    return (dict(zip(names, cams)), refined, dict(zip(views, bds)),
            {c: np.concatenate(e) for c, e in errors.items()}, shifts)


def _vector(T: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]])


def _matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0], tvec
    return T


def neighbour_errors(board: Board, cameras: list[Camera],
                     detections: list[dict[str, Detection]], views: list[str]) -> np.ndarray:
    """A check of a calibrated rig against the board itself: its points in `views`
    triangulated (uav_vs.vision.triangulation, linear, by every camera that sees them)
    and the distance of each pair of grid neighbours minus their true spacing
    (board.square), m. `detections[k]` are camera k's, by view."""
    objects = board.object_points()
    gap = np.linalg.norm(objects[:, None] - objects[None], axis=2)
    pairs = np.argwhere(np.triu(np.isclose(gap, board.square)))
    errors = []
    for view in views:
        pixels = np.full((len(cameras), len(objects), 2), np.nan)
        for k, seen in enumerate(detections):
            if view in seen:
                pixels[k, seen[view].ids] = seen[view].points
        points = triangulate(cameras, pixels, max_reproj_px=math.inf).points
        errors += [np.linalg.norm(points[i] - points[j]) - board.square for i, j in pairs
                   if np.isfinite(points[[i, j]]).all()]
    return np.array(errors)
