"""How uncertain the ground station's pose is, from what its frame sets show (section 3.1.1,
eq 24-26 linearised about their solution).

1. Pixel noise. A landmark seen by k cameras fits 2k pixel coordinates with 3 unknowns
   (eq 24-25), so its squared reprojection errors sum to sigma^2 chi^2(2k - 3) on average:
   `PixelNoise` pools them over the recent frame sets (exponential forgetting) into one
   sigma per station, never below a floor (what the centroids cannot do better than).
2. Landmark positions. Each triangulated landmark X has covariance sigma^2 (J^T J)^-1,
   J the 2k x 3 Jacobian of its pixels in the cameras that saw it (the pinhole of K, R, t
   at X; the lens distortion, a few percent of the scale, is left out of J).
3. Pose. The fit of eq 26 (or its rigid form) is, to first order, linear in the landmark
   positions: with a_i = R (l_i - l_mean) the rotated, centred layout,
       d theta = M^-1 sum_i a_i x d X_i,   M = sum_i (|a_i|^2 I - a_i a_i^T)
   (about z alone for eq 26: d yaw = sum_i (a_i x d X_i)_z / sum_i |a_i,xy|^2), and
       d p = mean_i d X_i + (R l_mean) x d theta.
   The pose covariance is G diag(cov X_i) G^T with G that linear map.
4. What the residuals cannot see: a bias every camera shares (the rig's calibration, the
   landmarks' survey, a lit sphere's centroid off its centre in every view), added to the
   position as `bias_sigma` per axis.
"""
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from uav_vs.vision.body_pose import BodyPose
from uav_vs.vision.camera import Camera
from uav_vs.vision.triangulation import Triangulation

UNKNOWN = 1e6    # the variance of a rotation the fit does not estimate (roll, pitch of eq 26)


@dataclass
class PixelNoise:
    """The centroids' pixel noise pooled from the triangulations' residuals (step 1)."""

    floor: float = 0.3            # px: the sigma is never taken smaller
    memory: float = 0.95          # weight of the past at each frame set
    _squares: float = field(default=0.0, init=False)
    _dof: float = field(default=0.0, init=False)

    def update(self, tri: Triangulation) -> float:
        """Pool one frame set's residuals; returns the current sigma, px."""
        k = tri.n_views.astype(float)
        use = tri.inlier & (k >= 2)
        squares = float(np.sum(k[use] * tri.reproj_px[use] ** 2))   # reproj_px: RMS per camera
        self._squares = self.memory * self._squares + squares
        self._dof = self.memory * self._dof + float(np.sum(2 * k[use] - 3))
        return self.sigma

    @property
    def sigma(self) -> float:
        if self._dof <= 0:
            return self.floor
        return max(self.floor, float(np.sqrt(self._squares / self._dof)))


def landmark_covariances(cameras: Sequence[Camera], tri: Triangulation, sigma_px: float
                         ) -> np.ndarray:
    """(n_landmarks, 3, 3) covariance of each triangulated landmark (step 2); NaN where
    it was not triangulated."""
    n = tri.points.shape[0]
    info = np.zeros((n, 3, 3))
    for k, cam in enumerate(cameras):
        seen = tri.used[k] & np.all(np.isfinite(tri.points), axis=1)
        if not seen.any():
            continue
        Xc = tri.points[seen] @ cam.R.T + cam.t
        z = Xc[:, 2]
        rows = []
        for f, axis in ((cam.K[0, 0], 0), (cam.K[1, 1], 1)):
            rows.append(f / z[:, None] * (cam.R[axis] - (Xc[:, axis] / z)[:, None] * cam.R[2]))
        J = np.stack(rows, axis=1)                       # (m, 2, 3)
        info[seen] += np.einsum('mri,mrj->mij', J, J)
    cov = np.full((n, 3, 3), np.nan)
    solved = np.all(np.isfinite(tri.points), axis=1) & (tri.n_views >= 2)
    if solved.any():
        cov[solved] = sigma_px ** 2 * np.linalg.inv(info[solved])
    return cov


def pose_covariance(layout: np.ndarray, pose: BodyPose, landmark_cov: np.ndarray,
                    yaw_only: bool = True, bias_sigma: float = 0.0) -> np.ndarray:
    """6x6 covariance of the pose (x, y, z, rotation about x, y, z; ROS order) from the
    landmarks' (step 3), plus bias_sigma^2 (m^2) on each position axis (step 4). With
    `yaw_only` (eq 26) roll and pitch are not estimated: their variance is UNKNOWN."""
    used = np.all(np.isfinite(landmark_cov.reshape(len(landmark_cov), -1)), axis=1)
    used &= np.isfinite(pose.residuals)
    lay = np.asarray(layout, float)[used]
    cov_x = landmark_cov[used]
    n = len(lay)
    mean = lay.mean(axis=0)
    a = (lay - mean) @ pose.R.T                         # rotated, centred layout
    # d theta = M^-1 sum a_i x dX_i: rows of [a_i]x stacked as (3, 3n)
    cross = np.zeros((n, 3, 3))
    cross[:, 0, 1], cross[:, 0, 2] = -a[:, 2], a[:, 1]
    cross[:, 1, 0], cross[:, 1, 2] = a[:, 2], -a[:, 0]
    cross[:, 2, 0], cross[:, 2, 1] = -a[:, 1], a[:, 0]
    if yaw_only:
        spread = np.sum(a[:, :2] ** 2)
        G_rot = np.zeros((3, 3 * n))
        G_rot[2] = np.concatenate(cross[:, 2]) / spread
    else:
        M = np.einsum('ni,ni->', a, a) * np.eye(3) - a.T @ a
        G_rot = np.linalg.solve(M, np.concatenate(cross, axis=1))
    lever = pose.R @ mean
    lever_x = np.array([[0, -lever[2], lever[1]], [lever[2], 0, -lever[0]],
                        [-lever[1], lever[0], 0]])
    G_pos = np.tile(np.eye(3) / n, n) + lever_x @ G_rot
    G = np.vstack([G_pos, G_rot])
    Gi = G.reshape(6, n, 3)                            # G's block for each landmark
    cov = np.einsum('anj,njk,bnk->ab', Gi, cov_x, Gi)
    cov[:3, :3] += bias_sigma ** 2 * np.eye(3)
    if yaw_only:
        cov[3, 3] = cov[4, 4] = UNKNOWN
    return cov
