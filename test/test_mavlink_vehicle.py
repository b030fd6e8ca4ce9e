"""The simulated ArduCopter on its own, driven by a bare pymavlink GCS (not the relay).

Checks the Copter behaviour the relay has to cope with: no streams until asked,
readiness (pre-arm bit, EKF flags, GPS fix), ACK codes and reasons, velocity targets
ignored on the ground, aborting a takeoff, GUID_TIMEOUT coasting, silent stop-and-hold
on bad targets, nose-into-travel when yaw is ignored, SETUP_SIGNING ignored while armed,
and the console script as a process; then what its PX4 personality does differently
(unasked streams, main/sub modes, OFFBOARD only with a setpoint stream and the hold when
it stops, AMSL takeoff ending in AUTO.LOITER).
"""
import math
import subprocess
import sys
import time

import numpy as np

from uav_vs.autopilot.link import mavlink, open_connection
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig
from uav_vs.sim.sitl_truth import SitlTruth

VEL_YAW_RATE, VEL_ONLY = 0x05C7, 0x0DC7


class Gcs:
    """A bare GCS over UDP: send commands, wait for their ACK."""

    def __init__(self, port: int):
        self.conn = open_connection(f'udpout:127.0.0.1:{port}', source_system=250)
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def command(self, command, *params):
        """MAV_RESULT of a COMMAND_LONG; STATUSTEXT seen meanwhile goes to self.texts."""
        p = (list(params) + [0.0] * 7)[:7]
        self.conn.mav.command_long_send(1, 1, command, 0, *p)
        self.texts = []
        while (msg := self.conn.recv_match(type=['COMMAND_ACK', 'STATUSTEXT'], blocking=True,
                                           timeout=2.0)) is not None:
            if msg.get_type() == 'STATUSTEXT':
                self.texts.append(msg.text)
            elif msg.command == command:
                return msg.result
        raise AssertionError(f'no ACK for {command}')

    def target(self, v, yaw_rate=0.0, frame=mavlink.MAV_FRAME_LOCAL_NED, mask=VEL_YAW_RATE):
        self.conn.mav.set_position_target_local_ned_send(0, 1, 1, frame, mask, 0, 0, 0, *v, 0, 0, 0, 0, yaw_rate)

    def collect(self, seconds):
        end, out = time.monotonic() + seconds, []
        while time.monotonic() < end:
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() != 'BAD_DATA':
                out.append(msg)
        return out

    def close(self):
        self.conn.close()


def vehicle(**kw):
    return MavlinkVehicle(VehicleConfig(connection='udpin:127.0.0.1:0', **{'ready_delay': 0.0, **kw}))


def wait_for(predicate, timeout, what):
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, f'timed out waiting for {what}'
        time.sleep(0.02)


def airborne(sim, gcs, height=1.0):
    assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, height) == mavlink.MAV_RESULT_ACCEPTED
    wait_for(lambda: -sim.truth().position[2] > height - 0.03 and abs(sim.truth().velocity[2]) < 0.02,
             6.0, 'takeoff')


def test_streams_start_only_when_requested_and_ack_codes():
    with vehicle(ready_delay=0.3) as sim:
        gcs = Gcs(sim.address[1])
        kinds = {m.get_type() for m in gcs.collect(1.2)}
        assert kinds <= {'HEARTBEAT', 'STATUSTEXT'} and 'HEARTBEAT' in kinds
        ok = mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100000) == ok
        assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, 100000) == mavlink.MAV_RESULT_FAILED
        assert gcs.command(mavlink.MAV_CMD_DO_REPOSITION) == mavlink.MAV_RESULT_UNSUPPORTED
        stamps = [m.time_boot_ms for m in gcs.collect(1.0) if m.get_type() == 'LOCAL_POSITION_NED']
        assert len(stamps) > 3 and 80 <= np.median(np.diff(stamps)) <= 120  # 10 Hz on its own clock
        assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, -1) == ok
        gcs.collect(0.1)
        assert not [m for m in gcs.collect(0.5) if m.get_type() == 'LOCAL_POSITION_NED']
        gcs.close()


def test_readiness_reports_stream_when_asked_and_turn_good_at_ready_delay():
    with vehicle(ready_delay=1.5) as sim:
        gcs = Gcs(sim.address[1])
        kinds = {m.get_type() for m in gcs.collect(0.3)}
        assert not kinds & {'EKF_STATUS_REPORT', 'GPS_RAW_INT', 'SYS_STATUS'}
        for msg_id in (mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT,
                       mavlink.MAVLINK_MSG_ID_SYS_STATUS):
            assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 100000) == mavlink.MAV_RESULT_ACCEPTED
        seen = gcs.collect(2.0)     # across ready_delay: 'EKF3 IMU0 is using GPS' marks it
        ready = [k for k, m in enumerate(seen) if m.get_type() == 'STATUSTEXT'
                 and m.text == 'EKF3 IMU0 is using GPS']
        assert len(ready) == 1
        before, after = seen[:ready[0]], seen[ready[0]:]

        def values(msgs, kind, field):
            return [getattr(m, field) for m in msgs if m.get_type() == kind]
        bit, good = mavlink.MAV_SYS_STATUS_PREARM_CHECK, 0x10 | 0x200
        for msgs, ok in ((before, False), (after, True)):
            ekf = values(msgs, 'EKF_STATUS_REPORT', 'flags')
            fix = values(msgs, 'GPS_RAW_INT', 'fix_type')
            health = values(msgs, 'SYS_STATUS', 'onboard_control_sensors_health')
            assert len(ekf) >= 3 and len(fix) >= 3 and len(health) >= 3
            assert all((f & good == good) is ok for f in ekf), ekf
            assert all((f >= 3) is ok for f in fix), fix
            assert all(bool(h & bit) is ok for h in health), health
        gcs.close()


def test_arming_rules():
    with vehicle(ready_delay=0.8, disarm_delay=0.5) as sim:
        gcs = Gcs(sim.address[1])
        arm, failed = mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_FAILED
        assert gcs.command(arm, 1) == failed and gcs.texts == ['PreArm: Need Position Estimate']
        gcs.conn.recv_match(type='STATUSTEXT', condition='STATUSTEXT.text=="EKF3 IMU0 is using GPS"',
                            blocking=True, timeout=2.0)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 9) == mavlink.MAV_RESULT_ACCEPTED  # LAND
        assert gcs.command(arm, 1) == failed and gcs.texts == ['Arm: Mode not armable']
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0) == mavlink.MAV_RESULT_ACCEPTED  # STABILIZE
        assert gcs.command(arm, 1) == mavlink.MAV_RESULT_ACCEPTED and sim.truth().armed
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == failed  # not GUIDED
        wait_for(lambda: not sim.truth().armed, 2.0, 'auto-disarm without takeoff')
        gcs.close()


def test_guided_targets_ground_takeoff_abort_and_guid_timeout():
    with vehicle() as sim:
        gcs = Gcs(sim.address[1])
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        gcs.target((1.0, 0.0, -1.0))            # on the ground: ignored
        time.sleep(0.3)
        assert np.allclose(sim.truth().position, 0.0)
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0) == mavlink.MAV_RESULT_ACCEPTED
        wait_for(lambda: -sim.truth().position[2] > 0.5, 3.0, 'climbing')
        gcs.target((0.0, 0.0, 0.0))             # aborts the climb
        wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 0.02, 3.0, 'stop')
        assert -sim.truth().position[2] < 2.0
        p0 = sim.truth().position
        gcs.target((1.0, 0.0, 0.0))             # one target, then silence: flown for GUID_TIMEOUT
        time.sleep(2.0)
        assert sim.truth().velocity[0] > 0.95   # still going after 2 s
        wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 0.02, 4.0, 'stop after GUID_TIMEOUT')
        assert math.isclose((sim.truth().position - p0)[0], 3.0, abs_tol=0.15)
        gcs.close()


def hold(sim, gcs, seconds):
    """Stream a zero velocity target for `seconds`; the truth every 0.1 s and every
    LOCAL_POSITION_NED received meanwhile."""
    truths, reported = [], []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        gcs.target((0.0, 0.0, 0.0))
        reported += [m for m in gcs.collect(0.1) if m.get_type() == 'LOCAL_POSITION_NED']
        truths.append(sim.truth())
    return truths, reported


def test_gusts_push_a_holding_vehicle():
    sigma, tau = 0.3, 0.5
    with vehicle(gust_sigma=sigma, gust_time_constant=tau, seed=3) as sim:
        gcs = Gcs(sim.address[1])
        time.sleep(0.5)
        assert np.all(sim.truth().position == 0.0)          # no gusts on the ground
        airborne(sim, gcs, height=2.0)
        truths, _ = hold(sim, gcs, 6.0)
        v = np.array([t.velocity for t in truths])
        # the gust is the ground velocity of a vehicle told to hold: spread sigma, level
        assert 0.5 * sigma < v[:, :2].std() < 1.6 * sigma
        assert np.abs(v[:, 2]).max() < 0.05
        moved = truths[-1].position - truths[0].position
        assert np.linalg.norm(moved[:2]) > 0.02 and abs(moved[2]) < 0.05
        gcs.close()


def test_land_holds_where_it_began_against_a_push():
    # A steady 0.1 m/s east push the velocity loop does not reject (the gust state, set
    # directly; no random gusts). LAND's position hold (land_hold_gain k = 1/s) settles
    # push / k = 0.1 m downwind of where LAND began, within the ~0.7 s of its loop; a
    # vehicle without it drifts at 0.1 m/s through the whole 4 s descent (0.4 m).
    push, gain = 0.1, VehicleConfig.land_hold_gain
    with vehicle() as sim:
        gcs = Gcs(sim.address[1])
        airborne(sim, gcs, height=2.0)
        start = sim.truth().position.copy()
        sim._gust[:2] = (0.0, push)
        assert gcs.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
        wait_for(lambda: not sim.truth().flying, 10.0, 'touchdown')
        moved = sim.truth().position[:2] - start[:2]
        assert abs(moved[0]) < 0.005 and 0.9 * push / gain < moved[1] < 1.05 * push / gain, moved
        gcs.close()


def test_the_reported_position_drifts_from_the_truth_and_gps_stays_true():
    rate = 0.05
    with vehicle(drift_rate=rate, seed=4) as sim:
        gcs = Gcs(sim.address[1])
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT):
            assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 50000) == \
                mavlink.MAV_RESULT_ACCEPTED
        airborne(sim, gcs, height=2.0)
        wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 1e-4, 4.0, 'the end of the climb')
        gcs.collect(0.3)                                    # what was sent on the climb
        truths, reported = hold(sim, gcs, 6.0)
        p = truths[-1].position                             # still air: it holds still
        assert np.linalg.norm(p - truths[0].position) < 1e-3
        gaps = np.array([[m.x, m.y, m.z] for m in reported]) - p
        # a random walk of rate * sqrt(t), t ~ 8 s since the start: neither zero nor far
        assert np.abs(gaps).max() > 0.01 and np.abs(gaps).max() < 8 * rate * np.sqrt(8.0)
        assert np.abs(np.diff(gaps, axis=0)).max() < 0.07  # it wanders, it does not jump
        gps = [m for m in gcs.collect(0.3) if m.get_type() == 'GPS_RAW_INT'][-1]
        assert abs(gps.alt / 1e3 - (VehicleConfig.home[2] - p[2])) < 0.002
        gcs.close()


def test_the_truth_port_serves_sim_state_as_sitl_does_and_ignores_a_cut_link():
    with vehicle(truth_connection='udpin:127.0.0.1:0', gust_sigma=0.2, drift_rate=0.05,
                 seed=2) as sim:
        truth = SitlTruth(f'udpout:127.0.0.1:{sim.truth_address[1]}').start()
        try:
            truth.wait(10.0)                     # asked SIM_STATE at 50 Hz, as of SITL
            gcs = Gcs(sim.address[1])
            airborne(sim, gcs, height=1.5)
            gcs.target((0.3, -0.2, 0.0), yaw_rate=0.2)
            time.sleep(1.0)
            sim.cut_link()                       # the radio, not the world's port
            time.sleep(0.5)
            true, seen = sim.truth(), truth.state()
            # ENU seen against NED simulated, both at their own instant, moving < 1 m/s
            assert np.allclose(seen.position, [true.position[1], true.position[0],
                                               -true.position[2]], atol=0.05), seen.position
            assert abs(math.remainder(seen.yaw - (math.pi / 2 - true.yaw), 2 * math.pi)) < 0.05
            assert seen.armed and seen.mode == 'GUIDED' and seen.flying
            gcs.close()
        finally:
            truth.close()


def test_bad_targets_hold_and_yaw_follows_travel_when_ignored():
    with vehicle() as sim:
        gcs = Gcs(sim.address[1])
        airborne(sim, gcs)
        for bad in ((math.nan, 0.0, 0.0), (1500.0, 0.0, 0.0)):
            gcs.target((1.0, 0.0, 0.0))
            wait_for(lambda: sim.truth().velocity[0] > 0.5, 2.0, 'moving')
            gcs.target(bad)                     # stop and hold, no error
            wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 0.02, 2.0, 'hold')
        gcs.target((1.0, 0.0, 0.0))
        wait_for(lambda: sim.truth().velocity[0] > 0.5, 2.0, 'moving')
        gcs.target((1.0, 0.0, 0.0), frame=mavlink.MAV_FRAME_GLOBAL)  # unsupported frame
        wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 0.02, 2.0, 'hold')
        # yaw and yaw rate ignored: the nose turns to the travel direction (east: +pi/2)
        for _ in range(25):
            gcs.target((0.0, 0.5, 0.0), mask=VEL_ONLY)
            time.sleep(0.08)
        assert math.isclose(sim.truth().yaw, math.pi / 2, abs_tol=0.1)
        # heading-aligned body frame: forward is now east
        gcs.target((0.0, 0.0, 0.0))
        wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 0.02, 2.0, 'hold')
        gcs.target((0.8, 0.0, 0.0), frame=mavlink.MAV_FRAME_BODY_OFFSET_NED)
        wait_for(lambda: sim.truth().velocity[1] > 0.7, 2.0, 'flying east')
        assert abs(sim.truth().velocity[0]) < 0.1
        gcs.close()


def test_setup_signing_is_ignored_while_armed():
    key = bytes(range(32))
    with vehicle() as sim:
        gcs = Gcs(sim.address[1])
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        gcs.conn.mav.setup_signing_send(1, 1, list(key), 1)
        heartbeats = [m for m in gcs.collect(1.2) if m.get_type() == 'HEARTBEAT']   # no ACK, by design
        assert heartbeats and sim.truth().armed and not sim.truth().signing
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_ACCEPTED
        gcs.conn.mav.setup_signing_send(1, 1, list(key), 1)   # disarmed: installed
        wait_for(lambda: sim.truth().signing, 1.0, 'the key to be installed')
        gcs.close()


def test_link_cut_and_console_script():
    with vehicle() as sim:
        gcs = Gcs(sim.address[1])
        assert gcs.collect(1.1)
        sim.cut_link()
        gcs.collect(0.05)
        assert gcs.collect(1.2) == []
        sim.restore_link()
        assert any(m.get_type() == 'HEARTBEAT' for m in gcs.collect(1.2))
        gcs.close()
    proc = subprocess.Popen([sys.executable, '-m', 'uav_vs.sim.mavlink_vehicle', '--connection',
                             'tcpin:127.0.0.1:0', '--ready-delay', '0'], stdout=subprocess.PIPE, text=True)
    try:
        port = int(proc.stdout.readline().split('(')[1].split(')')[0].split(':')[1])
        client = open_connection(f'tcp:127.0.0.1:{port}')
        hb = client.recv_match(type='HEARTBEAT', blocking=True, timeout=3.0)
        assert hb is not None and hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        client.close()
    finally:
        proc.terminate()
        proc.wait(timeout=5)


# ------------------------------------------------------------------ PX4 personality

def px4_mode(main, sub=0):
    """DO_SET_MODE params of a PX4 mode: custom-mode flag, main mode, sub mode."""
    return 1, main, sub


def stream(gcs, seconds, v=(0.0, 0.0, 0.0), rate=10.0) -> float:
    """Velocity setpoints at `rate` for `seconds` (the offboard signal); the time the last
    one was sent."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        gcs.target(v, mask=VEL_ONLY)
        sent = time.monotonic()
        gcs.collect(1.0 / rate)
    return sent


def test_px4_streams_unasked_and_encodes_its_modes_as_main_and_sub():
    with vehicle(autopilot='px4', ready_delay=0.3) as sim:
        gcs = Gcs(sim.address[1])
        seen = gcs.collect(1.5)
        kinds = {m.get_type() for m in seen}
        assert {'HEARTBEAT', 'SYS_STATUS', 'ATTITUDE', 'GLOBAL_POSITION_INT'} <= kinds
        assert 'EKF_STATUS_REPORT' not in kinds
        beat = [m for m in seen if m.get_type() == 'HEARTBEAT'][-1]
        assert beat.autopilot == mavlink.MAV_AUTOPILOT_PX4 and beat.custom_mode == 3 << 16  # POSCTL
        assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 100000) == mavlink.MAV_RESULT_FAILED
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, *px4_mode(4, 3)) == mavlink.MAV_RESULT_ACCEPTED
        assert sim.truth().mode == 'LOITER'
        beat = gcs.conn.recv_match(type='HEARTBEAT', blocking=True, timeout=2.0)
        assert beat.custom_mode == 4 << 16 | 3 << 24            # AUTO.LOITER
        gcs.close()


def test_px4_offboard_needs_a_second_of_setpoints_and_falls_back_to_hold_without_them():
    with vehicle(autopilot='px4', disarm_delay=30.0) as sim:
        gcs = Gcs(sim.address[1])
        offboard, rejected = px4_mode(6), mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == rejected
        assert gcs.texts == ['Switching to Offboard is currently not possible']
        arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
        assert gcs.command(arm, 1) == rejected                   # POSCTL needs RC
        stream(gcs, 0.5)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == rejected   # too short
        stream(gcs, 1.2)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(arm, 1) == mavlink.MAV_RESULT_ACCEPTED
        # AMSL takeoff altitude: home 584 m + 1.5 m; climbs in AUTO.TAKEOFF, then holds.
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan,
                           585.5) == mavlink.MAV_RESULT_ACCEPTED
        assert sim.truth().mode == 'TAKEOFF'
        wait_for(lambda: sim.truth().mode == 'LOITER', 6.0, 'AUTO.LOITER after the climb')
        assert abs(-sim.truth().position[2] - 1.5) < 0.03
        stream(gcs, 1.5, (0.5, 0.0, 0.0))                        # not flown in LOITER
        assert np.linalg.norm(sim.truth().velocity) < 0.01
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == mavlink.MAV_RESULT_ACCEPTED
        n0 = sim.truth().position[0]
        last = stream(gcs, 1.0, (0.5, 0.0, 0.0))
        assert sim.truth().position[0] - n0 > 0.2                # north, in OFFBOARD
        # The stream stops (companion computer gone): after COM_OF_LOSS_T, hold.
        wait_for(lambda: sim.truth().mode == 'LOITER', 2.0, 'offboard loss failsafe')
        assert 0.95 < time.monotonic() - last < 1.5
        wait_for(lambda: np.linalg.norm(sim.truth().velocity) < 0.02, 3.0, 'the hold')
        assert gcs.command(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan) == mavlink.MAV_RESULT_ACCEPTED
        assert sim.truth().mode == 'LAND'
        wait_for(lambda: not sim.truth().armed, 6.0, 'landing and disarming')
        assert sim.truth().position[2] == 0.0
        gcs.close()
