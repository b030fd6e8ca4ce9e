"""The servo loop around the fuzzy controllers: frames, limits and fail-safe behaviour.

Truth: analytic rotations, the loop's documented timeout and stamp rules, and the
velocity plant. Unless a test says otherwise both clocks read the same (`at`).
"""
import math

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from conftest import REPO
from uav_vs.control.controllers import PoseController, TrackingController, load_config
from uav_vs.control.servo import Limits, Now, ServoLoop, Timing, Verdict, limit_command, pose_error
from uav_vs.sim.velocity_plant import VelocityPlant

CFG = load_config(REPO / 'config' / 'fuzzy_controller.yaml')


def loop(**kw) -> ServoLoop:
    args = dict(limits=Limits(1.0, 0.5, 0.8), timing=Timing(0.25, 0.5, 0.1), body=False,
                enabled=True)
    return ServoLoop(PoseController.from_config(CFG), **{**args, **kw})


def at(t: float) -> Now:
    return Now(t, t)


def fed(s: ServoLoop, t: float, stamp: float | None = None, x: float = 0.0) -> Verdict:
    """s given a pose at x (m), arriving at t, stamped `stamp` (else t)."""
    return s.on_pose(at(t), t if stamp is None else stamp, np.array([x, 0.0, 0.0]), 0.0)


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


FLOATS = st.floats(allow_nan=False, allow_infinity=False)   # 1e308 and subnormals included


@given(st.tuples(FLOATS, FLOATS, FLOATS, FLOATS))
@example((1.7e308, 1.7e308, 1e308, -1e308))
def test_limits_hold_for_any_float_without_overflow(cmd):
    out = limit_command(np.array(cmd), Limits(1.0, 0.5, 0.8))
    assert np.isfinite(out).all() and math.hypot(out[0], out[1]) <= 1.0 + 1e-12
    assert abs(out[2]) <= 0.5 and abs(out[3]) <= 0.8
    half_speed = math.hypot(cmd[0] / 2, cmd[1] / 2)   # cannot overflow
    if half_speed > 0.5 * (1 + 1e-12):   # too fast: at the limit, same direction
        assert math.isclose(math.hypot(out[0], out[1]), 1.0, rel_tol=1e-12)
        assert math.isclose(math.atan2(out[1], out[0]), math.atan2(cmd[1], cmd[0]), abs_tol=1e-12)
    elif half_speed < 0.5 * (1 - 1e-12):
        assert (out[0], out[1]) == (cmd[0], cmd[1])


def test_zero_command_when_disabled_without_setpoint_or_measurement():
    s = loop(enabled=False)
    s.set_setpoint(np.array([1.0, 0.0, 0.0]), 0.0)
    fed(s, 1.0)
    cmd, why = s.command(at(1.01))
    assert not cmd.any() and why == 'disabled'
    s = loop()
    fed(s, 1.0)
    assert s.command(at(1.01))[1] == 'no setpoint'
    s = loop()
    s.set_setpoint(np.array([1.0, 0.0, 0.0]), 0.0)
    assert s.command(at(1.0))[1] == 'no measurement yet'


def test_stale_measurement_gives_zero_right_after_the_timeout():
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    for k in range(5):
        fed(s, 1.0 + 0.05 * k)
    cmd, why = s.command(at(1.2 + 0.25 - 1e-6))
    assert why == '' and cmd[0] > 0.5
    cmd, why = s.command(at(1.2 + 0.25 + 1e-6))
    assert not cmd.any() and why.startswith('measurement stale')


def test_non_finite_pose_is_refused_and_never_reaches_the_command():
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    assert fed(s, 1.0) is Verdict.TAKEN
    before = s.command(at(1.01))[0]
    assert fed(s, 1.05, x=math.nan) is Verdict.NON_FINITE
    assert s.on_pose(at(1.05), 1.05, np.zeros(3), math.inf) is Verdict.NON_FINITE
    after = s.command(at(1.06))[0]
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
        s.on_pose(at(1.0 + k * dt), 1.0 + k * dt, np.array([x, y, z]), yaw)
        cmd, why = s.command(at(1.0 + k * dt))
        assert why == '' and math.hypot(cmd[0], cmd[1]) <= 1.0 + 1e-9 and abs(cmd[3]) <= 0.8
        c, si = math.cos(yaw), math.sin(yaw)
        plant.step(np.array([c * cmd[0] - si * cmd[1], si * cmd[0] + c * cmd[1], cmd[2], cmd[3]]))
    x, y, z, yaw = plant.pose
    assert math.dist((x, y, z), (0.0, 0.0, 1.5)) < 0.05
    assert abs(yaw) < math.radians(2)


def test_tracking_turns_towards_the_target():
    s = ServoLoop(TrackingController.from_config(CFG), Limits(), Timing(0.25), enabled=True)
    s.on_target(at(1.0), 1.0, 150.0)            # target 150 px left of centre
    cmd, why = s.command(at(1.01))
    assert why == '' and cmd[3] > 0 and not cmd[:3].any()
    assert s.on_target(at(1.05), 1.05, math.nan) is Verdict.NON_FINITE


def test_pose_stamped_zero_or_too_old_is_refused_and_the_command_goes_zero():
    # Clocks at 100 s; a stream of poses 10 s old (or unstamped) never commands: once the
    # last fresh pose is past the timeout the command is zero and says why.
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    assert fed(s, 100.0) is Verdict.TAKEN and s.command(at(100.0))[1] == ''
    for k in range(1, 10):
        assert fed(s, 100.0 + 0.05 * k, stamp=90.0 + 0.05 * k, x=-5.0) is Verdict.OLD
    cmd, why = s.command(at(100.45))
    assert not cmd.any() and why == 'pose stamp 10.0 s old (> 0.50 s)'
    assert fed(s, 100.5, stamp=0.0) is Verdict.OLD
    assert s.command(at(100.5))[1] == 'pose unstamped (stamp 0)'
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    assert fed(s, 100.0, stamp=99.6) is Verdict.TAKEN             # 0.4 s: within the limit
    assert fed(s, 100.05, stamp=99.6 - 0.55) is Verdict.OLD
    assert s.command(at(100.05))[1] == ''                          # the last fresh pose still holds


def test_stamp_age_runs_on_the_ros_clock_as_well_as_arrival():
    # A simulation running at 4x: 0.2 s after a pose arrived (within the timeout) its
    # stamp is 0.8 s behind the ROS clock, over the 0.5 s limit.
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    assert s.on_pose(Now(1.0, 50.0), 50.0, np.zeros(3), 0.0) is Verdict.TAKEN
    assert s.command(Now(1.1, 50.4))[1] == ''
    cmd, why = s.command(Now(1.2, 50.8))
    assert not cmd.any() and why == 'pose stamp 0.8 s old (> 0.50 s)'


def test_future_stamp_is_refused_and_never_reaches_the_controllers_dt():
    # b sees the same poses as a, and between them ones stamped 5 s and 0.2 s ahead of the
    # clock (at another position): b's commands stay a's, to the bit. 0.05 s ahead is taken.
    a, b = loop(), loop()
    for s in (a, b):
        s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    for k in range(8):
        t = 10.0 + 0.05 * k
        for s in (a, b):
            assert fed(s, t, x=0.1 * k) is Verdict.TAKEN
        assert fed(b, t + 0.01, stamp=t + 5.0, x=1.5) is Verdict.FUTURE
        assert fed(b, t + 0.02, stamp=t + 0.22, x=1.5) is Verdict.FUTURE
        np.testing.assert_array_equal(a.command(at(t + 0.03))[0], b.command(at(t + 0.03))[0])
    assert b.command(at(10.4))[0].any()
    assert fed(b, 10.4, stamp=10.45) is Verdict.TAKEN
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    assert fed(s, 10.0, stamp=15.0) is Verdict.FUTURE
    cmd, why = s.command(at(10.0))
    assert not cmd.any() and why == 'future stamp (pose 5.00 s ahead of the clock)'


def test_a_ros_clock_that_stands_still_gives_zero_even_with_poses_arriving():
    # Poses keep arriving, stamped with a ROS clock that stopped at 20 s (steady 2.0 s):
    # commands go on within the timeout of the stop, are zero after it, and come back
    # once the clock moves again.
    s = loop()
    s.set_setpoint(np.array([2.0, 0.0, 0.0]), 0.0)
    for k in range(20):
        steady = 1.0 + 0.05 * k
        ros = 19.05 + 0.05 * min(k, 19)
        assert s.on_pose(Now(steady, ros), ros, np.zeros(3), 0.0) is Verdict.TAKEN
    assert s.command(Now(1.95, 20.0))[1] == ''
    assert s.on_pose(Now(2.15, 20.0), 20.0, np.zeros(3), 0.0) is Verdict.TAKEN
    assert s.command(Now(2.15, 20.0))[1] == ''
    assert s.on_pose(Now(2.25, 20.0), 20.0, np.zeros(3), 0.0) is Verdict.TAKEN
    cmd, why = s.command(Now(2.25, 20.0))
    assert not cmd.any() and why == 'clock stopped (0.30 s without a ROS time step)'
    assert s.on_pose(Now(2.3, 20.05), 20.05, np.zeros(3), 0.0) is Verdict.TAKEN
    assert s.command(Now(2.3, 20.05))[1] == ''
