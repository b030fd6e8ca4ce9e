"""The vehicle's truth from ArduPilot SITL (chapter section 5 with the real autopilot).

ArduPilot's SITL streams its physics model's own state as SIM_STATE (MAVLink 108):
attitude, NED velocity and the position as latitude, longitude and altitude, none of it
from the EKF. SitlTruth reads it, with HEARTBEAT (mode, armed) and EXTENDED_SYS_STATE
(landed or in the air), on a MAVLink port of its own (SITL's SERIAL1 or SERIAL2; the
relay keeps SERIAL0), and gives the world's VehicleState: base_link (FLU) in `world`
(ENU) whose origin is where the vehicle stood when the first SIM_STATE came, on the
ground, as the autopilot's home is; or, for one of several vehicles, that home placed at
`start` (x, y) in world.

SIM_STATE carries no time stamp: a sample is dated when it is read, so the link must be
local (SITL on this machine) and the SITL run at real time (speed-up 1) for the cameras'
stamps to mean the autopilot's time.
"""
import math
import threading
import time
from collections.abc import Sequence

import numpy as np
from pymavlink import mavutil
from scipy.spatial.transform import Rotation

from uav_vs.autopilot.frames import attitude_ned_to_enu, ned_to_enu, yaw_ned_to_enu
from uav_vs.autopilot.link import mavlink, open_connection
from uav_vs.sim.world import VehicleState

# Metres per 1e-7 degree of latitude (WGS-84 equatorial radius, as ArduPilot's
# LOCATION_SCALING_FACTOR); a degree of longitude is cos(latitude) of it.
M_PER_E7_DEG = 0.011131884502145034
SIM_STATE_RATE = 50.0          # Hz asked of SITL
_ASK_EVERY = 1.0               # s: streams are asked for again until they flow
_STALE_S = 1.0                 # no SIM_STATE for this long: the link is down


class SitlTruth:
    """SIM_STATE truth read by a thread from `connection` (tcp:HOST:PORT or udpin:...)."""

    def __init__(self, connection: str, target_system: int = 1, source_system: int = 253,
                 start: Sequence[float] = (0.0, 0.0)):
        self._start = np.array([start[0], start[1], 0.0])
        self._conn = open_connection(connection, source_system=source_system,
                                     source_component=mavlink.MAV_COMP_ID_PATHPLANNER)
        self.connection, self.target = connection, target_system
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._origin: tuple[float, float, float] | None = None   # lat, lon (1e-7 deg), alt m
        self._state: VehicleState | None = None
        self._received = -math.inf
        self._armed, self._mode, self._flying = False, 'UNKNOWN', False
        self._thread = threading.Thread(target=self._run, name='sitl-truth', daemon=True)

    def start(self) -> 'SitlTruth':
        self._thread.start()
        return self

    def wait(self, timeout: float) -> 'SitlTruth':
        """Return once the first SIM_STATE has come; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while self.latest() is None:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise TimeoutError(f'no SIM_STATE from {self.connection} in {timeout:g} s '
                                   '(is it ArduPilot SITL, and this its own port?)')
            time.sleep(0.02)
        return self

    @property
    def link_up(self) -> bool:
        return time.monotonic() - self._received < _STALE_S

    def latest(self) -> VehicleState | None:
        with self._lock:
            return self._state

    def state(self) -> VehicleState:
        """The newest sample, moved on by its velocity to now (SIM_STATE comes at 50 Hz,
        the cameras sample it at their own rate)."""
        s = self.latest()
        if s is None:
            raise RuntimeError(f'no SIM_STATE from {self.connection} yet')
        now = time.monotonic()
        return VehicleState(now, s.position + (now - s.time) * s.velocity, s.velocity, s.yaw,
                            s.R, s.armed, s.mode, s.flying)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._conn.close()

    def _run(self) -> None:
        asked = -math.inf
        while not self._stop.is_set():
            if time.monotonic() - asked > _ASK_EVERY and not self.link_up:
                self._ask_streams()
                asked = time.monotonic()
            msg = self._conn.recv_match(type=['SIM_STATE', 'HEARTBEAT', 'EXTENDED_SYS_STATE'],
                                        blocking=True, timeout=0.1)
            if msg is None or msg.get_srcSystem() != self.target:
                continue
            kind = msg.get_type()
            if kind == 'HEARTBEAT' and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1:
                self._armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self._mode = mavutil.mode_string_v10(msg)
            elif kind == 'EXTENDED_SYS_STATE':
                self._flying = msg.landed_state in (mavlink.MAV_LANDED_STATE_IN_AIR,
                                                    mavlink.MAV_LANDED_STATE_TAKEOFF,
                                                    mavlink.MAV_LANDED_STATE_LANDING)
            elif kind == 'SIM_STATE':
                self._on_sim_state(msg)

    def _ask_streams(self) -> None:
        for msg_id, rate in ((mavlink.MAVLINK_MSG_ID_SIM_STATE, SIM_STATE_RATE),
                             (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5.0)):
            self._conn.mav.command_long_send(self.target, mavlink.MAV_COMP_ID_AUTOPILOT1,
                                             mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                             1e6 / rate, 0, 0, 0, 0, 0)

    def _on_sim_state(self, msg) -> None:
        now = time.monotonic()
        lat, lon = sim_state_latlon(msg)
        if self._origin is None:
            self._origin = (lat, lon, msg.alt)
        ned = latlon_to_ned(lat, lon, msg.alt, self._origin)
        q = attitude_ned_to_enu(msg.roll, msg.pitch, msg.yaw)
        state = VehicleState(now, ned_to_enu(ned) + self._start, ned_to_enu([msg.vn, msg.ve, msg.vd]),
                             float(yaw_ned_to_enu(msg.yaw)), Rotation.from_quat(q).as_matrix(),
                             self._armed, self._mode, self._flying)
        with self._lock:
            self._state, self._received = state, now


def sim_state_latlon(msg) -> tuple[int, int]:
    """SIM_STATE's position in 1e-7 degree: the integer fields (MAVLink 2), else the floats."""
    lat, lon = getattr(msg, 'lat_int', 0), getattr(msg, 'lon_int', 0)
    if lat or lon:
        return lat, lon
    return round(msg.lat), round(msg.lon)


def latlon_to_ned(lat: int, lon: int, alt: float, origin: tuple[float, float, float]
                  ) -> np.ndarray:
    """Position (1e-7 degree, 1e-7 degree, m above sea level) as NED metres from `origin`,
    flat-earth as ArduPilot's Location::get_distance_NED."""
    lat0, lon0, alt0 = origin
    north = (lat - lat0) * M_PER_E7_DEG
    east = (lon - lon0) * M_PER_E7_DEG * math.cos(math.radians(lat0 * 1e-7))
    return np.array([north, east, -(alt - alt0)])
