"""SitlTruth turns SITL's SIM_STATE into base_link in world, checked against a SITL
stand-in on a local port that sends known states (analytic truth: a flat-earth offset,
NED to ENU, Euler angles to a rotation)."""
import math
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uav_vs.autopilot.link import mavlink
from uav_vs.sim.mavlink_vehicle import _TcpServer
from uav_vs.sim.sitl_truth import M_PER_E7_DEG, SitlTruth, latlon_to_ned

LAT0, LON0, ALT0 = -353632610, 1491652299, 584.09


def test_latlon_offsets_are_flat_earth_metres():
    ned = latlon_to_ned(LAT0 + 1000, LON0 - 2000, ALT0 + 1.5, (LAT0, LON0, ALT0))
    cos_lat = math.cos(math.radians(LAT0 * 1e-7))
    np.testing.assert_allclose(ned, [1000 * M_PER_E7_DEG, -2000 * M_PER_E7_DEG * cos_lat, -1.5])
    assert ned[0] == pytest.approx(11.13, abs=0.01)     # 1e-4 degree of latitude


class FakeSitl:
    """Sends HEARTBEAT, EXTENDED_SYS_STATE and SIM_STATE of `self.sim` at 50 Hz once asked."""

    def __init__(self) -> None:
        self.conn = _TcpServer('127.0.0.1:0', source_system=1, source_component=1)
        self.port = self.conn.listen.getsockname()[1]
        self.sim = dict(lat=LAT0, lon=LON0, alt=ALT0, roll=0.0, pitch=0.0, yaw=0.0,
                        vn=0.0, ve=0.0, vd=0.0)
        self.asked: set[int] = set()
        self.stop = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self.stop.is_set():
            while (msg := self.conn.recv_msg()) is not None:
                if msg.get_type() == 'COMMAND_LONG' and \
                        msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                    self.asked.add(int(msg.param1))
            if self.conn.port is not None:
                self._send()
            time.sleep(0.02)

    def _send(self) -> None:
        mav, s = self.conn.mav, self.sim
        mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                           mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                           | mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, mavlink.MAV_STATE_ACTIVE)
        if mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE in self.asked:
            mav.extended_sys_state_send(0, mavlink.MAV_LANDED_STATE_IN_AIR)
        if mavlink.MAVLINK_MSG_ID_SIM_STATE in self.asked:
            q = Rotation.from_euler('ZYX', [s['yaw'], s['pitch'], s['roll']]).as_quat()
            mav.sim_state_send(q[3], q[0], q[1], q[2], s['roll'], s['pitch'], s['yaw'],
                               0, 0, -9.8, 0, 0, 0, float(s['lat']), float(s['lon']), s['alt'],
                               0, 0, s['vn'], s['ve'], s['vd'], s['lat'], s['lon'])

    def close(self) -> None:
        self.stop.set()
        self.conn.close()


@pytest.fixture
def sitl():
    fake = FakeSitl()
    yield fake
    fake.close()


def test_sim_state_is_base_link_in_world_from_the_first_position(sitl):
    truth = SitlTruth(f'tcp:127.0.0.1:{sitl.port}').start()
    try:
        first = truth.wait(10.0).latest()
        np.testing.assert_allclose(first.position, 0.0, atol=1e-9)     # the origin
        sitl.sim.update(lat=LAT0 + 900, lon=LON0 + 450, alt=ALT0 + 2.0, roll=0.1, pitch=-0.2,
                        yaw=0.3, vn=1.0, ve=-0.5, vd=-0.25)
        deadline = time.monotonic() + 5.0
        while truth.latest().position[2] < 1.0 and time.monotonic() < deadline:
            time.sleep(0.02)
        s = truth.latest()
        north = 900 * M_PER_E7_DEG
        east = 450 * M_PER_E7_DEG * math.cos(math.radians(LAT0 * 1e-7))
        np.testing.assert_allclose(s.position, [east, north, 2.0], atol=1e-6)   # ENU
        np.testing.assert_allclose(s.velocity, [-0.5, 1.0, 0.25], atol=1e-6)
        assert s.yaw == pytest.approx(math.pi / 2 - 0.3)
        # base_link (FLU) in world (ENU) from FRD in NED: R = R_enu_ned R_ned_frd R_frd_flu
        R_ned_frd = Rotation.from_euler('ZYX', [0.3, -0.2, 0.1]).as_matrix()
        swap, flip = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]]), np.diag([1, -1, -1])
        np.testing.assert_allclose(s.R, swap @ R_ned_frd @ flip, atol=1e-6)
        assert s.armed and s.mode == 'GUIDED' and s.flying
        # Sampled between two SIM_STATEs, the state is moved on by its velocity.
        later = truth.state()
        np.testing.assert_allclose(later.position, s.position + (later.time - s.time) * s.velocity,
                                   atol=1e-9)
        assert {mavlink.MAVLINK_MSG_ID_SIM_STATE,
                mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE} <= sitl.asked
    finally:
        truth.close()


def test_no_sim_state_is_a_timeout_naming_the_port(sitl):
    sitl._send = lambda: None               # a port that never sends SIM_STATE
    truth = SitlTruth(f'tcp:127.0.0.1:{sitl.port}').start()
    try:
        with pytest.raises(TimeoutError, match=f'no SIM_STATE from tcp:127.0.0.1:{sitl.port}'):
            truth.wait(1.0)
    finally:
        truth.close()
