"""ENU/FLU <-> NED/FRD: the one module where ROS frames meet MAVLink frames.

ROS (REP-103/105): `world` is ENU (x east, y north, z up); `base_link` is FLU
(x forward, y left, z up). MAVLink: the local frame is NED (x north, y east, z down)
and the body frame FRD (x forward, y right, z down) -- the chapter's helicopter frame
X_h forward, Z_h down (section 3.0.2, eq 17) is FRD as well.

    ENU -> NED:  (e, n, u) -> (n, e, -u)      swap x/y, negate z
    FLU -> FRD:  (f, l, u) -> (f, -l, -u)     negate y and z
    yaw:         ENU 0 = east, counter-clockwise;  NED 0 = north, clockwise
                 yaw_ned = pi/2 - yaw_enu
    z rates:     a turn rate about z-up is minus the rate about z-down

Both maps are their own inverse, so each pair of functions below is one formula under
two names: call sites then say which way they go. Quaternions are (x, y, z, w) as in
geometry_msgs; an attitude quaternion q_a_b rotates vectors from frame b into frame a.
Every function takes arrays of shape (..., 3) (or (..., 4)) as well as single values.
"""
import numpy as np

# Rotation taking NED components to ENU components (and back: it is an involution).
# As a rotation: 180 deg about the axis (1, 1, 0)/sqrt(2).
R_ENU_NED = np.array([[0.0, 1.0, 0.0],
                      [1.0, 0.0, 0.0],
                      [0.0, 0.0, -1.0]])
# Rotation taking FRD components to FLU components (and back): 180 deg about x.
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])

_S = np.sqrt(0.5)
Q_ENU_NED = np.array([_S, _S, 0.0, 0.0])   # quaternion of R_ENU_NED
Q_FRD_FLU = np.array([1.0, 0.0, 0.0, 0.0])  # quaternion of R_FLU_FRD (its own inverse)
_SWAP = [1, 0, 2]
_NEG_Z = np.array([1.0, 1.0, -1.0])
_NEG_YZ = np.array([1.0, -1.0, -1.0])


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """World ENU position/velocity -> MAVLink local NED (north = ENU y, east = ENU x)."""
    return np.asarray(v, dtype=float)[..., _SWAP] * _NEG_Z


def ned_to_enu(v: np.ndarray) -> np.ndarray:
    """MAVLink local NED position/velocity -> world ENU."""
    return np.asarray(v, dtype=float)[..., _SWAP] * _NEG_Z


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """Body FLU vector (velocity, angular velocity) -> MAVLink body FRD."""
    return np.asarray(v, dtype=float) * _NEG_YZ


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    """MAVLink body FRD vector -> body FLU."""
    return np.asarray(v, dtype=float) * _NEG_YZ


def wrap_angle(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def yaw_enu_to_ned(yaw):
    """Heading: ENU (0 = east, CCW positive) -> NED (0 = north, CW positive)."""
    return wrap_angle(np.pi / 2 - np.asarray(yaw, dtype=float))


def yaw_ned_to_enu(yaw):
    """Heading: NED (0 = north, CW positive) -> ENU (0 = east, CCW positive)."""
    return wrap_angle(np.pi / 2 - np.asarray(yaw, dtype=float))


def yaw_rate_enu_to_ned(rate):
    """Turn rate about world z-up (or body z-up, FLU) -> about z-down (NED, FRD)."""
    return -np.asarray(rate, dtype=float)


def yaw_rate_ned_to_enu(rate):
    """Turn rate about z-down (NED, FRD) -> about z-up (ENU, FLU)."""
    return -np.asarray(rate, dtype=float)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (x, y, z, w) quaternions."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=float), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=float), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def euler_to_quat(roll, pitch, yaw) -> np.ndarray:
    """Aerospace Z-Y-X Euler angles (yaw, then pitch, then roll) -> (x, y, z, w)."""
    hr, hp, hy = (np.asarray(a, dtype=float) / 2 for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(hr), np.sin(hr), np.cos(hp), np.sin(hp), np.cos(hy), np.sin(hy)
    return np.stack([sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy], axis=-1)


def quat_to_euler(q: np.ndarray) -> tuple:
    """(x, y, z, w) -> aerospace Z-Y-X Euler angles (roll, pitch, yaw)."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_ned_to_enu(q_ned_frd: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) of the FRD body in NED -> of base_link FLU in world ENU.

    q_enu_flu = q_enu_ned * q_ned_frd * q_frd_flu, sign chosen so that w >= 0.
    """
    q = quat_multiply(quat_multiply(Q_ENU_NED, q_ned_frd), Q_FRD_FLU)
    return q * np.where(q[..., 3:] < 0, -1.0, 1.0)


def attitude_ned_to_enu(roll, pitch, yaw) -> np.ndarray:
    """MAVLink ATTITUDE (FRD body in NED) -> quaternion of base_link FLU in world ENU."""
    return quat_ned_to_enu(euler_to_quat(roll, pitch, yaw))


def attitude_enu_to_ned(q_enu_flu: np.ndarray) -> tuple:
    """Quaternion of base_link FLU in world ENU -> (roll, pitch, yaw) of FRD body in NED."""
    q_ned_frd = quat_multiply(quat_multiply(Q_ENU_NED, q_enu_flu), Q_FRD_FLU)
    return quat_to_euler(q_ned_frd)


def yaw_of(q_enu_flu: np.ndarray):
    """ENU heading of base_link (angle of its forward axis from east, CCW)."""
    x, y, z, w = np.moveaxis(np.asarray(q_enu_flu, dtype=float), -1, 0)
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def body_to_world(v_flu: np.ndarray, yaw_enu) -> np.ndarray:
    """Rotate an FLU vector into ENU by heading only (roll and pitch taken as level).

    This is how both autopilots read body-frame velocity setpoints.
    """
    v = np.asarray(v_flu, dtype=float)
    c, s = np.cos(yaw_enu), np.sin(yaw_enu)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], axis=-1)


def pose_covariance_enu_to_ned(cov: np.ndarray) -> np.ndarray:
    """6x6 pose covariance (x, y, z, rot x, rot y, rot z) from ENU/FLU to NED/FRD.

    Position rows use ENU -> NED, rotation rows FLU -> FRD (small rotations about the
    body axes, i.e. roll, pitch, yaw errors): C' = J C J^T, J = diag(R_ENU_NED, R_FLU_FRD).
    """
    j = np.zeros((6, 6))
    j[:3, :3] = R_ENU_NED
    j[3:, 3:] = R_FLU_FRD
    return j @ np.asarray(cov, dtype=float) @ j.T


def pose_covariance_ned_to_enu(cov: np.ndarray) -> np.ndarray:
    """6x6 pose covariance from NED/FRD to ENU/FLU: the same J C J^T, J being an involution."""
    return pose_covariance_enu_to_ned(cov)


def covariance_from_upper(upper) -> np.ndarray | None:
    """MAVLink's 21-float upper right triangle (row-major, ODOMETRY) as a symmetric 6x6
    matrix; None when its first element is NaN (unknown); other NaN entries (not
    reported) become 0."""
    upper = np.asarray(upper, dtype=float)
    if upper.shape != (21,) or np.isnan(upper[0]):
        return None
    cov = np.zeros((6, 6))
    cov[np.triu_indices(6)] = np.nan_to_num(upper, nan=0.0)
    return cov + np.triu(cov, 1).T


def velocity_covariance_to_flu(cov: np.ndarray, frame: str, q_enu_flu: np.ndarray) -> np.ndarray:
    """3x3 linear velocity covariance in base_link FLU, from MAVLink's `frame`: 'local_ned'
    (world NED axes, rotated into the body with the attitude q_enu_flu) or 'body_frd'."""
    if frame == 'body_frd':
        return R_FLU_FRD @ cov @ R_FLU_FRD.T
    x, y, z, w = np.asarray(q_enu_flu, dtype=float)
    r_enu_flu = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    to_flu = r_enu_flu.T @ R_ENU_NED
    return to_flu @ cov @ to_flu.T
