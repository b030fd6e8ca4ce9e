"""What the MAVLink session guards, against the simulated ArduCopter and bare endpoints
over loopback: the autopilot's refusals and their reasons, readiness to arm, message
signing, and the geofence flown."""
import math
import time

import numpy as np
import pytest

from mavlink_pair import ReadinessEndpoint, fly, pair, settle, take_off, wait_for
from uav_vs.autopilot.link import load_signing_key, mavlink, open_connection
from uav_vs.autopilot.session import (AutopilotError, CommandError, Limits, LinkState, Session,
                                      SessionConfig)


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_refusal_reason_holds_only_statustext_sent_after_the_command(transport):
    with pair(transport, vehicle_cfg={'ready_delay': 60.0}, allow_arming=True) as (vehicle, session):
        session.wait_connected(5.0)
        with pytest.raises(CommandError) as err:
            session.set_guided()
        assert err.value.statustext == ['Mode change failed: GUIDED requires position']
        # that refusal's text is in, well within a second, when the arming is refused
        assert 'Mode change failed: GUIDED requires position' in session.status().statustext
        with pytest.raises(CommandError) as err:
            session.arm()
        assert err.value.statustext == ['PreArm: Need Position Estimate']
        assert 'Mode change' not in str(err.value)


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


def _raw_gcs(transport, port, system=254):
    """A GCS without the key. The simulator serves one TCP client, the newest: over TCP,
    close the session first or the two take the link from each other."""
    device = {'tcp': f'tcp:127.0.0.1:{port}', 'udp': f'udpout:127.0.0.1:{port}'}[transport]
    return open_connection(device, source_system=system)


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


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_signing_rejects_unsigned_traffic_both_ways(tmp_path, transport):
    key_file = tmp_path / 'signing.key'
    key_file.write_text('correct horse battery staple\n')
    key = load_signing_key(key_file)
    with pair(transport, vehicle_cfg={'signing_key': key}, allow_arming=True,
              signing_key_file=str(key_file)) as (vehicle, session):
        session.wait_connected(5.0)
        wait_for(lambda: session.status().prearm_ok, 5.0, 'a position (GUIDED needs one)')
        session.set_guided()
        assert vehicle.truth().mode == 'GUIDED'       # signed commands accepted, ACKs accepted
        status = session.status()
        assert status.signing and status.vehicle_signs and status.rejected_unsigned == 0
        if transport == 'tcp':
            session.close()
        gcs = _raw_gcs(transport, vehicle.address[1])
        gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0)
        acks, signed = _acks_for(gcs, 254, 1.5)
        assert acks == [] and vehicle.truth().mode == 'GUIDED'   # its unsigned command was dropped
        assert signed and all(signed)                             # and what it hears is signed
        gcs.close()
    # the other way: a vehicle that does not sign is not accepted by a session that requires it
    with pair(transport, signing_key_file=str(key_file)) as (vehicle, session):
        with pytest.raises(AutopilotError, match='timed out'):
            session.wait_connected(2.5)
        assert session.status().link is LinkState.CONNECTING and session.status().rejected_unsigned > 0


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_setup_signing_installs_the_key(tmp_path, transport):
    key_file = tmp_path / 'signing.key'
    key_file.write_text('ab' * 32)
    with pair(transport, signing_key_file=str(key_file), signing_required=False) as (vehicle, session):
        session.wait_connected(5.0)
        assert not session.status().vehicle_signs and not vehicle.truth().signing
        session.install_signing_key()
        assert vehicle.truth().signing and session.status().vehicle_signs
        if transport == 'tcp':
            session.close()
        gcs = _raw_gcs(transport, vehicle.address[1])
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 9, 0, 0, 0, 0, 0)
        acks, _ = _acks_for(gcs, 254, 1.2)
        assert acks == [] and vehicle.truth().mode == 'STABILIZE'
        gcs.close()


def test_setup_signing_is_refused_while_armed(tmp_path):
    key_file = tmp_path / 'signing.key'
    key_file.write_text('ab' * 32)
    with pair('udp', allow_arming=True, signing_key_file=str(key_file),
              signing_required=False) as (vehicle, session):
        session.wait_connected(5.0)
        wait_for(lambda: session.status().prearm_ok, 5.0, 'the pre-arm checks to pass')
        session.set_guided()
        session.arm()
        with pytest.raises(AutopilotError, match='refused while armed'):
            session.install_signing_key()
        time.sleep(0.3)
        assert vehicle.truth().armed and not vehicle.truth().signing
        assert not session.status().vehicle_signs
        session.disarm()                          # disarmed, the same call installs it
        session.install_signing_key()
        assert vehicle.truth().signing and session.status().vehicle_signs


def test_geofence_brakes_before_the_face_when_flying_straight_at_it():
    # east face 1 m from the takeoff point; 1.5 m/s east for 4 s would cross it by 5 m
    lo, hi = (-5.0, -5.0, 0.0), (1.0, 5.0, 3.0)
    with pair('udp', allow_arming=True, limits=Limits(fence_min=lo, fence_max=hi)) as (vehicle, session):
        take_off(session, vehicle)
        wait_for(lambda: session.telemetry().position is not None, 3.0, 'the position estimate')
        east = []
        end = time.monotonic() + 4.0
        while time.monotonic() < end:
            assert session.send_velocity([1.5, 0.0, 0.0], 0.0)
            east.append(vehicle.truth().position[1])       # NED: east is index 1
            time.sleep(0.02)
        settle(vehicle)
        east.append(vehicle.truth().position[1])
        assert max(east) <= hi[0] + 0.01                   # never past the face
        assert east[-1] >= hi[0] - 0.1                     # but close up to it


def test_geofence_zeroes_outward_commands_at_the_face_and_lets_inward_ones_through():
    # east face at x = 0 m, where the copter takes off (NED east stays exactly 0 in the climb)
    lo, hi = (-5.0, -5.0, 0.0), (0.0, 5.0, 3.0)
    with pair('udp', allow_arming=True, limits=Limits(fence_min=lo, fence_max=hi)) as (vehicle, session):
        take_off(session, vehicle)
        wait_for(lambda: session.telemetry().position is not None
                 and session.telemetry().orientation is not None, 3.0, 'the position estimate')
        p0 = vehicle.truth().position
        assert p0[1] == 0.0 and vehicle.truth().yaw == 0.0      # on the face, nose north
        t0 = time.monotonic()
        fly(session, [1.0, 0.0, 0.0], duration=0.8)              # world: east, straight out
        fly(session, [0.0, -1.0, 0.0], body=True, duration=0.8)  # body right: east, nose north
        fly(session, [0.8, 0.6, 0.0])                            # east and north: only north flown
        settle(vehicle)
        moved = vehicle.truth().position - p0
        assert abs(moved[1]) < 1e-6 and vehicle.truth().position[1] <= hi[0]  # never out east
        assert math.isclose(moved[0], 0.6 * vehicle.moving_time(since=t0), abs_tol=0.05)
        assert abs(moved[2]) < 0.03
        sent = vehicle.targets(since=t0)
        assert sent and all(t.velocity[1] == 0.0 for t in sent)   # NED east: zeroed on the wire
        assert any(t.velocity[0] > 0.5 for t in sent)

        # inward (west, 0.5 m/s for 1.2 s): flown
        p0, t0 = vehicle.truth().position, time.monotonic()
        fly(session, [-0.5, 0.0, 0.0])
        settle(vehicle)
        assert np.allclose(vehicle.truth().position - p0,
                           [0.0, -0.5 * vehicle.moving_time(since=t0), 0.0], atol=0.05)


def test_ardupilot_is_ready_to_arm_only_with_prearm_bit_ekf_flags_and_3d_fix():
    ap = ReadinessEndpoint(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    with Session(SessionConfig(connection=f'udpout:127.0.0.1:{ap.port}')) as session:
        def reasons(*expected):
            ap.pump(lambda: session.status().prearm_reasons == expected)
            return session.status().prearm_ok
        assert reasons('SYS_STATUS pre-arm check not passed', 'no EKF_STATUS_REPORT yet',
                       'no GPS_RAW_INT yet') is False
        ap.prearm, ap.ekf_flags, ap.gps_fix = True, 0x1 | 0x10, mavlink.GPS_FIX_TYPE_3D_FIX
        # the pre-arm bit alone is not enough (the bit is all the relay used to read)
        assert reasons('EKF_STATUS_REPORT flags 0x11 lack EKF_PRED_POS_HORIZ_ABS') is False
        ap.ekf_flags, ap.gps_fix = 0x33F, mavlink.GPS_FIX_TYPE_2D_FIX
        assert reasons('GPS fix GPS_FIX_TYPE_2D_FIX, needs 3D') is False
        ap.ekf_flags = 0x0F   # no absolute horizontal position at all
        assert reasons('EKF_STATUS_REPORT flags 0xf lack EKF_POS_HORIZ_ABS, EKF_PRED_POS_HORIZ_ABS',
                       'GPS fix GPS_FIX_TYPE_2D_FIX, needs 3D') is False
        ap.ekf_flags, ap.gps_fix = 0x33F, mavlink.GPS_FIX_TYPE_RTK_FIXED
        assert reasons() is True
        assert {mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT,
                mavlink.MAVLINK_MSG_ID_SYS_STATUS} <= ap.requested
        assert mavlink.MAVLINK_MSG_ID_ODOMETRY not in ap.requested      # ArduPilot sends none
    ap.conn.close()


def test_without_gps_the_origin_is_sent_until_answered_and_stands_in_for_the_gps_fix():
    """ArduPilot on external navigation: no GPS fix ever, but no arming before the EKF
    has taken an origin (an EKF still starting ignores one: it is sent again)."""
    ap = ReadinessEndpoint(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    ap.prearm, ap.ekf_flags, ap.gps_fix = True, 0x33F, mavlink.GPS_FIX_TYPE_NO_GPS
    config = SessionConfig(connection=f'udpout:127.0.0.1:{ap.port}',
                           ekf_origin=(-35.363261, 149.16523, 584.0))
    with Session(config) as session:
        ap.pump(lambda: len(ap.origins) >= 2, timeout=5.0)
        status = session.status()
        assert status.prearm_reasons == (
            'EKF origin not set yet (SET_GPS_GLOBAL_ORIGIN unanswered)',)
        assert status.ekf_origin_set is False and status.ekf.flags == 0x33F
        assert status.ekf.navigating
        assert ap.origins[-1] == (-353632610, 1491652300, 584000)   # 1e-7 deg, mm
        ap.answer_origin = True
        ap.pump(lambda: session.status().prearm_ok, timeout=5.0)
        assert session.status().ekf_origin_set is True
        answered = len(ap.origins)
        later = time.monotonic() + 2.5
        ap.pump(lambda: time.monotonic() > later)
        assert len(ap.origins) == answered            # no more once taken
    ap.conn.close()


def test_an_ekf_origin_off_the_earth_is_refused():
    with pytest.raises(ValueError, match='ekf_origin must be latitude'):
        Session(SessionConfig(connection='udpout:127.0.0.1:14550', ekf_origin=(95.0, 0.0, 0.0)))


def test_px4_readiness_is_its_prearm_bit_and_no_ekf_status_report_is_requested():
    px4 = ReadinessEndpoint(mavlink.MAV_AUTOPILOT_PX4)   # PX4 sends no EKF_STATUS_REPORT
    px4.gps_fix = mavlink.GPS_FIX_TYPE_NO_GPS            # e.g. flying on vision (if asked)
    with Session(SessionConfig(connection=f'udpout:127.0.0.1:{px4.port}')) as session:
        px4.pump(lambda: session.status().prearm_reasons == ('SYS_STATUS pre-arm check not passed',))
        assert session.status().prearm_ok is False
        px4.prearm = True
        px4.pump(lambda: session.status().prearm_ok)
        assert session.status().prearm_reasons == ()
        assert mavlink.MAVLINK_MSG_ID_SYS_STATUS in px4.requested
        assert not {mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT} & px4.requested
        assert mavlink.MAVLINK_MSG_ID_ODOMETRY in px4.requested           # its covariances
    px4.conn.close()


def test_simulated_copter_becomes_ready_to_arm_at_its_ready_delay():
    with pair('udp', vehicle_cfg={'ready_delay': 2.5}) as (vehicle, session):
        session.wait_connected(5.0)
        wait_for(lambda: not any('yet' in r for r in session.status().prearm_reasons), 3.0,
                 'the readiness telemetry')
        status = session.status()
        assert status.prearm_ok is False and status.prearm_reasons == (
            'SYS_STATUS pre-arm check not passed',
            'EKF_STATUS_REPORT flags 0xa5 lack EKF_POS_HORIZ_ABS, EKF_PRED_POS_HORIZ_ABS',
            'GPS fix GPS_FIX_TYPE_NO_FIX, needs 3D')
        wait_for(lambda: session.status().prearm_ok, 4.0, 'ready to arm')
        assert session.status().prearm_reasons == ()
