"""The visual-servo loop around the fuzzy controllers (chapter sections 5-6), without ROS.

`ServoLoop` holds the latest measurement, setpoint and enable state, runs the
controller once per new measurement (the error rate is then a true measurement rate)
and answers, every output cycle, with the command to send and why. It fails safe:
disabled, no setpoint, no measurement yet or one older than the timeout, and
non-finite input all give a zero command. Limits apply to every command.

Two clocks (`Now`): the steady clock times arrivals, the ROS clock (the one the stamps
are on; /clock under use_sim_time) judges stamps. A measurement stamped 0, further
behind the ROS clock than `Timing.max_stamp_age` or further ahead than
`Timing.max_future` is refused: it never reaches the controller (nor its dt), and the
command, once zero, says why. A ROS clock that stands still for longer than the
timeout (a stopped simulation) gives a zero command as well.

Pose mode: error = setpoint - pose (x, y, z, yaw) in world ENU, rotated into body
FLU when commands are body-frame; command (vx, vy, vz, yaw_rate) in that frame.
Tracking mode: error = image-centre column - target column (px); command = yaw rate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import NamedTuple

import numpy as np

from uav_vs.control.controllers import AxisGroup, PoseController, TrackingController

ZERO = np.zeros(4)


class Now(NamedTuple):
    """One instant on both clocks, s."""

    steady: float      # monotonic: arrivals and timeouts
    ros: float         # the node's clock: what stamps are compared with


class Verdict(Enum):
    """What became of a measurement."""

    TAKEN = 'taken'
    NON_FINITE = 'non-finite'
    OLD = 'old stamp'            # stamped 0, or further behind the ROS clock than allowed
    FUTURE = 'future stamp'      # further ahead of the ROS clock than allowed


@dataclass(frozen=True)
class Timing:
    """When a measurement is too old to act on, or not to be believed: seconds."""

    timeout: float = 0.25        # since it arrived (steady clock); also the longest ROS clock stop
    max_stamp_age: float = 0.5   # its stamp behind the ROS clock (0: stamps are not aged)
    max_future: float = 0.1      # its stamp ahead of the ROS clock


@dataclass(frozen=True)
class Limits:
    """Command limits applied after the controller: m/s and rad/s."""

    horizontal: float = 1.0        # norm of (vx, vy)
    vertical: float = 0.5
    yaw_rate: float = 0.8


def pose_error(position: np.ndarray, yaw: float, setpoint: np.ndarray, setpoint_yaw: float,
               body: bool) -> np.ndarray:
    """(ex, ey, ez, eyaw) = setpoint - pose; x, y rotated into body FLU when `body`."""
    e = np.empty(4)
    e[:3] = np.asarray(setpoint, float) - np.asarray(position, float)
    e[3] = math.remainder(setpoint_yaw - yaw, 2.0 * math.pi)
    if body:
        c, s = math.cos(yaw), math.sin(yaw)
        e[0], e[1] = c * e[0] + s * e[1], -s * e[0] + c * e[1]
    return e


def limit_command(cmd: np.ndarray, limits: Limits) -> np.ndarray:
    """Horizontal speed scaled down to its limit (direction kept), vz and yaw rate clipped;
    any non-finite component zeroes the whole command. Finite and within the limits for
    any input (no intermediate overflows, even at 1e308)."""
    cmd = np.asarray(cmd, float)
    if not np.isfinite(cmd).all():
        return ZERO.copy()
    out = cmd.copy()
    m = np.abs(out[:2]).max()   # divided by it, the norm is in [1, sqrt 2]: no overflow
    if m > 0.0:
        unit = out[:2] / m
        n = math.hypot(*unit)
        if m > limits.horizontal / n:
            out[:2] = unit * (limits.horizontal / n)
    out[2] = min(max(out[2], -limits.vertical), limits.vertical)
    out[3] = min(max(out[3], -limits.yaw_rate), limits.yaw_rate)
    return out


class ServoLoop:
    """Measurement in, command out at a fixed rate; times are `Now`s and stamps in seconds."""

    def __init__(self, controller: AxisGroup, limits: Limits, timing: Timing, body: bool = False,
                 enabled: bool = False):
        if not isinstance(controller, (PoseController, TrackingController)):
            raise TypeError('controller: expected a PoseController or TrackingController')
        self.controller, self.limits, self.timing, self.body = controller, limits, timing, body
        self.tracking = isinstance(controller, TrackingController)
        self.what = 'target' if self.tracking else 'pose'
        self.enabled = enabled
        self.setpoint: tuple[np.ndarray, float] | None = None
        self.refused = ''                      # why the last measurement was refused, if it was
        self._command = ZERO.copy()
        self._last_t: float | None = None      # arrival time of the last measurement
        self._last_stamp: float | None = None  # its stamp, for the controller's dt
        self._clock: tuple[float, float] | None = None   # (ROS time, steady time it was first read)

    def set_limits(self, limits: Limits) -> None:
        """New command limits, from the command held now on."""
        self.limits = limits
        self._command = limit_command(self._command, limits)

    def set_timing(self, timing: Timing) -> None:
        """New timeout and stamp checks, from the next measurement and command on."""
        self.timing = timing

    def set_controller(self, controller: AxisGroup) -> None:
        """A controller of the same kind (new gains, rules) in place of this one; it
        starts afresh, and the command is zero until it has stepped on a measurement."""
        if isinstance(controller, TrackingController) != self.tracking:
            raise TypeError('controller: expected one of the same kind (pose or tracking)')
        self.controller = controller

    def enable(self, on: bool) -> None:
        """Enable or disable; either way the controller starts afresh."""
        self.enabled = on
        self._restart()

    def set_setpoint(self, position: np.ndarray, yaw: float) -> None:
        self.setpoint = (np.asarray(position, float), float(yaw))

    def on_pose(self, now: Now, stamp: float, position: np.ndarray, yaw: float) -> Verdict:
        """A new vehicle pose (pose mode). Anything but TAKEN leaves the loop as it was,
        but for `refused`, which says what was wrong with the stamp."""
        if not (np.isfinite(position).all() and math.isfinite(yaw)):
            return Verdict.NON_FINITE
        verdict = self._judge(now, stamp)
        if verdict is not Verdict.TAKEN:
            return verdict
        if self.setpoint is None:
            self._accept(now.steady, stamp)
        else:
            self._step(now.steady, stamp, pose_error(position, yaw, *self.setpoint, self.body))
        return verdict

    def on_target(self, now: Now, stamp: float, pixel_error: float) -> Verdict:
        """A new target position (tracking mode): image-centre column minus target column."""
        if not math.isfinite(pixel_error):
            return Verdict.NON_FINITE
        verdict = self._judge(now, stamp)
        if verdict is Verdict.TAKEN:
            self._step(now.steady, stamp, float(pixel_error))
        return verdict

    def command(self, now: Now) -> tuple[np.ndarray, str]:
        """(vx, vy, vz, yaw_rate) to send now, and '' or the reason it is zero."""
        self._watch_clock(now)
        if not self.enabled:
            return ZERO.copy(), 'disabled'
        if self.setpoint is None and not self.tracking:
            return ZERO.copy(), 'no setpoint'
        stopped = now.steady - self._clock[1]
        if stopped > self.timing.timeout:
            return ZERO.copy(), f'clock stopped ({stopped:.2f} s without a ROS time step)'
        if self._last_t is None:
            return ZERO.copy(), self.refused or 'no measurement yet'
        age = now.steady - self._last_t
        if age > self.timing.timeout:
            return ZERO.copy(), self.refused or \
                f'measurement stale ({age:.2f} s > {self.timing.timeout:.2f} s)'
        if self._too_old(now.ros - self._last_stamp):
            return ZERO.copy(), self._old_text(now.ros - self._last_stamp)
        if not self.controller.valid.all():
            return ZERO.copy(), 'controller input out of its domain'
        return self._command.copy(), ''

    def _judge(self, now: Now, stamp: float) -> Verdict:
        """TAKEN for a stamp to believe at `now`, else OLD or FUTURE with `refused` set."""
        self._watch_clock(now)
        lag = now.ros - stamp
        if stamp <= 0.0:
            self.refused = f'{self.what} unstamped (stamp {stamp:g})'
            return Verdict.OLD
        if self._too_old(lag):
            self.refused = self._old_text(lag)
            return Verdict.OLD
        if -lag > self.timing.max_future:
            self.refused = f'future stamp ({self.what} {-lag:.2f} s ahead of the clock)'
            return Verdict.FUTURE
        return Verdict.TAKEN

    def _too_old(self, lag: float) -> bool:
        return 0.0 < self.timing.max_stamp_age < lag

    def _old_text(self, lag: float) -> str:
        return f'{self.what} stamp {lag:.1f} s old (> {self.timing.max_stamp_age:.2f} s)'

    def _watch_clock(self, now: Now) -> None:
        """Note when the ROS clock last moved (on the steady clock)."""
        if self._clock is None or now.ros != self._clock[0]:
            self._clock = (now.ros, now.steady)

    def _step(self, t: float, stamp: float, error: np.ndarray | float) -> None:
        dt = stamp - self._last_stamp if self._last_stamp is not None else math.nan
        fresh = self._last_t is not None and t - self._last_t <= self.timing.timeout
        if not fresh:
            self.controller.reset()
            dt = math.nan
        self._accept(t, stamp)
        out = self.controller.step(error, dt)
        cmd = np.array([0.0, 0.0, 0.0, out]) if self.tracking else out
        self._command = limit_command(cmd, self.limits)

    def _accept(self, t: float, stamp: float) -> None:
        self._last_t, self._last_stamp, self.refused = t, stamp, ''

    def _restart(self) -> None:
        self.controller.reset()
        self._command = ZERO.copy()
        self._last_t = self._last_stamp = None
