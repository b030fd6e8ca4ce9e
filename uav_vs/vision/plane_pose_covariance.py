"""How uncertain the onboard pose is (section 4.1, the refined pose of eq 27 linearised
about its solution), for pose fusion (onboard/pose_cov).

1. The fit. The refined pose minimises the inliers' reprojection errors
   (plane_geometry.refine_plane_pose); to first order its world-to-camera perturbation
   (w, dt) (R <- exp([w]x) R, t <- t + dt) has covariance sigma^2 (J^T J)^-1, J the
   2N x 6 Jacobian of the inliers' pixels (plane_geometry.linearise), sigma the pixel
   noise the residuals show, sqrt(sum r^2 / (2N - 6)), never below a floor (what L-K
   tracks cannot do better than).
2. To the vehicle in the world. With R_wc = R^T, the world-frame rotation of the body is
   phi = -R^T w, and its position p moves by dp = -[p]x phi - R^T dt (the camera's offset
   on the body turns with it), whatever the camera's mounting.
3. Drift. A re-anchor maps new features onto the plane through the pose of that frame
   (plane_pose.PlanePoseEstimator), so they carry its error from then on: the map's
   covariance grows by the fit covariance of every frame made a keyframe (a random walk),
   and every later pose carries it beside its own fit's. That is a bound, not the
   figure: the tracks that survive a re-anchor keep their plane points, so a later pose
   moves by only part of that error (on the sample flight the errors came out 0.17-0.66
   of the predicted standard deviations; counting only the new features' share s, as
   s^2 times the fit, understated them up to 2.7 times).
"""
import numpy as np

from uav_vs.vision.plane_geometry import linearise


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x, the cross-product matrix."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def fit_covariance(K: np.ndarray, R: np.ndarray, t: np.ndarray, plane_xyz: np.ndarray,
                   pixels: np.ndarray, position: np.ndarray, floor_px: float
                   ) -> tuple[np.ndarray, float]:
    """6x6 covariance (x, y, z, rotation about world x, y, z; ROS order) of the body
    pose at world `position` from the refined world-to-camera R, t and its inliers
    (plane points (N, 3), ideal pixels (N, 2)), and the pixel sigma used (steps 1-2)."""
    r, J = linearise(K, R, t, np.asarray(plane_xyz, float), np.asarray(pixels, float))
    dof = len(r) - 6
    sigma = max(floor_px, float(np.sqrt(r @ r / dof))) if dof > 0 else floor_px
    camera_cov = sigma ** 2 * np.linalg.inv(J.T @ J)
    G = np.zeros((6, 6))
    G[:3, :3] = skew(np.asarray(position, float)) @ R.T        # dp/dw
    G[:3, 3:] = -R.T                                           # dp/dt
    G[3:, :3] = -R.T                                           # dphi/dw
    return G @ camera_cov @ G.T, sigma
