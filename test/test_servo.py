"""The servo loop around the fuzzy controllers: frames, limits and fail-safe behaviour.

Truth: analytic rotations, the loop's documented timeout, and the velocity plant.
"""
import math

import numpy as np
import pytest

from conftest import REPO
from uav_vs.control.controllers import PoseController, TrackingController, load_config
from uav_vs.control.servo import Limits, ServoLoop, limit_command, pose_error
from uav_vs.sim.velocity_plant import VelocityPlant

CFG = load_config(REPO / 'config' / 'fuzzy_controller.yaml')


def loop(**kw) -> ServoLoop:
    args = dict(limits=Limits(1.0, 0.5, 0.8), timeout=0.25, body=False, enabled=True)
    return ServoLoop(PoseController.from_config(CFG), **{**args, **kw})


def test_pose_error_in_world_and_body_frames():
    # Vehicle at the origin facing north (yaw 90 deg); setpoint 1 m east, 0.5 m up, facing east.
    e = pose_error(np.zeros(3), math.pi / 2, np.array([1.0, 0.0, 0.5]), 0.0, body=False)
    np.testing.assert_allclose(e, [1.0, 0.0, 0.5, -math.pi / 2], atol=1e-12)
    e = pose_error(np.zeros(3), math.pi / 2, np.array([1.0, 0.0, 0.5]), 0.0, body=True)
    np.testing.assert_allclose(e, [0.0, -1.0, 0.5, -math.pi / 2], atol=1e-12)   # east = right
    e = pose_error(np.zeros(3), math.radians(170), np.zeros(3), math.radians(-170), body=False)
    assert e[3] == pytest.approx(math.radians(20))                               # wrapped


def test_limits_keep_direction_and_reject_non_finite():
    out = limit_command(np.array([3.0, 4.0, -2.0, 5.0]), Limits(1.0, 0.5, 0.8))
    np.testing.assert_allclose(out, [0.6, 0.8, -0.5, 0.8])
    assert not limit_command(np.array([0.1, math.nan, 0.0, 0.0]), Limits()).any()


def test_zero_command_when_disabled_without_setpoint_or_measurement():
    s = loop(enabled=False)
    s.set_setpoint(np.array([1.0, 0.0, 0.0]), 0.0)
    s.on_pose(0.0, 0.0, np.zeros(3), 0.0)
    cmd, why = s.command(0.01)
    assert not cmd.any() and why == 'disabled'
    s = loop()
    s.on_pose(0.0, 0.0, np.zeros(3), 0.0)
    assert s.command(0.01)[1] == 'no setpoint'
    s = loop()
    s.set_setpoint(np.array([1.0, 0.0, 0.0]), 0.0)
    assert s.command(0.0)[1] == 'no measurement yet'


def test_stale_measurement_gives_zero_right_after_the_timeout():
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    for k in range(5):
        s.on_pose(0.05 * k, 0.05 * k, np.zeros(3), 0.0)
    cmd, why = s.command(0.2 + 0.25 - 1e-6)
    assert why == '' and cmd[0] > 0.5
    cmd, why = s.command(0.2 + 0.25 + 1e-6)
    assert not cmd.any() and why.startswith('measurement stale')


def test_non_finite_pose_is_refused_and_never_reaches_the_command():
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    assert s.on_pose(0.0, 0.0, np.zeros(3), 0.0)
    before = s.command(0.01)[0]
    assert not s.on_pose(0.05, 0.05, np.array([math.nan, 0.0, 0.0]), 0.0)
    assert not s.on_pose(0.05, 0.05, np.zeros(3), math.inf)
    after = s.command(0.06)[0]
    assert np.isfinite(after).all()
    np.testing.assert_array_equal(before, after)


def test_body_frame_loop_brings_the_vehicle_home_from_2m_and_90deg():
    """Body-frame commands, rotated into the world by the plant's yaw, settle like the
    world-frame ones: within 5 cm and 2 deg after 10 s, speed within the limits."""
    dt = 0.05
    plant = VelocityPlant(dt, pose=(2.0, -1.0, 1.0, math.pi / 2))
    s = loop(body=True)
    s.set_setpoint(np.array([0.0, 0.0, 1.5]), 0.0)
    for k in range(int(10 / dt)):
        x, y, z, yaw = plant.pose
        s.on_pose(k * dt, k * dt, np.array([x, y, z]), yaw)
        cmd, why = s.command(k * dt)
        assert why == '' and math.hypot(cmd[0], cmd[1]) <= 1.0 + 1e-9 and abs(cmd[3]) <= 0.8
        c, si = math.cos(yaw), math.sin(yaw)
        plant.step(np.array([c * cmd[0] - si * cmd[1], si * cmd[0] + c * cmd[1], cmd[2], cmd[3]]))
    x, y, z, yaw = plant.pose
    assert math.dist((x, y, z), (0.0, 0.0, 1.5)) < 0.05
    assert abs(yaw) < math.radians(2)


def test_tracking_turns_towards_the_target():
    s = ServoLoop(TrackingController.from_config(CFG), Limits(), 0.25, enabled=True)
    s.on_target(0.0, 0.0, 150.0)            # target 150 px left of centre
    cmd, why = s.command(0.01)
    assert why == '' and cmd[3] > 0 and not cmd[:3].any()
    assert not s.on_target(0.05, 0.05, math.nan)
