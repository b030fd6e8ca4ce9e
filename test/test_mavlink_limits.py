"""The MAVLink session's bounds without a vehicle: the speed, climb and yaw-rate limits,
the geofence and what can go on the wire, each judged by hand-worked values or by their
invariants over any float (Hypothesis). The flights that put them on the wire to the
simulated autopilot are test_mavlink_session's.
"""
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from uav_vs.autopilot.link import connection_problem
from uav_vs.autopilot.session import Limits, Session, SessionConfig, fence_velocity, limit_velocity


def test_fence_limits_only_outward_components_by_the_distance_to_the_face():
    lo, hi = (-5.0, -5.0, 0.5), (5.0, 5.0, 3.0)
    v = np.array([1.0, -1.0, 0.5])
    assert np.array_equal(fence_velocity(v, np.array([0.0, 0.0, 1.0]), lo, hi, 1.5), v)  # far inside
    # 0.6 m from the east face, 1.5 s approach: east at most 0.4 m/s; the rest untouched
    assert np.allclose(fence_velocity(v, np.array([4.4, 0.0, 1.0]), lo, hi, 1.5), [0.4, -1.0, 0.5])
    assert np.array_equal(fence_velocity(v, np.array([5.2, 0.0, 1.0]), lo, hi, 1.5), [0.0, -1.0, 0.5])
    # back in from beyond the east face: allowed; down, 0.5 m above the floor: 1/3 m/s at most
    assert np.allclose(fence_velocity(-v, np.array([5.2, 0.0, 1.0]), lo, hi, 1.5), [-1.0, 1.0, -1 / 3])
    assert np.array_equal(fence_velocity(v, np.array([0.0, -5.0, 3.0]), lo, hi, 1.5), [1.0, 0.0, 0.0])
    assert np.array_equal(fence_velocity(v, None, lo, hi, 1.5), np.zeros(3))            # no estimate: hover


# ---------------------------------------------------------------- bounded commands
LIMITS = Limits(max_speed=2.0, max_climb=1.0, max_descent=0.7, max_yaw_rate=1.0)
HUGE = 1.7976931348623157e308   # the largest float
COMPONENTS = st.floats(allow_nan=False, allow_infinity=False)   # subnormals and 1e308 included


def within_limits(v, yaw_rate, limits=LIMITS, rel=1e-12):
    x, y, z = v
    return (all(map(math.isfinite, (x, y, z, yaw_rate)))
            and math.hypot(x, y) <= limits.max_speed * (1 + rel)
            and -limits.max_descent <= z <= limits.max_climb
            and abs(yaw_rate) <= limits.max_yaw_rate)


@pytest.mark.parametrize('v', [(1e308, 0.0, 0.0), (-1e308, 1e308, 0.0), (HUGE, HUGE, HUGE),
                               (-HUGE, 5e-324, -HUGE), (1e308, 3.0, 0.0), (1e200, -1e308, 1e308)])
def test_huge_commands_are_scaled_to_the_limit_with_their_direction(v):
    (x, y, z), yaw_rate = limit_velocity(v, -HUGE, LIMITS)
    assert within_limits((x, y, z), yaw_rate)
    assert math.isclose(math.hypot(x, y), 2.0, rel_tol=1e-12)
    assert math.isclose(math.atan2(y, x), math.atan2(v[1], v[0]), abs_tol=1e-12)
    assert z == (1.0 if v[2] > 0 else -0.7 if v[2] < 0 else 0.0) and yaw_rate == -1.0


@given(st.tuples(COMPONENTS, COMPONENTS, COMPONENTS), COMPONENTS)
def test_any_finite_command_is_limited_to_a_finite_one_in_its_direction(v, yaw_rate):
    (x, y, z), r = limit_velocity(v, yaw_rate, LIMITS)
    assert within_limits((x, y, z), r)
    if math.hypot(v[0] / 2, v[1] / 2) <= 1.0 * (1 - 1e-12):   # |v| <= max_speed: untouched
        assert (x, y) == (v[0], v[1])
    elif (x, y) != (0.0, 0.0):
        assert math.isclose(math.atan2(y, x), math.atan2(v[1], v[0]), abs_tol=1e-12)


@pytest.mark.parametrize('bad', [(math.inf, 0.0, 0.0), (0.0, -math.inf, 0.0), (0.0, 0.0, math.nan)])
def test_non_finite_commands_raise(bad):
    with pytest.raises(ValueError, match='not finite'):
        limit_velocity(bad, 0.0, LIMITS)
    with pytest.raises(ValueError, match='not finite'):
        limit_velocity((0.0, 0.0, 0.0), bad[0] + bad[1] + bad[2], LIMITS)


@pytest.mark.parametrize('position, stamp, why', [
    ((3.5e38, 0.0, 0.0), 1.0, 'not finite in float32'),     # finite, but no MAVLink float
    ((0.0, math.nan, 0.0), 1.0, 'not finite in float32'),
    ((1.0, 2.0, 3.0), -1.0, 'not a time since the epoch'),   # time_usec is unsigned
])
def test_a_vision_pose_that_cannot_go_on_the_wire_raises(position, stamp, why):
    session = Session(SessionConfig(connection='udpout:127.0.0.1:9'))   # never started
    with pytest.raises(ValueError, match=why):
        session.send_vision_pose(position, [0.0, 0.0, 0.0, 1.0], stamp)


@given(st.tuples(COMPONENTS, COMPONENTS, COMPONENTS),
       st.tuples(COMPONENTS, COMPONENTS, COMPONENTS))
def test_the_fence_never_makes_a_limited_command_faster(v, position):
    limited, _ = limit_velocity(v, 0.0, LIMITS)
    fenced = fence_velocity(np.array(limited), np.array(position), (-5.0, -5.0, 0.0),
                            (5.0, 5.0, 3.0), 1.5)
    assert np.isfinite(fenced).all() and (np.abs(fenced) <= np.abs(limited)).all()


@pytest.mark.parametrize('position', [(math.nan, 0.0, 1.0), (0.0, math.inf, 1.0)])
def test_the_fence_hovers_on_a_non_finite_position_estimate(position):
    fenced = fence_velocity(np.array([1.0, -1.0, 0.5]), np.array(position), (-5.0, -5.0, 0.0),
                            (5.0, 5.0, 3.0), 1.5)
    assert np.array_equal(fenced, np.zeros(3))


@pytest.mark.parametrize('device, problem', [
    ('tcp:127.0.0.1:5760', None), ('udpin:0.0.0.0:14550', None), ('udpout:gcs.local:0', None),
    ('tcpin:[::1]:5760', None), ('/dev/ttyACM0', None), ('COM3', None),
    ('tcp:nohost', 'expected tcp:HOST:PORT'), ('tcp::5760', 'expected tcp:HOST:PORT'),
    ('udpin:0.0.0.0:', 'expected udpin:HOST:PORT'), ('udp:host:65536', 'expected udp:HOST:PORT'),
    ('udpout:host:-1', 'expected udpout:HOST:PORT'), ('localhost:5760', 'or a serial device'),
    ('', 'or a serial device')])
def test_connection_strings_are_judged_by_their_form(device, problem):
    found = connection_problem(device)
    assert found is None if problem is None else problem in found, found


def test_a_connection_that_cannot_be_right_is_refused_before_anything_opens():
    with pytest.raises(ValueError, match="connection: expected tcp:HOST:PORT .* got 'tcp:nohost'"):
        Session(SessionConfig(connection='tcp:nohost'))


def test_limits_and_send_rate_must_be_finite_and_consistent():
    with pytest.raises(ValueError, match='max_speed'):
        Limits(max_speed=math.inf)
    with pytest.raises(ValueError, match='max_yaw_rate'):
        Limits(max_yaw_rate=math.nan)
    with pytest.raises(ValueError, match='max_send_rate must be at least stream_rate'):
        Session(SessionConfig(connection='udpout:127.0.0.1:9', stream_rate=20.0, max_send_rate=10.0))
