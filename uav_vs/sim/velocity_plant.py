"""Velocity-command vehicle for closed-loop controller tests (section 6).

Per axis i in (x, y, z, yaw), with command u_i (m/s or rad/s):

    v_i'(t) = (u_i(t - delay) - v_i(t)) / tau_i        first-order velocity loop
    p_i'(t) = v_i(t) + w_i                              w: constant drift (wind), p_yaw wrapped

integrated exactly for a command held over each step dt (zero-order hold); the
delay is a whole number of steps. Commands and pose are in the world frame, as a
multirotor in velocity (GUIDED) mode takes them.
"""
from __future__ import annotations

from collections import deque

import numpy as np


class VelocityPlant:
    """Four independent first-order-lag, pure-delay velocity axes."""

    def __init__(self, dt: float, tau=(0.3, 0.3, 0.25, 0.2), delay: float = 0.1,
                 pose=(0.0, 0.0, 0.0, 0.0), drift=(0.0, 0.0, 0.0, 0.0)):
        self.dt = float(dt)
        self.pose = np.array(pose, dtype=float)
        self.velocity = np.zeros(4)
        self.drift = np.array(drift, dtype=float)
        self._decay = np.exp(-self.dt / np.asarray(tau, dtype=float))
        self._tau = np.asarray(tau, dtype=float)
        n = int(round(delay / self.dt))
        self._queue = deque([np.zeros(4)] * n)

    def step(self, command: np.ndarray) -> np.ndarray:
        """Apply one command for dt; return the new pose (x, y, z, yaw)."""
        self._queue.append(np.asarray(command, dtype=float))
        u = self._queue.popleft()
        # Exact ZOH solution: v(t) = u + (v0 - u) e^(-t/tau), integrated over dt.
        self.pose += u * self.dt + (self.velocity - u) * self._tau * (1.0 - self._decay)
        self.pose += self.drift * self.dt
        self.pose[3] = (self.pose[3] + np.pi) % (2.0 * np.pi) - np.pi
        self.velocity = u + (self.velocity - u) * self._decay
        return self.pose.copy()
