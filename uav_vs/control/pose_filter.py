"""One latency-compensated estimate of the vehicle's position, velocity, yaw and yaw rate
from every pose source (the chapter's Fig. 6 compares the vision poses with such a
Kalman-filtered state).

An extended Kalman filter in the world frame (REP-103: ENU, m, rad, s). The state is
x = [p (3), v (3), yaw, yaw rate]; between measurements the vehicle keeps its velocity
and yaw rate, disturbed by white acceleration (`accel_sigma`, m/s^2 per axis) and white
yaw acceleration (`yaw_accel_sigma`, rad/s^2). Measurements:

- a pose (ground station, onboard camera): p and yaw, each with its own covariance;
- odometry (the autopilot's estimate): p, yaw, the velocity in base_link (FLU, so
  h(x) = Rz(yaw)^T v, the filter's non-linear part: the vehicle flies near level) and
  the yaw rate.

Each measurement is applied at its own stamp, the time its image was taken: the filter
keeps its recent history (`history` s), and a measurement older than the newest one is
put in its place and every later one applied again (re-propagation), so a late source
weighs exactly as if it had arrived on time. An innovation beyond the Mahalanobis gate
(chi-square, `gate_probability`) is refused and counted. Nothing arrives from a source
that stops: the covariance grows with the process noise for as long as it is gone.

A gate can lock the filter out: once its covariance is smaller than the sources' real
errors (a motion model too confident for a manoeuvre, a source whose bias moved), every
measurement is refused and the estimate coasts away on its own. So when measurements
keep coming and none has been applied for `reset_after` s (by their stamps), the filter
starts again from the one that arrived last (counted as a reset of its source), as
PX4's EKF2 resets its position to the vision or GPS one after its innovation checks have
failed for a while.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from uav_vs.control.controllers import wrap_angle

P, V, YAW, RATE = slice(0, 3), slice(3, 6), 6, 7
N = 8
# each quantity and its rate: x, y, z, yaw and vx, vy, vz, yaw rate
_LEVEL, _RATE_OF = np.array([0, 1, 2, YAW]), np.array([3, 4, 5, RATE])


@dataclass(frozen=True)
class FilterParams:
    accel_sigma: float = 2.0          # m/s^2, white acceleration per axis
    yaw_accel_sigma: float = 1.0      # rad/s^2
    gate_probability: float = 0.999   # innovations beyond this chi-square quantile are refused
    history: float = 1.0              # s of measurements kept for late ones
    reset_after: float = 1.0          # s of refused measurements, none applied: start again
    initial_velocity_sigma: float = 1.0    # m/s, before any velocity is measured
    initial_rate_sigma: float = 1.0        # rad/s


@dataclass(frozen=True)
class Measurement:
    """What one source saw at `stamp` (s): z = h(x) + noise of covariance `R`. `kind`
    is 'pose' (z = p, yaw) or 'odometry' (z = p, yaw, base_link velocity, yaw rate)."""

    source: str
    stamp: float
    kind: str
    z: np.ndarray
    R: np.ndarray


@dataclass
class SourceCounts:
    applied: int = 0
    gated: int = 0          # refused by the Mahalanobis gate
    too_old: int = 0        # older than the history kept
    resets: int = 0         # the filter started again from one of its measurements
    last_stamp: float = -math.inf


@dataclass(frozen=True)
class Estimate:
    stamp: float
    x: np.ndarray
    P: np.ndarray

    @property
    def position(self) -> np.ndarray:
        return self.x[P]

    @property
    def velocity(self) -> np.ndarray:
        return self.x[V]

    @property
    def yaw(self) -> float:
        return float(self.x[YAW])


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose_measurement(source: str, stamp: float, position, yaw: float,
                     covariance: np.ndarray) -> Measurement:
    """A pose: position (3, m) and yaw (rad), covariance 4x4 over (x, y, z, yaw)."""
    return Measurement(source, stamp, 'pose', np.append(np.asarray(position, float), yaw),
                       np.asarray(covariance, float).reshape(4, 4))


def odometry_measurement(source: str, stamp: float, position, yaw: float, velocity_body,
                         yaw_rate: float, covariance: np.ndarray) -> Measurement:
    """Odometry: position (3), yaw, velocity in base_link (3), yaw rate; covariance 8x8."""
    z = np.concatenate([np.asarray(position, float), [yaw], np.asarray(velocity_body, float),
                        [yaw_rate]])
    return Measurement(source, stamp, 'odometry', z, np.asarray(covariance, float).reshape(8, 8))


class PoseFilter:
    """The filter: `add` measurements in any order, `estimate` at any time after the
    first."""

    def __init__(self, params: FilterParams = FilterParams()) -> None:
        self.params = params
        self.counts: dict[str, SourceCounts] = {}
        self._gates = {n: chi2.ppf(params.gate_probability, n) for n in (4, 8)}
        self._q = np.array([params.accel_sigma ** 2] * 3 + [params.yaw_accel_sigma ** 2])
        # the history: measurements by stamp, and the state after each was applied
        self._stamps: list[float] = []
        self._measurements: list[Measurement] = []
        self._states: list[tuple[np.ndarray, np.ndarray]] = []

    @property
    def initialised(self) -> bool:
        return bool(self._states)

    def add(self, m: Measurement) -> str:
        """Apply `m` at its stamp: 'applied', 'gated', 'too_old', 'initialised' or 'reset'
        (refused, but none applied for `reset_after`: the filter starts again from it)."""
        counts = self.counts.setdefault(m.source, SourceCounts())
        counts.last_stamp = max(counts.last_stamp, m.stamp)
        if not self._states:
            self._start(m)
            counts.applied += 1
            return 'initialised'
        newest = self._stamps[-1]
        if m.stamp < newest - self.params.history or m.stamp < self._stamps[0]:
            counts.too_old += 1
            return 'too_old'
        k = bisect.bisect_right(self._stamps, m.stamp)
        before = self._states[k - 1]
        after = self._update(before, self._stamps[k - 1], m)
        if after is None:
            counts.gated += 1
            if m.stamp - newest > self.params.reset_after:
                self._start(m)
                counts.resets += 1
                return 'reset'
            return 'gated'
        counts.applied += 1
        self._stamps.insert(k, m.stamp)
        self._measurements.insert(k, m)
        self._states.insert(k, after)
        # every later measurement again, from the corrected state (re-propagation)
        for j in range(k + 1, len(self._stamps)):
            again = self._update(self._states[j - 1], self._stamps[j - 1], self._measurements[j])
            self._states[j] = again if again is not None else \
                self._predict(*self._states[j - 1], self._stamps[j] - self._stamps[j - 1])
        self._forget()
        return 'applied'

    def estimate(self, stamp: float) -> Estimate:
        """The state predicted to `stamp` from the newest measurement at or before it."""
        if not self._states:
            raise RuntimeError('no measurement yet')
        k = max(bisect.bisect_right(self._stamps, stamp), 1)
        x, P_ = self._predict(*self._states[k - 1], stamp - self._stamps[k - 1])
        return Estimate(stamp, x, P_)

    def _start(self, m: Measurement) -> None:
        """Forget everything; the state is `m`'s."""
        self._stamps[:], self._measurements[:] = [m.stamp], [m]
        self._states[:] = [self._initial(m)]

    # ---------------------------------------------------------------- the model
    def _initial(self, m: Measurement) -> tuple[np.ndarray, np.ndarray]:
        p = self.params
        x, P_ = np.zeros(N), np.zeros((N, N))
        x[P], x[YAW] = m.z[:3], m.z[3]
        P_[:3, :3], P_[3:6, 3:6] = m.R[:3, :3], np.eye(3) * p.initial_velocity_sigma ** 2
        P_[YAW, YAW], P_[RATE, RATE] = m.R[3, 3], p.initial_rate_sigma ** 2
        if m.kind == 'odometry':
            x, P_ = self._correct(x, P_, m) or (x, P_)
        return x, P_

    def _predict(self, x: np.ndarray, P_: np.ndarray, dt: float
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Constant velocity and yaw rate over dt (s, may be 0)."""
        if dt <= 0:
            return x, P_
        F = np.eye(N)
        F[_LEVEL, _RATE_OF] = dt
        # white acceleration: the discrete noise of a double integrator, per axis
        Q = np.zeros((N, N))
        Q[_LEVEL, _LEVEL] = self._q * dt ** 4 / 4
        Q[_LEVEL, _RATE_OF] = Q[_RATE_OF, _LEVEL] = self._q * dt ** 3 / 2
        Q[_RATE_OF, _RATE_OF] = self._q * dt ** 2
        x = F @ x
        x[YAW] = wrap_angle(x[YAW])
        return x, F @ P_ @ F.T + Q

    def _update(self, state: tuple[np.ndarray, np.ndarray], t0: float, m: Measurement
                ) -> tuple[np.ndarray, np.ndarray] | None:
        x, P_ = self._predict(*state, m.stamp - t0)
        return self._correct(x, P_, m)

    def _correct(self, x: np.ndarray, P_: np.ndarray, m: Measurement
                 ) -> tuple[np.ndarray, np.ndarray] | None:
        """The Kalman update by `m`, or None when its innovation fails the gate."""
        h, H = self._observe(x, m.kind)
        y = m.z - h
        y[3] = wrap_angle(y[3])
        PHt = P_ @ H.T
        S_inv = np.linalg.inv(H @ PHt + m.R)
        if y @ S_inv @ y > self._gates[len(y)]:
            return None
        K = PHt @ S_inv
        x = x + K @ y
        x[YAW] = wrap_angle(x[YAW])
        I_KH = np.eye(N) - K @ H
        P_ = I_KH @ P_ @ I_KH.T + K @ m.R @ K.T      # Joseph form: stays symmetric, positive
        return x, P_

    @staticmethod
    def _observe(x: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """h(x) and its Jacobian H for a measurement of `kind`."""
        if kind == 'pose':
            H = np.zeros((4, N))
            H[:3, P], H[3, YAW] = np.eye(3), 1.0
            return np.append(x[P], x[YAW]), H
        R_wb = rot_z(x[YAW])
        v_body = R_wb.T @ x[V]
        H = np.zeros((8, N))
        H[:3, P], H[3, YAW] = np.eye(3), 1.0
        H[4:7, V] = R_wb.T
        c, s = math.cos(x[YAW]), math.sin(x[YAW])
        dRT = np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])   # d Rz(yaw)^T / d yaw
        H[4:7, YAW] = dRT @ x[V]
        H[7, RATE] = 1.0
        return np.concatenate([x[P], [x[YAW]], v_body, [x[RATE]]]), H

    def _forget(self) -> None:
        """Drop what is older than the history (keeping one state to start from)."""
        cut = bisect.bisect_left(self._stamps, self._stamps[-1] - self.params.history) - 1
        if cut > 0:
            del self._stamps[:cut], self._measurements[:cut], self._states[:cut]
