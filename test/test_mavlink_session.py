"""The relay's MAVLink session against the simulated ArduCopter over loopback TCP and UDP.

Ground truth is the simulator's own NED state: expected displacements are worked out
here by hand from the commanded ENU/FLU velocity (never through uav_vs.autopilot.frames),
so a frame mix-up in the session cannot cancel out. For the simulator's first-order
velocity lag the distance flown by a velocity pulse, once stopped, is exactly v * T.
"""
import contextlib
import math
import time

import numpy as np
import pytest

from uav_vs.autopilot.link import load_signing_key, mavlink, open_connection
from uav_vs.autopilot.session import (AutopilotError, CommandError, CommandState, LinkState,
                                      Session, SessionConfig)
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

VELOCITY_YAW_RATE = 0x05C7


@contextlib.contextmanager
def pair(transport='tcp', vehicle_cfg=None, **session_kw):
    """A simulated vehicle serving on a free loopback port and a session connected to it."""
    server = {'tcp': 'tcpin:127.0.0.1:0', 'udp': 'udpin:127.0.0.1:0'}[transport]
    cfg = vehicle_cfg or {}
    with MavlinkVehicle(VehicleConfig(connection=server, **{'ready_delay': 0.2, **cfg})) as vehicle:
        port = vehicle.address[1]
        client = {'tcp': f'tcp:127.0.0.1:{port}', 'udp': f'udpout:127.0.0.1:{port}'}[transport]
        with Session(SessionConfig(connection=client, **session_kw)) as session:
            yield vehicle, session


def wait_for(predicate, timeout, what):
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, f'timed out waiting for {what}'
        time.sleep(0.02)


def settle(vehicle, timeout=5.0):
    wait_for(lambda: np.linalg.norm(vehicle.truth().velocity) < 0.02
             and abs(vehicle.truth().yaw_rate) < 0.01, timeout, 'the vehicle to stop')


def take_off(session, vehicle, height=1.0):
    session.wait_connected(5.0)
    wait_for(lambda: session.status().prearm_ok, 5.0, 'the pre-arm checks to pass')
    session.set_guided()
    session.arm()
    session.takeoff(height)
    settle(vehicle)


def fly(session, velocity, yaw_rate=0.0, body=False, duration=1.2, rate=25.0):
    """Stream one command for `duration`, then command zero."""
    end = time.monotonic() + duration
    while time.monotonic() < end:
        assert session.send_velocity(velocity, yaw_rate, body)
        time.sleep(1.0 / rate)
    assert session.send_velocity([0.0, 0.0, 0.0])


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

        # world ENU (0.6 east, 0.8 south, 0.3 up) m/s for 1.2 s: NED (-0.96, +0.72, -0.36) m
        p0 = vehicle.truth().position
        fly(session, [0.6, -0.8, 0.3])
        settle(vehicle)
        assert np.allclose(vehicle.truth().position - p0, [-0.96, 0.72, -0.36], atol=0.1)

        # +0.6 rad/s about z-up for 1.2 s: a left turn, NED yaw falls by 0.72 rad
        yaw0 = vehicle.truth().yaw
        fly(session, [0.0, 0.0, 0.0], yaw_rate=0.6, body=True)
        settle(vehicle)
        psi = vehicle.truth().yaw
        assert math.isclose(math.remainder(psi - yaw0, 2 * math.pi), -0.72, abs_tol=0.07)

        # body FLU (0.8 forward, 0.6 left) m/s for 1.2 s at heading psi (NED, clockwise)
        forward, right = np.array([math.cos(psi), math.sin(psi)]), np.array([-math.sin(psi), math.cos(psi)])
        p0 = vehicle.truth().position
        t0 = time.monotonic()
        fly(session, [0.8, 0.6, 0.0], body=True)
        settle(vehicle)
        moved = vehicle.truth().position - p0
        assert np.allclose(moved[:2], 1.2 * (0.8 * forward - 0.6 * right), atol=0.1)
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
        wait_for(lambda: vehicle.targets(since=t0), 1.0, 'the command')
        sent = vehicle.targets(since=t0)[0]
        assert sent.frame == mavlink.MAV_FRAME_LOCAL_NED
        assert np.allclose(sent.velocity, [1.6, 1.2, -1.0])  # NED: north 1.6, east 1.2, up 1.0
        assert math.isclose(sent.yaw_rate, 1.0)            # -1 rad/s about up = +1 about down
        settle(vehicle)

        p0 = vehicle.truth().position
        end = time.monotonic() + 0.5
        while time.monotonic() < end:   # 1 m/s north for 0.5 s, then the input stops
            assert session.send_velocity([0.0, 1.0, 0.0])
            time.sleep(0.04)
        last = time.monotonic()
        wait_for(lambda: session.status().command is CommandState.HOVER, 2.0, 'the command watchdog')
        settle(vehicle)
        north = (vehicle.truth().position - p0)[0]
        # the last command streamed until the 0.3 s watchdog, then zero: about 0.8 m;
        # the copter's own GUID_TIMEOUT (3 s) would have carried it 3.5 m
        assert 0.6 < north < 1.1
        later = vehicle.targets(since=last + 0.45)
        assert later and all(t.velocity == (0.0, 0.0, 0.0) and t.yaw_rate == 0.0 for t in later)


def test_link_loss_reconnects_without_replaying_commands():
    with pair('tcp', allow_arming=True) as (vehicle, session):
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


def test_arming_refusals_carry_the_autopilot_reason():
    with pair('tcp', vehicle_cfg={'ready_delay': 60.0}) as (vehicle, session):
        session.wait_connected(5.0)
        with pytest.raises(AutopilotError, match='arming is disabled'):
            session.arm()
        with pytest.raises(CommandError, match='GUIDED requires position') as err:
            session.set_guided()
        assert err.value.result == mavlink.MAV_RESULT_FAILED
    with pair('tcp', vehicle_cfg={'ready_delay': 60.0}, allow_arming=True) as (vehicle, session):
        session.wait_connected(5.0)
        with pytest.raises(CommandError, match='PreArm: Need Position Estimate') as err:
            session.arm()
        assert err.value.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM
        assert err.value.result == mavlink.MAV_RESULT_FAILED
        assert 'MAV_RESULT_FAILED' in str(err.value)
        assert not vehicle.truth().armed and not session.status().armed


def _raw_gcs(port, system=254):
    return open_connection(f'udpout:127.0.0.1:{port}', source_system=system)


def _acks_for(gcs, system, seconds):
    end, acks, signed = time.monotonic() + seconds, [], []
    while time.monotonic() < end:
        msg = gcs.recv_match(blocking=True, timeout=0.1)
        if msg is None:
            continue
        if msg.get_type() == 'HEARTBEAT':  # no key here: read the header's signed flag
            signed.append(bool(msg.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED))
        if msg.get_type() == 'COMMAND_ACK' and msg.target_system == system:
            acks.append(msg)
    return acks, signed


def test_signing_rejects_unsigned_traffic_both_ways(tmp_path):
    key_file = tmp_path / 'signing.key'
    key_file.write_text('correct horse battery staple\n')
    key = load_signing_key(key_file)
    with pair('udp', vehicle_cfg={'signing_key': key}, allow_arming=True,
              signing_key_file=str(key_file)) as (vehicle, session):
        session.wait_connected(5.0)
        session.set_guided()
        assert vehicle.truth().mode == 'GUIDED'       # signed commands accepted, ACKs accepted
        status = session.status()
        assert status.signing and status.vehicle_signs and status.rejected == 0
        gcs = _raw_gcs(vehicle.address[1])            # a GCS without the key
        gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0)
        acks, signed = _acks_for(gcs, 254, 1.5)
        assert acks == [] and vehicle.truth().mode == 'GUIDED'   # its unsigned command was dropped
        assert signed and all(signed)                             # and what it hears is signed
        gcs.close()
    # the other way: a vehicle that does not sign is not accepted by a session that requires it
    with pair('udp', signing_key_file=str(key_file)) as (vehicle, session):
        with pytest.raises(AutopilotError, match='timed out'):
            session.wait_connected(2.5)
        assert session.status().link is LinkState.CONNECTING and session.status().rejected > 0


def test_setup_signing_installs_the_key(tmp_path):
    key_file = tmp_path / 'signing.key'
    key_file.write_text('ab' * 32)
    with pair('udp', signing_key_file=str(key_file), signing_required=False) as (vehicle, session):
        session.wait_connected(5.0)
        assert not session.status().vehicle_signs and not vehicle.truth().signing
        session.install_signing_key()
        assert vehicle.truth().signing and session.status().vehicle_signs
        gcs = _raw_gcs(vehicle.address[1])
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 9, 0, 0, 0, 0, 0)
        acks, _ = _acks_for(gcs, 254, 1.2)
        assert acks == [] and vehicle.truth().mode == 'STABILIZE'
        gcs.close()


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


def test_fence_zeroes_only_outward_components():
    from uav_vs.autopilot.session import fence_velocity
    lo, hi = (-5.0, -5.0, 0.5), (5.0, 5.0, 3.0)
    v = np.array([1.0, -1.0, 0.5])
    assert np.array_equal(fence_velocity(v, np.array([0.0, 0.0, 1.0]), lo, hi), v)       # inside
    assert np.array_equal(fence_velocity(v, np.array([5.2, 0.0, 1.0]), lo, hi), [0.0, -1.0, 0.5])
    assert np.array_equal(fence_velocity(-v, np.array([5.2, 0.0, 1.0]), lo, hi), -v)     # back in: allowed
    assert np.array_equal(fence_velocity(v, np.array([0.0, -5.0, 3.0]), lo, hi), [1.0, 0.0, 0.0])
    assert np.array_equal(fence_velocity(v, None, lo, hi), np.zeros(3))                 # no estimate: hover
