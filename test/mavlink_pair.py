"""A simulated vehicle and a MAVLink session connected to it, and the steps of a flight,
for the tests of the session (test_mavlink_session, test_mavlink_guards); a bare
autopilot streaming readiness telemetry."""
import contextlib
import time

import numpy as np

from uav_vs.autopilot.link import mavlink, open_connection
from uav_vs.autopilot.session import Session, SessionConfig
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


class ReadinessEndpoint:
    """A bare autopilot (ArduPilot or PX4 HEARTBEAT) streaming readiness telemetry with the
    values it is given, each message only once the session has asked for it with
    SET_MESSAGE_INTERVAL (their ids are recorded in `requested`)."""

    def __init__(self, autopilot):
        self.conn = open_connection('udpin:127.0.0.1:0', source_system=1, source_component=1)
        self.port = self.conn.port.getsockname()[1]
        self.autopilot, self.requested, self.next_send = autopilot, set(), 0.0
        self.prearm, self.ekf_flags, self.gps_fix = False, None, None   # None: never sent
        self.origins: list[tuple[int, int, int]] = []    # SET_GPS_GLOBAL_ORIGIN received
        self.answer_origin = False      # answer them with GPS_GLOBAL_ORIGIN

    def pump(self, until, timeout=5.0):
        end = time.monotonic() + timeout
        while not until():
            now = time.monotonic()
            assert now < end, 'the session never got there'
            if now >= self.next_send:
                self.next_send = now + 0.05
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, self.autopilot,
                                             mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0, 3)
                bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
                if mavlink.MAVLINK_MSG_ID_SYS_STATUS in self.requested:
                    self.conn.mav.sys_status_send(bit, bit, bit if self.prearm else 0, 0, 12600, -1,
                                                  -1, 0, 0, 0, 0, 0, 0)
                if self.ekf_flags is not None and mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT in self.requested:
                    self.conn.mav.ekf_status_report_send(self.ekf_flags, 0, 0, 0, 0, 0)
                if self.gps_fix is not None and mavlink.MAVLINK_MSG_ID_GPS_RAW_INT in self.requested:
                    self.conn.mav.gps_raw_int_send(0, self.gps_fix, 0, 0, 0, 0, 0, 0, 0, 0)
            msg = self.conn.recv_match(type=['COMMAND_LONG', 'SET_GPS_GLOBAL_ORIGIN'],
                                       blocking=True, timeout=0.01)
            if msg is None:
                continue
            if msg.get_type() == 'SET_GPS_GLOBAL_ORIGIN':
                self.origins.append((msg.latitude, msg.longitude, msg.altitude))
                if self.answer_origin:
                    self.conn.mav.gps_global_origin_send(msg.latitude, msg.longitude,
                                                         msg.altitude, msg.time_usec)
            elif msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                self.requested.add(int(msg.param1))
