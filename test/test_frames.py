"""ENU/FLU <-> NED/FRD conversions against hand-written cases and scipy rotations.

Each literal case is one of the mix-ups MAVROS users report (east becoming north,
up becoming up in NED, left becoming right, yaw measured from the wrong axis or
turning the wrong way); scipy's Rotation is the independent reference for attitude.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uav_vs.autopilot import frames

RNG = np.random.default_rng(7)


@pytest.mark.parametrize('enu, ned', [
    ([1, 0, 0], [0, 1, 0]),    # east is NED +y
    ([0, 1, 0], [1, 0, 0]),    # north is NED +x
    ([0, 0, 1], [0, 0, -1]),   # up is NED -z
    ([2, -3, 0.5], [-3, 2, -0.5]),
])
def test_world_vectors(enu, ned):
    assert np.allclose(frames.enu_to_ned(enu), ned)
    assert np.allclose(frames.ned_to_enu(ned), enu)


@pytest.mark.parametrize('flu, frd', [
    ([1, 0, 0], [1, 0, 0]),    # forward stays forward
    ([0, 1, 0], [0, -1, 0]),   # left is FRD -y (right negative)
    ([0, 0, 1], [0, 0, -1]),   # up is FRD -z
])
def test_body_vectors(flu, frd):
    assert np.allclose(frames.flu_to_frd(flu), frd)
    assert np.allclose(frames.frd_to_flu(frd), flu)


@pytest.mark.parametrize('yaw_enu, yaw_ned', [
    (0.0, np.pi / 2),          # facing east
    (np.pi / 2, 0.0),          # facing north
    (np.pi, -np.pi / 2),       # facing west
    (-np.pi / 2, -np.pi),      # facing south (wrapped to [-pi, pi))
    (0.3, np.pi / 2 - 0.3),    # turning CCW in ENU is turning CW-negative in NED
])
def test_yaw(yaw_enu, yaw_ned):
    assert np.isclose(frames.yaw_enu_to_ned(yaw_enu), yaw_ned)
    assert np.isclose(frames.wrap_angle(frames.yaw_ned_to_enu(yaw_ned) - yaw_enu), 0.0)


def test_yaw_rate_sign():
    # a left (CCW seen from above) turn is positive about z-up and negative about z-down
    assert frames.yaw_rate_enu_to_ned(0.5) == -0.5
    assert frames.yaw_rate_ned_to_enu(-0.5) == 0.5


def test_round_trips_vectorised():
    v = RNG.normal(size=(100, 3))
    assert np.allclose(frames.ned_to_enu(frames.enu_to_ned(v)), v)
    assert np.allclose(frames.frd_to_flu(frames.flu_to_frd(v)), v)
    yaw = RNG.uniform(-np.pi, np.pi, 100)
    assert np.allclose(frames.wrap_angle(frames.yaw_ned_to_enu(frames.yaw_enu_to_ned(yaw)) - yaw), 0)


def test_conversion_matrices_are_rotations():
    for r in (frames.R_ENU_NED, frames.R_FLU_FRD):
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
    assert np.allclose(Rotation.from_quat(frames.Q_ENU_NED).as_matrix(), frames.R_ENU_NED)


def test_attitude_matches_rotation_matrices():
    rpy = RNG.uniform([-1, -1.4, -np.pi], [1, 1.4, np.pi], size=(200, 3))
    q = frames.attitude_ned_to_enu(*rpy.T)
    # independent: R_enu_flu = R_ENU_NED @ R_ned_frd @ R_FRD_FLU with scipy's ZYX Euler
    r_ned_frd = Rotation.from_euler('ZYX', rpy[:, ::-1]).as_matrix()
    expected = frames.R_ENU_NED @ r_ned_frd @ frames.R_FLU_FRD
    assert np.allclose(Rotation.from_quat(q).as_matrix(), expected)
    assert (q[:, 3] >= 0).all()
    back = np.stack(frames.attitude_enu_to_ned(q), axis=-1)
    assert np.allclose(back, rpy)


def test_level_headings():
    # NED yaw 0 (nose north): base_link forward is world +y (north), left is world -x (west)
    r = Rotation.from_quat(frames.attitude_ned_to_enu(0.0, 0.0, 0.0)).as_matrix()
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(r @ [0, 1, 0], [-1, 0, 0])
    assert np.allclose(r @ [0, 0, 1], [0, 0, 1])
    # NED yaw +90 deg (nose east): ENU heading 0
    q = frames.attitude_ned_to_enu(0.0, 0.0, np.pi / 2)
    assert np.isclose(frames.yaw_of(q), 0.0)
    # positive NED roll (right wing down): base_link left axis tilts up
    r = Rotation.from_quat(frames.attitude_ned_to_enu(0.2, 0.0, 0.0)).as_matrix()
    assert (r @ [0, 1, 0])[2] > 0.19


def test_euler_quat_round_trip_against_scipy():
    rpy = RNG.uniform([-1, -1.4, -np.pi], [1, 1.4, np.pi], size=(50, 3))
    q = frames.euler_to_quat(*rpy.T)
    assert np.allclose(np.abs(np.sum(q * Rotation.from_euler('ZYX', rpy[:, ::-1]).as_quat(), axis=1)), 1)
    assert np.allclose(np.stack(frames.quat_to_euler(q), axis=-1), rpy)
    a, b = Rotation.random(10, random_state=1), Rotation.random(10, random_state=2)
    assert np.allclose(Rotation.from_quat(frames.quat_multiply(a.as_quat(), b.as_quat())).as_matrix(),
                       (a * b).as_matrix())


def test_body_to_world_by_heading():
    # heading north (ENU yaw pi/2): forward is north, left is west
    assert np.allclose(frames.body_to_world([1, 0, 0.5], np.pi / 2), [0, 1, 0.5])
    assert np.allclose(frames.body_to_world([0, 1, 0], np.pi / 2), [-1, 0, 0])
    yaw = RNG.uniform(-np.pi, np.pi)
    q = frames.attitude_ned_to_enu(0.0, 0.0, frames.yaw_enu_to_ned(yaw))
    v = RNG.normal(size=3)
    assert np.allclose(frames.body_to_world(v, yaw), Rotation.from_quat(q).apply(v))


def test_pose_covariance():
    # variance along east becomes variance along NED y; an east-up correlation flips sign
    cov = np.zeros((6, 6))
    cov[0, 0], cov[2, 2], cov[0, 2], cov[2, 0] = 4.0, 0.5, 0.25, 0.25
    cov[5, 5], cov[3, 4], cov[4, 3] = 0.01, 0.002, 0.002
    ned = frames.pose_covariance_enu_to_ned(cov)
    assert ned[1, 1] == 4.0 and ned[0, 0] == 0.0 and ned[2, 2] == 0.5
    assert ned[1, 2] == -0.25
    assert ned[5, 5] == 0.01 and ned[3, 4] == -0.002
    assert np.allclose(ned, ned.T) and np.allclose(np.linalg.eigvalsh(ned), np.linalg.eigvalsh(cov))


def test_covariance_from_mavlinks_upper_triangle():
    # MAVLink: the first six entries are row 0 (columns 0..5), the next five row 1 (1..5), ...
    upper = np.arange(1.0, 22.0)
    cov = frames.covariance_from_upper(upper)
    k = 0
    for row in range(6):
        for col in range(row, 6):
            assert cov[row, col] == cov[col, row] == upper[k]
            k += 1
    assert frames.covariance_from_upper([np.nan] + [1.0] * 20) is None     # unknown
    partial = [np.nan] * 21
    partial[0], partial[6], partial[20] = 0.5, 0.25, 0.125              # PX4: diagonals only
    assert np.array_equal(frames.covariance_from_upper(partial),
                          np.diag([0.5, 0.25, 0.0, 0.0, 0.0, 0.125]))


@pytest.mark.parametrize('yaw_enu, expected', [
    (np.pi / 2, [1.0, 2.0, 3.0]),     # facing north: forward is north, left is west
    (0.0, [2.0, 1.0, 3.0]),           # facing east: forward is east, left is north
])
def test_world_velocity_covariance_seen_in_the_body(yaw_enu, expected):
    ned = np.diag([1.0, 2.0, 3.0])    # variances north, east, down
    q = Rotation.from_euler('z', yaw_enu).as_quat()
    flu = frames.velocity_covariance_to_flu(ned, 'local_ned', q)
    assert np.allclose(flu, np.diag(expected))
    assert np.allclose(frames.velocity_covariance_to_flu(ned, 'body_frd', q), ned)


def test_velocity_covariance_against_scipy_at_any_attitude():
    a = RNG.normal(size=(3, 3))
    ned = a @ a.T
    q = Rotation.random(random_state=3).as_quat()               # base_link FLU in world ENU
    r_flu_ned = Rotation.from_quat(q).as_matrix().T @ frames.R_ENU_NED
    assert np.allclose(frames.velocity_covariance_to_flu(ned, 'local_ned', q),
                       r_flu_ned @ ned @ r_flu_ned.T)
