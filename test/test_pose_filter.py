"""The pose filter (uav_vs.control.pose_filter) against analytic motion: a vehicle at
constant velocity and yaw rate, measured by noisy sources at their own rates, late,
wrong or not at all."""
import math

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from uav_vs.control.controllers import wrap_angle
from uav_vs.control.pose_filter import (FilterParams, PoseFilter, odometry_measurement,
                                        pose_measurement, rot_z)

VELOCITY = np.array([0.5, -0.3, 0.1])       # m/s, world
YAW_RATE = 0.2                              # rad/s
START = np.array([1.0, 2.0, 1.5])
CALM = FilterParams(accel_sigma=0.3, yaw_accel_sigma=0.1)    # the truth does not accelerate


def truth(t: float, yaw0: float = 0.3, rate: float = YAW_RATE) -> tuple[np.ndarray, float]:
    return START + VELOCITY * t, wrap_angle(yaw0 + rate * t)


def poses(source: str, rate_hz: float, sigma: float, yaw_sigma: float, duration: float,
          rng, offset: float = 0.0, **motion) -> list:
    out = []
    for t in np.arange(offset, duration, 1.0 / rate_hz):
        p, yaw = truth(t, **motion)
        cov = np.diag([sigma ** 2] * 3 + [yaw_sigma ** 2])
        out.append(pose_measurement(source, float(t), p + rng.normal(0, sigma, 3),
                                    wrap_angle(yaw + rng.normal(0, yaw_sigma)), cov))
    return out


def run(measurements, params=CALM) -> PoseFilter:
    f = PoseFilter(params)
    for m in measurements:
        f.add(m)
    return f


def test_constant_velocity_is_tracked_and_its_covariance_is_honest():
    """Velocity learnt from positions alone; the position error's normalised square
    (NEES, 3 dof) averages about 3, as a consistent filter's does."""
    rng = np.random.default_rng(1)
    f = PoseFilter(CALM)
    nees, errors = [], []
    for m in poses('ground', 30, 0.03, 0.02, 10.0, rng):
        f.add(m)
        if m.stamp > 2.0:
            est = f.estimate(m.stamp)
            e = est.position - truth(m.stamp)[0]
            errors.append(np.linalg.norm(e))
            nees.append(e @ np.linalg.solve(est.P[:3, :3], e))
    est = f.estimate(10.0)
    assert np.linalg.norm(est.velocity - VELOCITY) < 0.05
    assert abs(est.x[7] - YAW_RATE) < 0.02
    assert np.sqrt(np.mean(np.square(errors))) < 0.03        # the measurements' own: 0.052
    assert 1.5 < np.mean(nees) < 5.0, np.mean(nees)


def test_a_late_measurement_weighs_as_if_it_had_come_on_time():
    """The ground poses reach the filter 0.1 s after the onboard ones of the same time:
    the estimate is the one of every measurement in stamp order. (The first to arrive
    starts the filter: the ground's start after it.)"""
    rng = np.random.default_rng(2)
    ground = poses('ground', 30, 0.03, 0.02, 5.0, rng, offset=0.02)
    onboard = poses('onboard', 20, 0.04, 0.03, 5.0, rng, offset=0.013)
    in_order = run(sorted(ground + onboard, key=lambda m: m.stamp))
    arrival = sorted([(m.stamp + 0.1, m) for m in ground] + [(m.stamp, m) for m in onboard],
                     key=lambda pair: pair[0])
    late = run([m for _, m in arrival])
    a, b = in_order.estimate(5.0), late.estimate(5.0)
    assert np.allclose(a.x, b.x, atol=1e-9) and np.allclose(a.P, b.P, atol=1e-12)
    assert late.counts['ground'].applied == len(ground)


def test_outliers_are_refused_and_counted():
    """One pose in ten 1.5 m off: every one refused by the gate, none of the others, and
    the estimate is the one without them."""
    rng = np.random.default_rng(3)
    good = poses('ground', 30, 0.03, 0.02, 6.0, rng)
    wrong = [pose_measurement('ground', m.stamp + 0.005, m.z[:3] + [1.5, 0.0, 0.0], m.z[3], m.R)
             for m in good[10::10]]
    f = run(sorted(good + wrong, key=lambda m: m.stamp))
    assert f.counts['ground'].gated == len(wrong) and f.counts['ground'].applied == len(good)
    assert np.allclose(f.estimate(6.0).x, run(good).estimate(6.0).x, atol=1e-12)


def test_a_source_gone_for_3_s_grows_the_covariance_and_the_estimate_holds():
    rng = np.random.default_rng(4)
    ms = [m for m in poses('ground', 30, 0.03, 0.02, 8.0, rng) if not 3.0 < m.stamp < 6.0]
    f = run([m for m in ms if m.stamp <= 3.0])
    sigmas = [math.sqrt(np.trace(f.estimate(t).P[:3, :3])) for t in np.arange(3.0, 6.0, 0.1)]
    assert all(b > a for a, b in zip(sigmas, sigmas[1:])) and sigmas[-1] > 5 * sigmas[0]
    gap = f.estimate(6.0)
    error = np.linalg.norm(gap.position - truth(6.0)[0])
    assert error < 0.1 and error < 3 * sigmas[-1]
    for m in ms:
        if m.stamp >= 6.0:
            f.add(m)
    back = f.estimate(8.0)
    assert np.trace(back.P[:3, :3]) < np.trace(gap.P[:3, :3]) / 20


def test_two_sources_give_a_better_estimate_than_either():
    """Ground (3 cm) and onboard (4 cm): the fused position's RMSE is under 0.7 x the
    better source's own."""
    rng = np.random.default_rng(5)
    ground = poses('ground', 30, 0.03, 0.02, 10.0, rng)
    onboard = poses('onboard', 30, 0.04, 0.03, 10.0, rng, offset=0.017)
    f = PoseFilter(CALM)
    fused, raw = [], []
    for m in sorted(ground + onboard, key=lambda m: m.stamp):
        f.add(m)
        if m.stamp > 1.0:
            p = truth(m.stamp)[0]
            fused.append(np.linalg.norm(f.estimate(m.stamp).position - p))
            if m.source == 'ground':
                raw.append(np.linalg.norm(m.z[:3] - p))
    rmse = lambda e: np.sqrt(np.mean(np.square(e)))      # noqa: E731
    assert rmse(fused) < 0.7 * rmse(raw), (rmse(fused), rmse(raw))


def test_odometry_in_base_link_gives_the_world_velocity():
    """The autopilot's velocity is in base_link (FLU): turned by the yaw, it is the world
    velocity the filter holds (h(x) = Rz(yaw)^T v, the filter's non-linear part)."""
    rng = np.random.default_rng(6)
    f = PoseFilter(CALM)
    for t in np.arange(0.0, 4.0, 0.1):
        p, yaw = truth(t, yaw0=2.0)
        v_body = rot_z(yaw).T @ VELOCITY
        cov = np.diag([0.5 ** 2] * 3 + [0.02 ** 2] + [0.01 ** 2] * 3 + [0.01 ** 2])
        f.add(odometry_measurement('autopilot', float(t), p + rng.normal(0, 0.5, 3),
                                   yaw + rng.normal(0, 0.02), v_body + rng.normal(0, 0.01, 3),
                                   YAW_RATE + rng.normal(0, 0.01), cov))
    est = f.estimate(4.0)
    assert np.linalg.norm(est.velocity - VELOCITY) < 0.03, est.velocity


@pytest.mark.parametrize('yaw0', [3.0, -3.0])
def test_yaw_across_pi_stays_continuous(yaw0):
    rng = np.random.default_rng(7)
    rate = 0.5 if yaw0 > 0 else -0.5
    f = PoseFilter(CALM)
    worst = 0.0
    for m in poses('ground', 30, 0.03, 0.02, 2.0, rng, yaw0=yaw0, rate=rate):
        f.add(m)
        error = wrap_angle(f.estimate(m.stamp).yaw - truth(m.stamp, yaw0, rate)[1])
        worst = max(worst, abs(error))
    assert worst < 0.05 and abs(f.estimate(2.0).x[7] - rate) < 0.1


def test_a_measurement_older_than_the_history_is_counted_not_applied():
    rng = np.random.default_rng(8)
    f = run(poses('ground', 30, 0.03, 0.02, 3.0, rng))
    before = f.estimate(3.0)
    old = pose_measurement('onboard', 0.5, START, 0.3, np.eye(4) * 1e-4)
    assert f.add(old) == 'too_old' and f.counts['onboard'].too_old == 1
    assert np.array_equal(f.estimate(3.0).x, before.x)


def test_on_poses_alone_it_is_filterpys_kalman_filter():
    """Poses in order are linear measurements: the same model in filterpy's KalmanFilter
    (predict, update) gives the same state and covariance."""
    rng = np.random.default_rng(9)
    ms = poses('ground', 30, 0.03, 0.02, 3.0, rng, rate=0.1, yaw0=0.2)
    ours = PoseFilter(CALM)
    ours.add(ms[0])
    ref = KalmanFilter(dim_x=8, dim_z=4)
    ref.x, ref.P = ours.estimate(ms[0].stamp).x.copy(), ours.estimate(ms[0].stamp).P.copy()
    ref.H = np.zeros((4, 8))
    ref.H[:3, :3], ref.H[3, 6] = np.eye(3), 1.0
    for prev, m in zip(ms, ms[1:]):
        dt = m.stamp - prev.stamp
        ref.F = np.eye(8)
        ref.F[:3, 3:6], ref.F[6, 7] = np.eye(3) * dt, dt
        ref.Q = np.zeros((8, 8))
        for axis in range(3):
            idx = np.ix_([axis, 3 + axis], [axis, 3 + axis])
            ref.Q[idx] = Q_discrete_white_noise(2, dt, CALM.accel_sigma ** 2)
        ref.Q[np.ix_([6, 7], [6, 7])] = Q_discrete_white_noise(2, dt, CALM.yaw_accel_sigma ** 2)
        ref.predict()
        ref.update(m.z, R=m.R)
        ours.add(m)
    est = ours.estimate(ms[-1].stamp)
    assert np.allclose(est.x, ref.x, atol=1e-10) and np.allclose(est.P, ref.P, atol=1e-12)


@pytest.mark.parametrize('reset_after', [1.0, math.inf])
def test_a_filter_locked_out_by_its_gate_starts_again_from_the_measurements(reset_after):
    """A model too confident for what the poses do (they step 0.4 m at 3 s, as when a
    camera is knocked): every pose after the step fails the gate. With `reset_after` the
    filter starts again from the first pose more than that after the last one applied,
    counts it, and follows the poses; without, it coasts away on its own."""
    rng = np.random.default_rng(5)
    step = np.array([0.4, 0.0, 0.0])
    ms = [pose_measurement('ground', m.stamp, m.z[:3] + (step if m.stamp >= 3.0 else 0.0),
                           m.z[3], m.R) for m in poses('ground', 30, 0.02, 0.02, 6.0, rng)]
    f = PoseFilter(FilterParams(accel_sigma=0.05, yaw_accel_sigma=0.1,
                                reset_after=reset_after))
    results = [f.add(m) for m in ms]
    stepped = [r for r, m in zip(results, ms) if m.stamp >= 3.0]   # all gated until a reset
    error = np.linalg.norm(f.estimate(6.0).position - (truth(6.0)[0] + step))
    if reset_after == math.inf:     # refused 1.5 s and more, then taken as the filter drifts
        assert stepped[:45] == ['gated'] * 45 and f.counts['ground'].resets == 0
        assert error > 0.25
        return
    k = results.index('reset')
    last_applied = max(m.stamp for m in ms if m.stamp < 3.0)
    assert ms[k - 1].stamp <= last_applied + reset_after < ms[k].stamp
    assert f.counts['ground'].resets == 1 and set(results[k + 1:]) == {'applied'}
    assert error < 0.05
