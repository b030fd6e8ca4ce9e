"""The visual-servo loop around the fuzzy controllers (chapter sections 5-6), without ROS.

`ServoLoop` holds the latest measurement, setpoint and enable state, runs the
controller once per new measurement (the error rate is then a true measurement rate)
and answers, every output cycle, with the command to send and why. It fails safe:
disabled, no setpoint, no measurement yet or one older than the timeout, and
non-finite input all give a zero command. Limits apply to every command.

Pose mode: error = setpoint - pose (x, y, z, yaw) in world ENU, rotated into body
FLU when commands are body-frame; command (vx, vy, vz, yaw_rate) in that frame.
Tracking mode: error = image-centre column - target column (px); command = yaw rate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from uav_vs.control.controllers import AxisGroup, PoseController, TrackingController

ZERO = np.zeros(4)


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
    any non-finite component zeroes the whole command."""
    cmd = np.asarray(cmd, float)
    if not np.isfinite(cmd).all():
        return ZERO.copy()
    out = cmd.copy()
    h = math.hypot(out[0], out[1])
    if h > limits.horizontal:
        out[:2] *= limits.horizontal / h
    out[2] = min(max(out[2], -limits.vertical), limits.vertical)
    out[3] = min(max(out[3], -limits.yaw_rate), limits.yaw_rate)
    return out


class ServoLoop:
    """Measurement in, command out at a fixed rate; times are seconds on one clock."""

    def __init__(self, controller: AxisGroup, limits: Limits, timeout: float, body: bool = False,
                 enabled: bool = False):
        if not isinstance(controller, (PoseController, TrackingController)):
            raise TypeError('controller: expected a PoseController or TrackingController')
        self.controller, self.limits, self.timeout, self.body = controller, limits, timeout, body
        self.tracking = isinstance(controller, TrackingController)
        self.enabled = enabled
        self.setpoint: tuple[np.ndarray, float] | None = None
        self._command = ZERO.copy()
        self._last_t: float | None = None      # arrival time of the last measurement
        self._last_stamp: float | None = None  # its stamp, for the controller's dt

    def enable(self, on: bool) -> None:
        """Enable or disable; either way the controller starts afresh."""
        self.enabled = on
        self._restart()

    def set_setpoint(self, position: np.ndarray, yaw: float) -> None:
        self.setpoint = (np.asarray(position, float), float(yaw))

    def on_pose(self, t: float, stamp: float, position: np.ndarray, yaw: float) -> bool:
        """A new vehicle pose (pose mode). Returns False (and keeps nothing) if it is not finite."""
        if not (np.isfinite(position).all() and math.isfinite(yaw)):
            return False
        if self.setpoint is None:
            self._accept(t, stamp)
            return True
        error = pose_error(position, yaw, *self.setpoint, self.body)
        self._step(t, stamp, error)
        return True

    def on_target(self, t: float, stamp: float, pixel_error: float) -> bool:
        """A new target position (tracking mode): image-centre column minus target column."""
        if not math.isfinite(pixel_error):
            return False
        self._step(t, stamp, float(pixel_error))
        return True

    def command(self, now: float) -> tuple[np.ndarray, str]:
        """(vx, vy, vz, yaw_rate) to send now, and '' or the reason it is zero."""
        if not self.enabled:
            return ZERO.copy(), 'disabled'
        if self.setpoint is None and not self.tracking:
            return ZERO.copy(), 'no setpoint'
        if self._last_t is None:
            return ZERO.copy(), 'no measurement yet'
        age = now - self._last_t
        if age > self.timeout:
            return ZERO.copy(), f'measurement stale ({age:.2f} s > {self.timeout:.2f} s)'
        if not self.controller.valid.all():
            return ZERO.copy(), 'controller input out of its domain'
        return self._command.copy(), ''

    def _step(self, t: float, stamp: float, error: np.ndarray | float) -> None:
        dt = stamp - self._last_stamp if self._last_stamp is not None else math.nan
        fresh = self._last_t is not None and t - self._last_t <= self.timeout
        if not fresh:
            self.controller.reset()
            dt = math.nan
        self._accept(t, stamp)
        out = self.controller.step(error, dt)
        cmd = np.array([0.0, 0.0, 0.0, out]) if self.tracking else out
        self._command = limit_command(cmd, self.limits)

    def _accept(self, t: float, stamp: float) -> None:
        self._last_t, self._last_stamp = t, stamp

    def _restart(self) -> None:
        self.controller.reset()
        self._command = ZERO.copy()
        self._last_t = self._last_stamp = None
