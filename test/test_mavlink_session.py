"""The relay's MAVLink session against the simulated ArduCopter over loopback TCP and UDP.

Ground truth is the simulator's own NED state: expected displacements are worked out
here by hand from the commanded ENU/FLU velocity (never through uav_vs.autopilot.frames),
so a frame mix-up in the session cannot cancel out. For the simulator's first-order
velocity lag the distance flown by a velocity pulse, once stopped, is exactly v * T, T the
time the vehicle held it (MavlinkVehicle.moving_time: from its receipt of the command to
that of the zero), which a loaded machine makes longer or shorter than the time the test
streamed it: either end of the pulse can reach the vehicle late.
"""
import logging
import math
import time

import numpy as np
import pytest

from mavlink_pair import (VELOCITY_YAW_RATE, ReadinessEndpoint, fly, pair, settle, take_off,
                          wait_for)
from test_mavlink_limits import HUGE, within_limits
from uav_vs.autopilot.link import mavlink, open_connection
from uav_vs.autopilot.session import (SEND_BURST, CommandState, LinkState, Session,
                                      SessionConfig)


def test_flight_in_world_and_body_frames_over_tcp():
    with pair('tcp', allow_arming=True) as (vehicle, session):
        status = session.wait_connected(5.0)
        assert (status.autopilot, status.vehicle_type) == ('ardupilot', 'QUADROTOR')
        take_off(session, vehicle, 1.0)
        truth = vehicle.truth()
        assert truth.armed and truth.mode == 'GUIDED' and 0.95 < -truth.position[2] < 1.05
        wait_for(lambda: session.telemetry().position is not None, 3.0, 'LOCAL_POSITION_NED')
        tel = session.telemetry()  # the estimate in ENU: (east, north, up) = (NED y, NED x, -NED z)
        n, e, d = vehicle.truth().position
        assert np.allclose(tel.position, [e, n, -d], atol=0.05)
        assert math.isclose(tel.height, -d, abs_tol=0.05)

        # world ENU (0.6 east, 0.8 south, 0.3 up) m/s held T s: NED (-0.8, +0.6, -0.3) T m
        p0, t0 = vehicle.truth().position, time.monotonic()
        fly(session, [0.6, -0.8, 0.3])
        settle(vehicle)
        held = vehicle.moving_time(since=t0)
        assert held > 0.6   # the pulse reached the vehicle (either end of it may come late)
        assert np.allclose(vehicle.truth().position - p0, np.array([-0.8, 0.6, -0.3]) * held,
                           atol=0.05)

        # +0.6 rad/s about z-up held T s: a left turn, NED yaw falls by 0.6 T rad
        yaw0, t0 = vehicle.truth().yaw, time.monotonic()
        fly(session, [0.0, 0.0, 0.0], yaw_rate=0.6, body=True)
        settle(vehicle)
        psi = vehicle.truth().yaw
        assert math.isclose(math.remainder(psi - yaw0, 2 * math.pi),
                            -0.6 * vehicle.moving_time(since=t0), abs_tol=0.03)

        # body FLU (0.8 forward, 0.6 left) m/s held T s at heading psi (NED, clockwise)
        forward, right = np.array([math.cos(psi), math.sin(psi)]), np.array([-math.sin(psi), math.cos(psi)])
        p0 = vehicle.truth().position
        t0 = time.monotonic()
        fly(session, [0.8, 0.6, 0.0], body=True)
        settle(vehicle)
        moved = vehicle.truth().position - p0
        assert np.allclose(moved[:2], vehicle.moving_time(since=t0)
                           * (0.8 * forward - 0.6 * right), atol=0.05)
        assert abs(moved[2]) < 0.03
        # the yaw rate (zero) is always sent, so the nose did not swing into the direction of travel
        assert abs(math.remainder(vehicle.truth().yaw - psi, 2 * math.pi)) < 0.02
        body = [t for t in vehicle.targets(since=t0) if t.velocity != (0.0, 0.0, 0.0)]
        assert body and {t.frame for t in body} == {mavlink.MAV_FRAME_BODY_OFFSET_NED}
        assert {t.type_mask for t in vehicle.targets()} == {VELOCITY_YAW_RATE}

        xy = vehicle.truth().position[:2]
        session.land()
        assert session.send_velocity([1.0, 0.0, 0.0]) is False  # landing: commands refused
        wait_for(lambda: not vehicle.truth().armed, 10.0, 'landing and disarm')
        truth = vehicle.truth()
        assert truth.mode == 'LAND' and not truth.flying and truth.position[2] == 0.0
        assert np.allclose(truth.position[:2], xy, atol=0.05)


def test_udp_flight_limits_and_stale_input_hover():
    with pair('udp', allow_arming=True, command_timeout=0.3) as (vehicle, session):
        take_off(session, vehicle)
        with pytest.raises(ValueError, match='not finite'):
            session.send_velocity([math.nan, 0.0, 0.0])
        with pytest.raises(ValueError, match='3 components'):
            session.send_velocity([1.0, 0.0])
        t0 = time.monotonic()
        assert session.send_velocity([30.0, 40.0, 5.0], yaw_rate=-9.0)  # limits 2 m/s, 1 m/s, 1 rad/s
        assert session.send_velocity([0.0, 0.0, 0.0])
        # a watchdog zero from before may land first: the limited command is the moving one
        def moving():
            return [t for t in vehicle.targets(since=t0) if t.velocity != (0.0, 0.0, 0.0)]
        wait_for(moving, 1.0, 'the command')
        sent = moving()[0]
        assert sent.frame == mavlink.MAV_FRAME_LOCAL_NED
        assert np.allclose(sent.velocity, [1.6, 1.2, -1.0])  # NED: north 1.6, east 1.2, up 1.0
        assert math.isclose(sent.yaw_rate, 1.0)            # -1 rad/s about up = +1 about down
        settle(vehicle)

        p0, t0 = vehicle.truth().position, time.monotonic()
        end = t0 + 0.5
        while time.monotonic() < end:   # 1 m/s north for 0.5 s, then the input stops
            last = time.monotonic()
            assert session.send_velocity([0.0, 1.0, 0.0])
            time.sleep(0.04)
        wait_for(lambda: session.status().command is CommandState.HOVER, 2.0, 'the command watchdog')
        settle(vehicle)
        north = (vehicle.truth().position - p0)[0]
        # the last command streamed until the 0.3 s watchdog, then zero: about 0.8 m;
        # the copter's own GUID_TIMEOUT (3 s) would have carried it 3.5 m
        held = vehicle.moving_time(since=t0)
        assert 0.5 < held < 2.0
        assert math.isclose(north, held, abs_tol=0.05)
        # the watchdog's zero, 0.3 s after the last command or later, then nothing but zeros
        sent = vehicle.targets(since=t0)
        first = next(k for k, t in enumerate(sent) if t.velocity != (0.0, 0.0, 0.0))
        stop = next(k for k in range(first, len(sent)) if sent[k].velocity == (0.0, 0.0, 0.0))
        assert sent[stop].time - last >= 0.3
        later = sent[stop:]
        assert all(t.velocity == (0.0, 0.0, 0.0) and t.yaw_rate == 0.0 for t in later)


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_link_loss_reconnects_without_replaying_commands(transport):
    with pair(transport, allow_arming=True) as (vehicle, session):
        take_off(session, vehicle)
        for _ in range(10):
            assert session.send_velocity([0.5, 0.0, 0.0])   # east
            time.sleep(0.05)
        vehicle.cut_link()
        refused = 0
        while session.status().link is LinkState.CONNECTED:
            session.send_velocity([0.5, 0.0, 0.0])
            time.sleep(0.05)
        status = session.status()
        assert status.link is LinkState.LOST and status.command is CommandState.IDLE
        for _ in range(5):   # input keeps coming during the loss: refused, not queued
            refused += session.send_velocity([0.5, 0.0, 0.0]) is False
        assert refused == 5
        settle(vehicle, timeout=6.0)   # its own GUID_TIMEOUT stopped it
        restored = time.monotonic()
        vehicle.restore_link()
        status = session.wait_connected(8.0)
        assert status.reconnects == 1 and status.command is CommandState.IDLE
        time.sleep(1.0)
        assert vehicle.targets(since=restored) == []   # nothing from before the loss
        assert np.linalg.norm(vehicle.truth().velocity) < 0.01
        fresh = time.monotonic()
        assert session.send_velocity([0.0, 0.5, 0.0])   # north
        wait_for(lambda: vehicle.targets(since=fresh), 1.0, 'the fresh command')
        assert vehicle.targets(since=fresh)[0].velocity == (0.5, 0.0, 0.0)  # NED north


class FakePx4:
    """A bare PX4-like endpoint: heartbeats with PX4 custom modes, ACKs, a record of setpoints."""

    def __init__(self):
        self.conn = open_connection('udpin:127.0.0.1:0', source_system=1, source_component=1)
        self.port = self.conn.port.getsockname()[1]
        self.custom_mode, self.height, self.commands, self.setpoints = 0, 0.0, [], []
        self.next_hb = 0.0

    def pump(self, until, timeout=8.0):
        """Serve until until() is true."""
        end = time.monotonic() + timeout
        while not until():
            now = time.monotonic()
            assert now < end, 'the session did not finish'
            if now >= self.next_hb:
                self.next_hb = now + 0.2
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                             mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self.custom_mode, 4)
                self.conn.mav.global_position_int_send(0, 0, 0, int((500.0 + self.height) * 1e3),
                                                       int(self.height * 1e3), 0, 0, 0, 0)
            msg = self.conn.recv_match(blocking=True, timeout=0.01)
            if msg is None:
                continue
            if msg.get_type() in ('SET_POSITION_TARGET_LOCAL_NED', 'VISION_POSITION_ESTIMATE'):
                self.setpoints.append((now, msg))
            elif msg.get_type() == 'COMMAND_LONG' and msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                self.commands.append((now, msg))
                if msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                    self.custom_mode = (int(msg.param2) << 16) | (int(msg.param3) << 24)
                elif msg.command == mavlink.MAV_CMD_NAV_LAND:
                    self.custom_mode = (4 << 16) | (6 << 24)   # AUTO.LAND
                elif msg.command == mavlink.MAV_CMD_NAV_TAKEOFF:
                    self.height = 2.0
                self.conn.mav.command_ack_send(msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 255, 190)


def test_px4_offboard_takeoff_body_frame_and_land():
    """PX4 specifics, against a bare endpoint: AMSL takeoff altitude, OFFBOARD entered only
    after more than a second of setpoints at > 2 Hz, body commands in MAV_FRAME_BODY_NED."""
    from concurrent.futures import ThreadPoolExecutor
    px4 = FakePx4()
    with Session(SessionConfig(connection=f'udpout:127.0.0.1:{px4.port}')) as session, \
            ThreadPoolExecutor(1) as pool:
        px4.pump(lambda: session.status().link is LinkState.CONNECTED)
        assert session.status().autopilot == 'px4'
        px4.pump(lambda: session.telemetry().altitude is not None)
        job = pool.submit(session.takeoff, 2.0)
        px4.pump(job.done)
        job.result()
        takeoff = [m for _, m in px4.commands if m.command == mavlink.MAV_CMD_NAV_TAKEOFF]
        assert math.isclose(takeoff[0].param7, 502.0)        # home 500 m AMSL + 2 m
        job = pool.submit(session.set_guided)
        px4.pump(job.done)
        job.result()
        assert session.status().mode == 'OFFBOARD'
        t_mode, mode = [(t, m) for t, m in px4.commands if m.command == mavlink.MAV_CMD_DO_SET_MODE][0]
        assert (mode.param1, mode.param2, mode.param3) == (1, 6, 0)
        before = [t for t, _ in px4.setpoints if t <= t_mode]
        assert before[-1] - before[0] > 1.0 and np.diff(before).max() < 0.5
        assert all(m.vx == m.vy == m.vz == 0 for _, m in px4.setpoints)
        n = len(px4.setpoints)
        assert session.send_velocity([1.0, 0.5, 0.0], body=True)
        px4.pump(lambda: any(m.vx for _, m in px4.setpoints[n:]))   # hover stream may come first
        sent = next(m for _, m in px4.setpoints[n:] if m.vx)
        assert sent.coordinate_frame == mavlink.MAV_FRAME_BODY_NED and (sent.vx, sent.vy) == (1.0, -0.5)
        # vision pose: 1 m east, 2 m north, 3 m up, nose east (ENU yaw 0, identity quaternion)
        assert session.send_vision_pose([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], stamp=1700000000.5)
        px4.pump(lambda: px4.setpoints[-1][1].get_type() == 'VISION_POSITION_ESTIMATE')
        vis = px4.setpoints[-1][1]
        assert (vis.x, vis.y, vis.z, vis.usec) == (2.0, 1.0, -3.0, 1700000000500000)
        assert math.isclose(vis.yaw, math.pi / 2, abs_tol=1e-6) and abs(vis.roll) < 1e-6
        assert np.isclose(vis.covariance[0], 0.01) and np.isclose(vis.covariance[20], 0.0025)
        job = pool.submit(session.land)
        px4.pump(job.done)
        job.result()
        assert session.status().mode == 'LAND' and session.status().command is CommandState.LOCKED
    px4.conn.close()


def test_a_late_acceptance_is_not_hidden_by_the_refusal_of_its_retry():
    """The first takeoff's ACK came late, so the session sent it again; the autopilot
    accepted the first and refuses the repeat (already taking off). When both ACKs are
    in before the waiting call looks, the command was carried out: ACCEPTED stands."""
    takeoff = mavlink.MAV_CMD_NAV_TAKEOFF
    with Session(SessionConfig(connection='udpout:127.0.0.1:9')) as session, session._cond:
        session._waiting.add(takeoff)
        for result in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_TEMPORARILY_REJECTED):
            session._on_ack(mavlink.MAVLink_command_ack_message(takeoff, result, 0, 0, 0, 0))
        assert session._acks[takeoff] == mavlink.MAV_RESULT_ACCEPTED
        session._acks.clear()      # a refusal on its own is still one
        session._on_ack(mavlink.MAVLink_command_ack_message(
            takeoff, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, 0, 0, 0, 0))
        assert session._acks[takeoff] == mavlink.MAV_RESULT_TEMPORARILY_REJECTED


def test_the_same_calls_fly_the_simulated_px4():
    """Against the simulator's PX4: set_guided streams setpoints before it asks for
    OFFBOARD, arming happens in OFFBOARD, the takeoff ends in AUTO.LOITER (velocity is
    not flown there) and set_guided re-enters OFFBOARD; a FLU body command then moves the
    vehicle v * T along its heading, and land() lands and disarms."""
    with pair('udp', {'autopilot': 'px4'}, allow_arming=True) as (vehicle, session):
        assert session.wait_connected(5.0).autopilot == 'px4'
        take_off(session, vehicle, 1.0)
        assert vehicle.truth().mode == 'LOITER'
        wait_for(lambda: session.status().mode == 'LOITER', 2.0, 'HEARTBEAT to say LOITER')
        assert 0.95 < -vehicle.truth().position[2] < 1.05
        session.set_guided()
        assert vehicle.truth().mode == 'OFFBOARD'
        settle(vehicle)
        p0, yaw, t0 = vehicle.truth().position, vehicle.truth().yaw, time.monotonic()
        fly(session, [0.5, 0.0, 0.0], body=True, duration=1.2)
        settle(vehicle)
        moved = vehicle.truth().position - p0
        flown = 0.5 * vehicle.moving_time(since=t0)
        assert np.allclose(moved, [flown * math.cos(yaw), flown * math.sin(yaw), 0.0], atol=0.05)
        assert vehicle.truth().mode == 'OFFBOARD'           # the hover stream keeps it
        session.land()
        wait_for(lambda: not vehicle.truth().armed, 8.0, 'landing and disarming')


def test_what_reaches_the_wire_is_finite_and_within_the_limits_for_any_float():
    """1e308, -1e308, the largest float, subnormals and mixed magnitudes, in both frames:
    every SET_POSITION_TARGET_LOCAL_NED the vehicle receives is finite and within limits
    (float32 on the wire: 1e-6 relative), and a non-finite command sends nothing."""
    commands = [((1e308, 0.0, 0.0), 0.0), ((-1e308, 1e308, -1e308), 1e308),
                ((HUGE, -HUGE, HUGE), -HUGE), ((5e-324, -5e-324, 5e-324), 5e-324),
                ((1e308, 1e-308, 1e300), -1e-300), ((-3.0, 40.0, -9.0), 7.0)]
    with pair('udp', allow_arming=True, max_send_rate=1000.0) as (vehicle, session):
        take_off(session, vehicle)
        t0 = time.monotonic()
        for body in (False, True):
            for v, yaw_rate in commands:
                assert session.send_velocity(v, yaw_rate, body=body)
                time.sleep(0.03)
        for bad in ((math.inf, 0.0, 0.0), (0.0, math.nan, 0.0)):
            with pytest.raises(ValueError, match='not finite'):
                session.send_velocity(bad)
        assert session.send_velocity((0.0, 0.0, 0.0))
        wait_for(lambda: len(vehicle.targets(since=t0)) >= 2 * len(commands) + 1, 2.0, 'the targets')
        sent = vehicle.targets(since=t0)
        for t in sent:   # NED/FRD: horizontal (x, y), z down, yaw rate about down
            assert within_limits((t.velocity[0], t.velocity[1], -t.velocity[2]), t.yaw_rate, rel=1e-6), t
        assert any(math.isclose(math.hypot(*t.velocity[:2]), 2.0, rel_tol=1e-6) for t in sent)
        settle(vehicle)


def test_a_burst_is_coalesced_to_the_send_rate_and_its_newest_command_is_flown():
    rate = 50.0
    with pair('udp', allow_arming=True, max_send_rate=rate, command_timeout=2.5) as (vehicle, session):
        take_off(session, vehicle)
        t0 = time.monotonic()
        n = 0
        while time.monotonic() < t0 + 0.5:   # ~1 kHz for 0.5 s: east 0..1 m/s
            assert session.send_velocity((min(n / 500, 1.0), 0.0, 0.0))
            n += 1
            time.sleep(0.001)
        last = time.monotonic()
        assert session.send_velocity((0.0, 0.5, 0.0))   # north 0.5: the one to be flown
        wait_for(lambda: any(t.velocity == (0.5, 0.0, 0.0) for t in vehicle.targets(since=last)),
                 0.9, 'the newest command (before the watchdog hovers)')
        end = time.monotonic()
        sent = [t for t in vehicle.targets(since=t0) if t.time <= end]
        assert n > 100 and len(sent) <= rate * (end - t0) + SEND_BURST, (n, len(sent), end - t0)
        assert sent[-1].velocity == (0.5, 0.0, 0.0)
        assert session.status().coalesced >= n + 1 - len(sent)   # each one sent or coalesced
        assert session.status().held >= session.status().coalesced > 0
        wait_for(lambda: abs(vehicle.truth().velocity[0] - 0.5) < 0.02, 2.0, 'north at 0.5 m/s')


def test_a_jittered_stream_at_the_send_rate_is_never_held_back():
    """A controller at max_send_rate whose commands come 12 and 28 ms apart (mean 20 ms)
    sends each one at once: no command waits for a send token."""
    with pair('udp', allow_arming=True, max_send_rate=50.0, command_timeout=2.5) as (vehicle, session):
        take_off(session, vehicle)
        t0 = time.monotonic()
        for k in range(100):
            assert session.send_velocity((0.001 * (k + 1), 0.0, 0.0))
            time.sleep(0.012 if k % 2 else 0.028)
        assert session.status().held == 0
        wait_for(lambda: len({t.velocity for t in vehicle.targets(since=t0)}) >= 100, 1.0,
                 'every command')


def test_a_command_waiting_for_its_slot_is_still_sent_on_close():
    with pair('udp', allow_arming=True, max_send_rate=2.5, stream_rate=2.5) as (vehicle, session):
        take_off(session, vehicle)
        assert session.send_velocity((0.5, 0.0, 0.0))
        assert session.send_velocity((0.0, 0.0, 0.0))   # within 0.4 s of the first: waits
        session.close()
        wait_for(lambda: vehicle.targets() and vehicle.targets()[-1].velocity[1] == 0.0, 1.0,
                 'the zero command')
        assert [t.velocity[1] for t in vehicle.targets()[-2:]] == [0.5, 0.0]


def test_an_unknown_host_is_named_throttled_and_kept_as_the_link_reason(caplog):
    caplog.set_level(logging.WARNING, logger='uav_vs.autopilot')
    with Session(SessionConfig(connection='tcp:nohost.invalid:5760')) as session:
        wait_for(lambda: session.status().link_reason, 3.0, 'a link reason')
        time.sleep(2.5)   # two more tries, inside the warning period
        status = session.status()
        assert status.link is LinkState.CONNECTING
        assert status.link_reason.startswith("cannot open tcp:nohost.invalid:5760: host "
                                             "'nohost.invalid' does not resolve")
    warnings = [r.getMessage() for r in caplog.records if 'does not resolve' in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].startswith(status.link_reason)


def test_odometry_with_an_attitude_that_is_no_rotation_leaves_the_twist_covariance_unknown():
    px4 = ReadinessEndpoint(mavlink.MAV_AUTOPILOT_PX4)
    diagonal = [math.nan] * 21
    diagonal[0] = diagonal[6] = diagonal[11] = 0.1          # PX4: variances on the diagonal
    with Session(SessionConfig(connection=f'udpout:127.0.0.1:{px4.port}')) as session:
        def send(q) -> None:
            px4.conn.mav.odometry_send(0, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED,
                                       0, 0, 0, q, 0, 0, 0, 0, 0, 0, diagonal, diagonal)
        px4.pump(lambda: session.status().autopilot == 'px4')
        send([0.0, 0.0, 0.0, 0.0])
        px4.pump(lambda: session.telemetry().pose_covariance is not None)
        assert session.telemetry().twist_covariance is None
        send([1.0, 0.0, 0.0, 0.0])                           # level, facing north
        px4.pump(lambda: session.telemetry().twist_covariance is not None)
        assert np.allclose(np.diag(session.telemetry().twist_covariance), [0.1] * 3 + [0] * 3)
    px4.conn.close()
