"""Fuzzy position and tracking controllers built from YAML (chapter section 6).

Each controlled axis is one Mamdani system (uav_vs.control.fuzzy) with inputs
`error` (setpoint minus measurement), `rate` (its time derivative) and optionally
`integral` (its clamped time integral, the PID-like rule base), and output
`command`. Physical values are scaled into the rule universes by per-variable
`gain`s, the command is scaled back by the output `gain` and always saturated at
the axis `limit`. All axes of a controller run in one batched engine call.

Configuration: the `fuzzy` section of config/fuzzy_controller.yaml, as a nested
dict or as the flat dotted ROS parameters (`config_from_params`):

    inference: {and, implication, aggregation, defuzzification, resolution}
    axes: {x|y|z|yaw: AXIS}      # PoseController
    tracking: AXIS               # TrackingController
    AXIS: {limit, rate_filter, integral_limit?, error, rate, integral?, command, rules}
    error/rate/integral/command: {gain, sets + apexes | range + mf}
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from uav_vs.control.fuzzy import FuzzyBank, FuzzySystem

INPUTS = ('error', 'rate', 'integral')
AXIS_KEYS = {'limit', 'rate_filter', 'integral_limit', 'rules', 'command', *INPUTS}
TWO_PI = 2.0 * math.pi


def config_from_params(params: Mapping[str, object], prefix: str = 'fuzzy') -> dict:
    """Nested controller config from ROS parameters: flat dotted names ('fuzzy.axes.x.limit')
    and/or nested dicts, as a params file or `node.get_parameters_by_prefix` gives them.
    Sequences (lists, tuples, array.array) become lists."""
    tree: dict = {}

    def put(keys: list[str], value: object) -> None:
        node = tree
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ValueError(f"parameter {'.'.join(keys)!r} nests under a value")
        if isinstance(value, Mapping):
            for k, v in value.items():
                put(keys + str(k).split('.'), v)
        else:
            node[keys[-1]] = value if isinstance(value, (str, bytes)) or not hasattr(value, '__len__') \
                else list(value)

    for name, value in params.items():
        put(str(name).split('.'), value)
    if prefix:
        if prefix not in tree:
            raise ValueError(f'no {prefix!r} parameters found (top-level keys: {sorted(tree)})')
        tree = tree[prefix]
    return tree


def load_config(path: str | Path, prefix: str = 'fuzzy') -> dict:
    """Controller config from a ROS 2 params file ('/**' or the first node section)."""
    import yaml
    doc = yaml.safe_load(Path(path).read_text())
    section = doc.get('/**') or next(iter(doc.values()))
    return config_from_params(section['ros__parameters'], prefix)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


class _Axis:
    """Scaling, limits and fuzzy system of one axis, parsed from its config."""

    def __init__(self, name: str, cfg: Mapping, inference: Mapping):
        unknown = set(cfg) - AXIS_KEYS
        if unknown:
            raise ValueError(f'axis {name!r}: unknown key(s) {sorted(unknown)}')
        for key in ('limit', 'error', 'rate', 'command', 'rules'):
            if key not in cfg:
                raise ValueError(f'axis {name!r}: missing {key!r}')
        self.limit = float(cfg['limit'])
        self.rate_filter = float(cfg.get('rate_filter', 0.0))
        self.integral_limit = float(cfg.get('integral_limit', math.inf))
        if not (math.isfinite(self.limit) and self.limit > 0):
            raise ValueError(f"axis {name!r}: 'limit' must be finite and > 0, got {cfg['limit']!r}")
        if not self.rate_filter >= 0 or not self.integral_limit > 0:
            raise ValueError(f"axis {name!r}: 'rate_filter' must be >= 0 and 'integral_limit' > 0")
        names = [k for k in INPUTS if k in cfg]
        self.gains = [self._gain(name, k, cfg[k]) for k in names]
        self.out_gain = self._gain(name, 'command', cfg['command'])
        strip = lambda v: {k: val for k, val in v.items() if k != 'gain'}
        system_cfg = {'inputs': {k: strip(cfg[k]) for k in names},
                      'output': {'command': strip(cfg['command'])},
                      'rules': cfg['rules'], **inference}
        try:
            self.system = FuzzySystem.from_config(system_cfg)
        except ValueError as err:
            raise ValueError(f'axis {name!r}: {err}') from None
        self.has_integral = 'integral' in names

    @staticmethod
    def _gain(axis: str, var: str, cfg: Mapping) -> float:
        if not isinstance(cfg, Mapping):
            raise ValueError(f'axis {axis!r}: {var!r} must be a mapping')
        gain = float(cfg.get('gain', 1.0))
        if not (math.isfinite(gain) and gain != 0):
            raise ValueError(f'axis {axis!r}: {var}.gain must be finite and non-zero')
        return gain


class AxisGroup:
    """Several fuzzy PD / PID axes stepped together (error -> command), section 6.

    rate = d(error)/dt by finite differences (angles wrapped), low-passed with time
    constant `rate_filter`; integral = sum(error * dt) clamped to +-integral_limit.
    The first step after `reset` (or after a non-finite error) uses rate 0.
    A non-finite error on an axis gives command 0 on that axis, clears its state
    and reports valid False; a non-finite or non-positive dt freezes rate and
    integral for that step.
    """

    def __init__(self, axes: list[_Axis], angular: list[bool]):
        self.axes = axes
        self.bank = FuzzyBank([a.system for a in axes])
        # Per axis: wrap angles, rate filter time constant, integral limit (None: no
        # integral input), gains of error, rate and integral.
        self._axis = [(wrap, a.rate_filter, a.integral_limit if a.has_integral else None,
                       *a.gains, *(0.0,) * (3 - len(a.gains))) for a, wrap in zip(axes, angular)]
        self._with_integral = self.bank.n_inputs > 2
        self._x = np.zeros((len(axes), self.bank.n_inputs))
        self._x_flat = self._x.ravel()
        self._out_gain = np.array([a.out_gain for a in axes])
        self.limit = np.array([a.limit for a in axes])
        self._minus_limit = -self.limit
        self.valid = np.zeros(len(axes), dtype=bool)
        self.reset()

    def reset(self) -> None:
        """Forget the previous error, the rate estimate and the integral."""
        n = len(self.axes)
        self._prev = [math.nan] * n
        self._rate = [0.0] * n
        self._integral = [0.0] * n

    def step(self, error: np.ndarray, dt: float) -> np.ndarray:
        """Commands (n,) for errors (n,) after dt seconds; always finite and within +-limit.

        A handful of axes: the state update runs on plain floats, the fuzzy systems in
        one bank call."""
        dt = float(dt)
        timed = math.isfinite(dt) and dt > 0
        prev, rate, integral = self._prev, self._rate, self._integral
        inputs: list[float] = []
        finite: list[bool] = []
        for i, e in enumerate(np.asarray(error, dtype=float).tolist()):
            wrap, tau, i_limit, g_e, g_r, g_i = self._axis[i]
            ok = math.isfinite(e)
            if not ok:
                prev[i], rate[i], integral[i] = math.nan, 0.0, 0.0
                e = 0.0                          # evaluated, then discarded below
            else:
                if wrap:
                    e = math.remainder(e, TWO_PI)
                if timed:
                    de = e - prev[i]
                    if wrap and math.isfinite(de):
                        de = math.remainder(de, TWO_PI)
                    if math.isfinite(de):
                        r = rate[i] + dt / (tau + dt) * (de / dt - rate[i])
                        rate[i] = r if math.isfinite(r) else 0.0
                    if i_limit is not None:
                        integral[i] = min(i_limit, max(-i_limit, integral[i] + e * dt))
                prev[i] = e
            finite.append(ok)
            inputs += ((e * g_e, rate[i] * g_r, integral[i] * g_i) if self._with_integral
                       else (e * g_e, rate[i] * g_r))
        self._x_flat[:] = inputs
        y, ok = self.bank.evaluate(self._x)
        u = np.multiply(y, self._out_gain, out=y)
        np.minimum(u, self.limit, out=u)
        np.maximum(u, self._minus_limit, out=u)
        if all(finite) and all(ok.tolist()):
            self.valid = ok
            return u
        self.valid = ok & np.array(finite)
        return np.where(self.valid, u, 0.0)


class PoseController(AxisGroup):
    """Position-based fuzzy control (section 5-6): error (x, y, z, yaw) -> (vx, vy, vz, yaw_rate).

    The error is setpoint minus pose in one frame (world ENU, or body FLU after the
    caller rotates it); the command is in that same frame, m/s and rad/s. Yaw error
    is wrapped to [-pi, pi). `valid` holds the per-axis validity of the last step.
    """
    AXES = ('x', 'y', 'z', 'yaw')

    @classmethod
    def from_config(cls, cfg: Mapping) -> PoseController:
        """From the controller config (see module docstring); ValueError names what is wrong."""
        inference, axes = cfg.get('inference', {}), cfg.get('axes', {})
        missing = [a for a in cls.AXES if a not in axes]
        if missing:
            raise ValueError(f'fuzzy controller: missing axes {missing}')
        unknown = set(axes) - set(cls.AXES)
        if unknown:
            raise ValueError(f'fuzzy controller: unknown axes {sorted(unknown)}')
        return cls([_Axis(a, axes[a], inference) for a in cls.AXES], [False, False, False, True])


class TrackingController(AxisGroup):
    """Image-based heading / camera-pointing control (section 6): pixel error -> rate.

    pixel_error is the image-centre coordinate minus the target's (px), so a target
    left of centre gives a positive error and a positive (leftward, FLU) yaw rate.
    """

    @classmethod
    def from_config(cls, cfg: Mapping) -> TrackingController:
        """From the controller config's `tracking` section."""
        if 'tracking' not in cfg:
            raise ValueError("fuzzy controller: missing 'tracking' section")
        return cls([_Axis('tracking', cfg['tracking'], cfg.get('inference', {}))], [False])

    def step(self, pixel_error: float, dt: float) -> float:
        """Yaw (or pan) rate command in rad/s, bounded by the limit."""
        return float(super().step(np.array([pixel_error]), dt)[0])
