"""Fuzzy controllers from config/fuzzy_controller.yaml closed around the velocity plant:
settling, no oscillation, bounded commands, integral action (the PID-like layer
config/fuzzy_controller_pid.yaml), safety and config errors."""
import copy
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from uav_vs.control.controllers import (PoseController, TrackingController, config_from_params,
                                        load_config, wrap_angle)
from uav_vs.sim.velocity_plant import VelocityPlant

YAML = Path(__file__).resolve().parents[1] / 'config' / 'fuzzy_controller.yaml'
PID_YAML = YAML.with_name('fuzzy_controller_pid.yaml')
CFG = load_config(YAML)


def flatten(d, prefix=''):
    """Nested params to flat dotted names, as ROS 2 declares them."""
    for k, v in d.items():
        if isinstance(v, dict):
            yield from flatten(v, f'{prefix}{k}.')
        else:
            yield f'{prefix}{k}', tuple(v) if isinstance(v, list) else v


def load_layered(*paths):
    """Params files layered as `--params-file a --params-file b` layers them: a later
    file overrides single parameters (leaves) of an earlier one."""
    flat = {}
    for path in paths:
        flat.update(flatten(yaml.safe_load(path.read_text())['/**']['ros__parameters']))
    return config_from_params(flat)


PID_CFG = load_layered(YAML, PID_YAML)     # z with the PID-like 45-rule base
DT = 0.02
# Bounds stated for the default tuning: within 6 s every axis is inside 5 cm / 2 deg
# and stays there; the error never crosses zero by more than 1 cm / 0.5 deg.
SETTLE_S, POS_TOL, YAW_TOL = 6.0, 0.05, np.radians(2.0)
POS_OVERSHOOT, YAW_OVERSHOOT = 0.01, np.radians(0.5)


def fly(ctl, plant, setpoint, seconds):
    errors, commands = [], []
    for _ in range(int(round(seconds / DT))):
        e = setpoint - plant.pose
        e[3] = wrap_angle(e[3])
        u = ctl.step(e, DT)
        errors.append(e)
        commands.append(u)
        plant.step(u)
    return np.array(errors), np.array(commands)


@pytest.mark.parametrize('tau,delay', [((0.3, 0.3, 0.25, 0.2), 0.1), ((0.45, 0.45, 0.4, 0.3), 0.2)])
def test_each_axis_settles_from_2m_and_90deg_without_oscillation(tau, delay):
    ctl = PoseController.from_config(CFG)
    setpoint = np.array([2.0, -2.0, 2.0, np.pi / 2])
    errors, commands = fly(ctl, VelocityPlant(DT, tau=tau, delay=delay), setpoint, 10.0)
    t = np.arange(len(errors)) * DT
    tol = np.array([POS_TOL] * 3 + [YAW_TOL])
    overshoot = np.array([POS_OVERSHOOT] * 3 + [YAW_OVERSHOOT])
    after = t >= SETTLE_S
    assert (np.abs(errors[after]) < tol).all()
    crossed = -(errors * np.sign(setpoint)).min(axis=0)       # how far past zero each axis went
    assert (crossed < overshoot).all(), crossed
    assert np.isfinite(commands).all() and (np.abs(commands) <= ctl.limit).all()
    assert (np.abs(commands).max(axis=0) == ctl.limit).all()  # it does use the full authority


def test_tracking_controller_centres_a_target_30deg_off():
    # Pinhole heading loop: target at bearing 30 deg, f = 500 px; error = centre - target column.
    ctl, f, dt = TrackingController.from_config(CFG), 500.0, 1 / 30
    plant = VelocityPlant(dt)
    errs = []
    for _ in range(int(8 / dt)):
        e = f * np.tan(np.radians(30) - plant.pose[3])
        u = ctl.step(e, dt)
        assert abs(u) <= ctl.limit[0]
        errs.append(e)
        plant.step(np.array([0, 0, 0, u]))
    errs = np.array(errs)
    assert abs(errs[-1]) < 2.0 and errs.min() > -2.0     # centred, no overshoot past 2 px
    assert plant.pose[3] == pytest.approx(np.radians(30), abs=np.radians(0.3))


def test_pid_layer_gives_z_three_inputs_and_45_rules():
    # config/fuzzy_controller_pid.yaml over the main file: z becomes error x rate x
    # integral (5 x 3 x 3 sets, every combination once), the rest stays as it was.
    ctl = PoseController.from_config(PID_CFG)
    z = ctl.axes[2]
    assert [v.name for v in z.system.inputs] == ['error', 'rate', 'integral']
    assert [len(v.sets) for v in z.system.inputs] == [5, 3, 3]
    assert len(z.system.rules) == 45 and z.has_integral and z.integral_limit == 0.6
    assert len({r.antecedent for r in z.system.rules}) == 45
    # The table the file's comment states: command index = 3 + offsets, saturated.
    for r in z.system.rules:
        (_, e), (_, d), (_, i) = r.antecedent
        assert r.consequent == min(6, max(0, 3 + (e - 2) + (d - 1) + (i - 1)))
    assert ctl.bank.n_inputs == 3
    assert [len(a.system.inputs) for a in ctl.axes] == [2, 2, 3, 2]
    base = CFG['axes']['z']
    assert (z.limit, z.rate_filter, z.out_gain) == (base['limit'], base['rate_filter'], base['command']['gain'])
    for axis in ('x', 'y', 'yaw'):
        assert PID_CFG['axes'][axis] == CFG['axes'][axis]
    assert PID_CFG['tracking'] == CFG['tracking'] and PID_CFG['inference'] == CFG['inference']


@pytest.mark.parametrize('path', [YAML, PID_YAML], ids=['main', 'pid'])
def test_every_config_key_is_commented(path):
    """Each `key:` line has a comment on it or on the line above."""
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        m = re.match(r'\s*"?(\w+)"?:', line)
        if m and m.group(1) != 'ros__parameters' and not line.startswith('/**'):
            assert '#' in line or lines[i - 1].strip().startswith('#'), f'{path.name}:{i + 1}: {line}'


def test_integral_input_removes_the_offset_a_steady_drift_leaves():
    drift = (0.0, 0.0, -0.15, 0.0)                       # e.g. a sinking autopilot velocity loop
    setpoint = np.array([0.0, 0.0, 1.0, 0.0])
    pid = PID_CFG                                        # config/fuzzy_controller_pid.yaml
    pd_err, _ = fly(PoseController.from_config(CFG), VelocityPlant(DT, pose=(0, 0, 1, 0), drift=drift), setpoint, 20)
    pid_err, pid_cmd = fly(PoseController.from_config(pid), VelocityPlant(DT, pose=(0, 0, 1, 0), drift=drift), setpoint, 20)
    assert abs(pd_err[-1, 2]) > 0.05                     # PD: steady offset
    assert abs(pid_err[-1, 2]) < 0.01                    # PID-like: none
    assert np.abs(pid_cmd[:, 2]).max() <= CFG['axes']['z']['limit']


def test_non_finite_errors_never_reach_the_command():
    ctl = PoseController.from_config(CFG)
    rng = np.random.default_rng(1)
    bad = [np.nan, np.inf, -np.inf, 1e308, -1e308]
    for k in range(300):
        e = rng.normal(0, 3, 4)
        e[rng.integers(4)] = bad[k % len(bad)]
        dt = [DT, 0.0, -1.0, np.nan, np.inf][k % 5] if k % 7 == 0 else DT
        u = ctl.step(e, dt)
        assert np.isfinite(u).all() and (np.abs(u) <= ctl.limit).all()
        assert (u[~np.isfinite(e)] == 0).all() and not ctl.valid[~np.isfinite(e)].any()
    # A NaN on x leaves the other axes under control.
    ctl.reset()
    u = ctl.step(np.array([np.nan, 1.0, -1.0, 0.3]), DT)
    assert u[0] == 0 and u[1] > 0 and u[2] < 0 and u[3] > 0
    assert ctl.valid.tolist() == [False, True, True, True]


def test_yaw_error_is_wrapped():
    ctl = PoseController.from_config(CFG)
    u = ctl.step(np.array([0, 0, 0, np.radians(350)]), DT)      # = -10 deg: turn right
    assert u[3] < 0


def test_flat_ros_parameters_give_the_same_config():
    params = yaml.safe_load(YAML.read_text())['/**']['ros__parameters']
    assert config_from_params(dict(flatten(params))) == CFG


def test_unknown_set_or_variable_in_yaml_fails_with_one_line():
    text = YAML.read_text().replace('"IF error IS PM AND rate IS ZE THEN command IS PM"',
                                    '"IF error IS PM AND rate IS ZE THEN command IS PX"', 1)
    cfg = config_from_params(yaml.safe_load(text)['/**']['ros__parameters'])
    with pytest.raises(ValueError) as err:
        PoseController.from_config(cfg)
    assert "axis 'x'" in str(err.value) and "'PX'" in str(err.value) and '\n' not in str(err.value)
    cfg = copy.deepcopy(CFG)
    cfg['axes']['yaw']['rules'][0] = 'IF heading IS NB THEN command IS NB'
    with pytest.raises(ValueError, match="axis 'yaw'.*'heading'"):
        PoseController.from_config(cfg)


def test_step_matches_a_per_axis_restatement():
    # rate filter, clamped integral, yaw wrapping and the fail-safes, one axis at a time
    # through each axis's own system, against the batched step (PID-like z axis included).
    ctl = PoseController.from_config(PID_CFG)
    assert ctl.bank.linear_firing and ctl.bank.closed_form      # the shortcuts carry the config
    rng = np.random.default_rng(3)
    prev, rate, integral = [np.nan] * 4, [0.0] * 4, [0.0] * 4
    for k in range(400):
        e = rng.normal(0, 1.5, 4)
        e[3] *= 3
        if k % 13 == 5:
            e[rng.integers(4)] = [np.nan, np.inf, -np.inf][k % 3]
        dt = [0.0, -1.0, np.nan][k % 3] if k % 17 == 9 else DT
        u = ctl.step(e, dt)
        for i, axis in enumerate(ctl.axes):
            if not np.isfinite(e[i]):
                prev[i], rate[i], integral[i] = np.nan, 0.0, 0.0
                assert u[i] == 0 and not ctl.valid[i]
                continue
            ei = math.remainder(e[i], 2 * math.pi) if i == 3 else e[i]
            if np.isfinite(dt) and dt > 0:
                de = ei - prev[i]
                if i == 3 and np.isfinite(de):
                    de = math.remainder(de, 2 * math.pi)
                if np.isfinite(de):
                    rate[i] += dt / (axis.rate_filter + dt) * (de / dt - rate[i])
                if axis.has_integral:
                    lim = axis.integral_limit
                    integral[i] = min(lim, max(-lim, integral[i] + ei * dt))
            prev[i] = ei
            x = [v * g for v, g in zip((ei, rate[i], integral[i]), axis.gains)]
            y, ok = axis.system.evaluate(x)
            assert ctl.valid[i] == ok
            assert u[i] == pytest.approx(min(axis.limit, max(-axis.limit, y * axis.out_gain)), abs=1e-12)
