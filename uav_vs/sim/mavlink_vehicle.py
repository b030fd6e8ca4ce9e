"""A simulated multirotor that speaks MAVLink the way ArduPilot Copter or PX4 does.

It is the test peer of the relay (uav_vs.autopilot.session) and the embedded default
vehicle; the real targets are ArduPilot/PX4 SITL and real autopilots.

With `truth_connection` it also serves its true state as ArduPilot's SITL does on a port
of its own: HEARTBEAT, and SIM_STATE and EXTENDED_SYS_STATE at the rates
SET_MESSAGE_INTERVAL asks there (uav_vs.sim.sitl_truth reads it). That port is the
world's, not the radio's: `cut_link` leaves it alone.

Dynamics, in the autopilot's own local NED frame with home and the ground at z = 0
(gravity-free: an armed, flying vehicle hovers where its velocity target is zero):

    dv/dt   = (v_target - v) / tau          velocity tracking, first-order lag
    dr/dt   = (r_target - r) / tau_yaw      yaw rate r (about z down), dpsi/dt = r
    dp/dt   = v + g                         ground contact: z <= 0, no speed into the ground

with g a horizontal wind gust (`gust_sigma`, Ornstein-Uhlenbeck, zero in still air). What
it reports as its estimate (LOCAL_POSITION_NED, ODOMETRY, GLOBAL_POSITION_INT) is p plus
a random-walk drift (`drift_rate`, zero by default); GPS_RAW_INT is the true position.

What it does like ArduPilot Copter 4.x (what the relay relies on):
- HEARTBEAT (1 Hz) with custom_mode: STABILIZE 0, GUIDED 4, LAND 9; type QUADROTOR.
- Nothing else streams until MAV_CMD_SET_MESSAGE_INTERVAL asks for it:
  SYS_STATUS, EKF_STATUS_REPORT, GPS_RAW_INT, ATTITUDE, LOCAL_POSITION_NED (only once
  the estimator is ready), GLOBAL_POSITION_INT; STATUSTEXT on events.
- Ready to arm as ArduCopter reports it, all at once at `ready_delay`: the SYS_STATUS
  pre-arm bit turns healthy, EKF_STATUS_REPORT gains flags 0x10 and 0x200 (absolute
  horizontal position, from 'constant position' mode before) and GPS_RAW_INT goes from
  no fix to a 3D fix.
- COMMAND_LONG answered by COMMAND_ACK with real result codes: DO_SET_MODE,
  COMPONENT_ARM_DISARM, NAV_TAKEOFF, NAV_LAND, SET_MESSAGE_INTERVAL; others UNSUPPORTED.
- Arming refused (FAILED + a 'PreArm:'/'Arm:' STATUSTEXT) until the estimator is ready
  (`ready_delay` after start) and outside GUIDED/STABILIZE; disarms itself if it has
  not taken off `disarm_delay` after arming; refuses to disarm in flight unless forced.
- NAV_TAKEOFF (GUIDED, armed, landed) climbs to param7 m above home, at most at
  takeoff_speed, slowing down without overshoot.
- SET_POSITION_TARGET_LOCAL_NED velocity (+ yaw rate) targets, frames 1, 7 (NED) and
  8, 9 (heading-aligned body), obeyed only in GUIDED, armed and flying; dropped
  silently otherwise (never acknowledged); they abort a takeoff climb. NaN, |v| > 1000
  or another frame: stop and hold, silently. With yaw and yaw rate both ignored the
  nose turns to the direction of travel. GUID_TIMEOUT: the last target is flown for
  `guid_timeout` s, then the vehicle stops. Position targets are not simulated.
- LAND descends at land_speed over the position its estimate had when LAND began (the
  position controller holds it: a P loop of `land_hold_gain`, PSC_POSXY_P, against
  gusts) and disarms on touchdown. STABILIZE simulates no pilot sticks: the vehicle
  holds still.
- SET_GPS_GLOBAL_ORIGIN answered by GPS_GLOBAL_ORIGIN with the origin it carried (the
  EKF's origin for flight on external navigation; the simulated estimate ignores it).
- MAVLink 2 signing when a key is configured or installed by SETUP_SIGNING (no ACK,
  ignored while armed): outgoing signed, unsigned incoming dropped, a signature checked
  before its timestamp counts (link.verify_signatures_first).

With `autopilot='px4'` it behaves like PX4 multicopter instead, where PX4 differs:
- HEARTBEAT of MAV_AUTOPILOT_PX4, custom_mode = main << 16 | sub << 24: POSCTL (at
  boot), AUTO.LOITER, AUTO.TAKEOFF, AUTO.LAND, OFFBOARD. Telemetry streams without being
  asked (SET_MESSAGE_INTERVAL still changes the rates); no EKF_STATUS_REPORT. ODOMETRY
  when asked, as PX4's stream sends it: frame LOCAL_NED, velocity frame LOCAL_NED, the
  estimate's variances (`odometry_variance`) on the diagonals, NaN elsewhere and for the
  body rates.
- Refusals are MAV_RESULT_TEMPORARILY_REJECTED, as PX4's commander answers a denied
  mode change. OFFBOARD is refused unless setpoints have streamed at > 2 Hz for more
  than a second; it is left for AUTO.LOITER (hold, what the default offboard-loss action
  comes to without RC) when none arrives for `offboard_loss_timeout` (COM_OF_LOSS_T).
- Arming only in LOITER or OFFBOARD (POSCTL needs the RC this simulator has not).
- NAV_TAKEOFF (armed, landed) takes param7 as the AMSL altitude (NaN: 2.5 m above home,
  MIS_TAKEOFF_ALT), climbs in AUTO.TAKEOFF and then holds in AUTO.LOITER; NAV_LAND is
  AUTO.LAND.
- Setpoints in MAV_FRAME_LOCAL_NED (1) and MAV_FRAME_BODY_NED (8) only, obeyed in
  OFFBOARD: the last one is flown until the offboard-loss failsafe, with no
  GUID_TIMEOUT.
"""
import argparse
import collections
import math
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from uav_vs.autopilot.link import (FORCE_DISARM, POSITION_IGNORE, VELOCITY_IGNORE,
                                   load_signing_key, mavlink, mavutil, verify_signatures_first)

ARDUPILOT, PX4 = 'ardupilot', 'px4'
# The modes simulated and their HEARTBEAT custom_mode: ArduCopter's mode numbers, and
# PX4's main << 16 | sub << 24 (pymavlink's px4_map holds main and sub).
CUSTOM_MODES = {
    ARDUPILOT: {'STABILIZE': 0, 'GUIDED': 4, 'LAND': 9},
    PX4: {name: main << 16 | sub << 24 for name, (_, main, sub) in mavutil.px4_map.items()
          if name in ('POSCTL', 'LOITER', 'TAKEOFF', 'LAND', 'OFFBOARD')}}
BOOT_MODE = {ARDUPILOT: 'STABILIZE', PX4: 'POSCTL'}
VELOCITY_MODE = {ARDUPILOT: 'GUIDED', PX4: 'OFFBOARD'}
ARMABLE = {ARDUPILOT: ('GUIDED', 'STABILIZE'), PX4: ('LOITER', 'OFFBOARD')}
SETPOINT_FRAMES = {ARDUPILOT: (1, 7, 8, 9), PX4: (1, 8)}
# PX4 streams these without being asked (interval, s).
PX4_STREAMS = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0, mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
               mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0, mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.05,
               mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.05,
               mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.2}
PX4_TAKEOFF_HEIGHT = 2.5            # MIS_TAKEOFF_ALT [m]
# What SET_MESSAGE_INTERVAL can stream: PX4 has no EKF_STATUS_REPORT (ardupilotmega).
STREAMABLE = {ARDUPILOT: frozenset({*PX4_STREAMS, mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT}),
              PX4: frozenset({*PX4_STREAMS, mavlink.MAVLINK_MSG_ID_ODOMETRY})}
EARTH_RADIUS = 6378137.0
# EKF_STATUS_REPORT flags before the estimator is ready (attitude and height, no horizontal
# position: 'constant position' mode) and after (horizontal position, absolute and predicted).
EKF_WAITING = (mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_VERT | mavlink.EKF_POS_VERT_ABS
               | mavlink.EKF_CONST_POS_MODE)
EKF_READY = (mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_VELOCITY_VERT
             | mavlink.EKF_POS_HORIZ_REL | mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_POS_VERT_ABS
             | mavlink.EKF_PRED_POS_HORIZ_REL | mavlink.EKF_PRED_POS_HORIZ_ABS)


@dataclass(frozen=True)
class VehicleConfig:
    connection: str = 'tcpin:127.0.0.1:5760'  # server side: tcpin:, udpin:, or udpout:HOST:PORT
    rate: float = 50.0                  # simulation and send loop [Hz]
    ready_delay: float = 3.0            # estimator 'ready' (armable, position known) after [s]
    tau: float = 0.35                   # velocity lag [s]: 1 m/s stops in about 1.4 s
    tau_yaw: float = 0.2                # yaw-rate lag [s]
    takeoff_speed: float = 2.5          # [m/s] (WPNAV_SPEED_UP)
    land_speed: float = 0.5             # [m/s] (LAND_SPEED)
    land_hold_gain: float = 1.0         # [1/s] LAND's position hold (PSC_POSXY_P, MPC_XY_P)
    guid_timeout: float = 3.0           # [s] (GUID_TIMEOUT)
    disarm_delay: float = 10.0          # [s] armed on the ground without takeoff
    system_id: int = 1
    autopilot: str = ARDUPILOT          # whose behaviour: 'ardupilot' (Copter) or 'px4'
    offboard_loss_timeout: float = 1.0  # PX4: OFFBOARD left this long without a setpoint [s]
    home: tuple[float, float, float] = (-35.363261, 149.165230, 584.0)  # lat, lon [deg], AMSL [m]
    signing_key: bytes | None = None
    truth_connection: str | None = None  # server side of the SIM_STATE truth port, as connection
    # PX4's ODOMETRY: variances of position (N, E, D) [m^2], orientation (roll, pitch,
    # yaw) [rad^2] and velocity (N, E, D) [m^2/s^2]
    odometry_variance: tuple = ((0.01, 0.02, 0.04), (1e-4, 2e-4, 4e-4), (0.001, 0.002, 0.003))
    # Wind gusts: the part of the wind the autopilot's velocity loop has not yet rejected,
    # a horizontal Ornstein-Uhlenbeck velocity of this spread [m/s] and time constant [s]
    # added to the flown velocity; 0: still air.
    gust_sigma: float = 0.0
    gust_time_constant: float = 1.0
    # The autopilot's estimate (LOCAL_POSITION_NED, ODOMETRY, GLOBAL_POSITION_INT) drifts
    # from the truth as a random walk of this rate [m/sqrt(s)] per axis; 0: exact.
    drift_rate: float = 0.0
    seed: int = 0                       # of the gusts and the drift


@dataclass(frozen=True)
class Truth:
    """Simulator ground truth, in the autopilot's NED frame (home on the ground at 0)."""
    time: float                  # time.monotonic()
    position: np.ndarray         # NED [m]
    velocity: np.ndarray         # NED [m/s]
    yaw: float                   # [rad], 0 north, clockwise
    yaw_rate: float              # [rad/s] about z down
    armed: bool
    mode: str
    flying: bool
    signing: bool                # a key is installed: unsigned input is dropped


@dataclass(frozen=True)
class Target:
    """A SET_POSITION_TARGET_LOCAL_NED as received (for tests: what went over the wire)."""
    time: float
    frame: int
    type_mask: int
    velocity: tuple[float, float, float]
    yaw_rate: float


class _TcpServer(mavutil.mavtcpin):
    """tcpin that takes the newest client and listens again after a client hangs up."""

    def recv(self, n=None):
        try:
            client, _ = self.listen.accept()
            if self.port is not None:
                self.port.close()
            client.setblocking(False)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.port, self.fd = client, client.fileno()
        except BlockingIOError:
            pass
        if self.port is None:
            return b''
        try:
            data = self.port.recv(n or self.mav.bytes_needed())
        except BlockingIOError:
            return b''
        except OSError:
            data = b''
        if not data:  # the client hung up
            self.port.close()
            self.port, self.fd = None, self.listen.fileno()
        return data


def _bound(conn) -> tuple[str, int]:
    sock = conn.listen if isinstance(conn, _TcpServer) else conn.port
    return sock.getsockname()[:2]


def _server(device: str, system_id: int):
    """The vehicle's end of the link; signatures verified before any state changes."""
    if device.startswith('tcpin:'):
        return verify_signatures_first(_TcpServer(device[6:], source_system=system_id,
                                                  source_component=1))
    return verify_signatures_first(mavutil.mavlink_connection(
        device, source_system=system_id, source_component=1, udp_timeout=5))


class MavlinkVehicle:
    """The simulated vehicle, run by a thread: start(), then truth(); stop() when done."""

    def __init__(self, config: VehicleConfig = VehicleConfig()):
        if config.autopilot not in CUSTOM_MODES:
            raise ValueError(f'autopilot: expected one of {", ".join(CUSTOM_MODES)}, '
                             f'got {config.autopilot!r}')
        self.config = config
        self._px4 = config.autopilot == PX4
        self._conn = _server(config.connection, config.system_id)
        self._truth_conn = (None if config.truth_connection is None
                            else _server(config.truth_connection, config.system_id))
        self._truth_intervals = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0}
        self._truth_next: dict[int, float] = {}
        self._truth_senders = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._send_heartbeat,
            mavlink.MAVLINK_MSG_ID_SIM_STATE: self._send_sim_state,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._send_extended_sys_state}
        if config.signing_key is not None:
            self._conn.setup_signing(config.signing_key, sign_outgoing=True)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='sim-vehicle', daemon=True)
        self._t0 = time.monotonic()
        self._link_up = True
        self._p = np.zeros(3)
        self._v = np.zeros(3)                   # flown, relative to the air
        self._gust = np.zeros(3)                # wind not yet rejected: ground = v + gust
        self._drift = np.zeros(3)               # estimate - truth
        self._land_at = np.zeros(2)             # estimated N, E where LAND began [m]
        self._rng = np.random.default_rng(config.seed)
        self._yaw = self._yaw_rate = 0.0
        self._v_target = np.zeros(3)
        self._yaw_rate_target = 0.0
        self._face_travel = False
        self._target_time = -math.inf
        self._mode = BOOT_MODE[config.autopilot]
        self._stream_start = self._last_setpoint = -math.inf   # PX4's offboard signal
        self._armed = self._flying = self._ready = False
        self._armed_at = 0.0
        self._takeoff_alt: float | None = None
        self._intervals = (dict(PX4_STREAMS) if self._px4
                           else {mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0})
        self._next_send: dict[int, float] = {}
        self._targets = collections.deque(maxlen=2000)
        self._senders = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._send_heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._send_sys_status,
            mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT: self._send_ekf_status,
            mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: self._send_gps_raw,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._send_attitude,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._send_local_position,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._send_global_position,
            mavlink.MAVLINK_MSG_ID_ODOMETRY: self._send_odometry}

    @property
    def address(self) -> tuple[str, int]:
        """The (host, port) actually served (useful with port 0)."""
        return _bound(self._conn)

    @property
    def truth_address(self) -> tuple[str, int]:
        """The (host, port) of the truth port."""
        return _bound(self._truth_conn)

    def start(self) -> 'MavlinkVehicle':
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._conn.close()
        if self._truth_conn is not None:
            self._truth_conn.close()

    def __enter__(self) -> 'MavlinkVehicle':
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def truth(self) -> Truth:
        with self._lock:
            return Truth(time.monotonic(), self._p.copy(), self._v + self._gust, self._yaw,
                         self._yaw_rate,
                         self._armed, self._mode, self._flying,
                         self._conn.mav.signing.secret_key is not None)

    def targets(self, since: float = -math.inf) -> list[Target]:
        """Velocity targets received at or after `since` (time.monotonic()), oldest first."""
        with self._lock:
            return [t for t in self._targets if t.time >= since]

    def moving_time(self, since: float = -math.inf) -> float:
        """How long the targets received at or after `since` held a velocity or yaw rate
        (any component above 1e-6) s: from each such target to the next zero one (or
        now), by the simulator's own clock. A velocity v held this long moves the vehicle v times it,
        once stopped, however late the targets came: the step integrates each target
        from its receipt, and the lag's rise and fall cancel."""
        now = time.monotonic()
        total, start = 0.0, None
        for t in self.targets(since):
            moving = max(map(abs, (*t.velocity, t.yaw_rate))) > 1e-6
            if moving and start is None:
                start = t.time
            elif not moving and start is not None:
                total, start = total + t.time - start, None
        return total + (now - start if start is not None else 0.0)

    def cut_link(self) -> None:
        """Simulated radio loss: nothing is sent, everything received is dropped."""
        with self._lock:
            self._link_up = False

    def restore_link(self) -> None:
        with self._lock:
            self._link_up = True

    # ---------------------------------------------------------------- loop
    def _run(self) -> None:
        period = 1.0 / self.config.rate
        last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                self._step(now, now - last)
                while (msg := self._conn.recv_msg()) is not None:
                    if self._link_up:
                        self._handle(msg, now)
                if self._link_up:
                    self._send_due(now)
                if self._truth_conn is not None:
                    self._serve_truth(now)
            last = now
            self._stop.wait(max(0.0, period - (time.monotonic() - now)))

    def _step(self, now: float, dt: float) -> None:
        cfg = self.config
        if not self._ready and now - self._t0 >= cfg.ready_delay:
            self._ready = True
            if not self._px4:
                self._text(mavlink.MAV_SEVERITY_INFO, 'EKF3 IMU0 is using GPS')
        if self._mode == 'OFFBOARD' and now - self._last_setpoint > cfg.offboard_loss_timeout:
            self._set_mode('LOITER')
            self._text(mavlink.MAV_SEVERITY_CRITICAL, 'Failsafe: no offboard signal, holding')
        if self._armed and not self._flying and now - self._armed_at > cfg.disarm_delay:
            self._disarm('Disarming: takeoff not started')
        if cfg.drift_rate > 0.0:
            self._drift += self._rng.normal(0.0, cfg.drift_rate * math.sqrt(dt), 3)
        if not self._flying:
            self._v[:] = 0.0
            self._gust[:] = 0.0
            self._yaw_rate = 0.0
            return
        v_target, r_target = self._targets_now(now)
        a = 1.0 - math.exp(-dt / cfg.tau)
        self._v += (v_target - self._v) * a
        self._yaw_rate += (r_target - self._yaw_rate) * (1.0 - math.exp(-dt / cfg.tau_yaw))
        self._yaw = (self._yaw + self._yaw_rate * dt + math.pi) % (2 * math.pi) - math.pi
        if cfg.gust_sigma > 0.0:   # exact discretisation of the OU process
            k = math.exp(-dt / cfg.gust_time_constant)
            self._gust[:2] = k * self._gust[:2] + cfg.gust_sigma * math.sqrt(1 - k * k) * \
                self._rng.standard_normal(2)
        self._p += (self._v + self._gust) * dt
        if self._p[2] >= 0.0 and v_target[2] >= 0.0:  # touchdown
            self._p[2] = 0.0
            self._v[:] = 0.0
            self._flying = False
            if self._mode == 'LAND':
                self._disarm('Landing detected' if self._px4 else 'Land complete: disarming')
        elif self._p[2] > 0.0:
            self._p[2], self._v[2] = 0.0, min(self._v[2], 0.0)

    def _targets_now(self, now: float) -> tuple[np.ndarray, float]:
        """Velocity (NED) and yaw-rate targets of the current mode."""
        cfg = self.config
        if self._mode == 'LAND':
            hold = cfg.land_hold_gain * (self._land_at - self._estimate()[:2])
            return np.array([*hold, cfg.land_speed]), 0.0
        if self._takeoff_alt is not None:   # ArduPilot GUIDED or PX4 AUTO.TAKEOFF climb
            remaining = self._takeoff_alt + self._p[2]
            if remaining > 0.02:  # climb rate led by the lag: critically damped, no overshoot
                climb = min(cfg.takeoff_speed, (remaining + cfg.tau * self._v[2]) / cfg.tau)
                return np.array([0.0, 0.0, -climb]), 0.0
            self._takeoff_alt = None
            if self._px4:
                self._set_mode('LOITER')
            else:
                self._text(mavlink.MAV_SEVERITY_INFO, 'Takeoff complete')
        if self._mode != VELOCITY_MODE[cfg.autopilot]:
            return np.zeros(3), 0.0
        if not self._px4 and now - self._target_time > cfg.guid_timeout:
            return np.zeros(3), 0.0
        if self._face_travel and math.hypot(*self._v_target[:2]) > 0.1:
            error = math.atan2(self._v_target[1], self._v_target[0]) - self._yaw
            error = (error + math.pi) % (2 * math.pi) - math.pi
            return self._v_target, max(-1.5, min(1.5, 2.0 * error))
        return self._v_target, self._yaw_rate_target

    # ---------------------------------------------------------------- incoming
    def _handle(self, msg, now: float) -> None:
        kind = msg.get_type()
        if kind == 'COMMAND_LONG' and msg.target_system in (0, self.config.system_id):
            result, text = self._command(msg, now)
            if text:
                self._text(mavlink.MAV_SEVERITY_CRITICAL, text)
            self._conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(),
                                            msg.get_srcComponent())
        elif kind == 'SET_POSITION_TARGET_LOCAL_NED' and msg.target_system in (0, self.config.system_id):
            self._velocity_target(msg, now)
        elif kind == 'SET_GPS_GLOBAL_ORIGIN' and msg.target_system in (0, self.config.system_id):
            # as ArduPilot: the origin is taken once and confirmed by GPS_GLOBAL_ORIGIN
            self._conn.mav.gps_global_origin_send(msg.latitude, msg.longitude, msg.altitude,
                                                  msg.time_usec)
        elif kind == 'SETUP_SIGNING' and msg.target_system in (0, self.config.system_id):
            if not self._armed:
                key = bytes(msg.secret_key)
                if any(key):
                    self._conn.setup_signing(key, sign_outgoing=True, initial_timestamp=msg.initial_timestamp)
                else:
                    self._conn.disable_signing()

    def _command(self, msg, now: float) -> tuple[int, str | None]:
        """Execute a COMMAND_LONG: (MAV_RESULT, STATUSTEXT reason or None)."""
        c, ok, failed = msg.command, mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED
        refused = mavlink.MAV_RESULT_TEMPORARILY_REJECTED if self._px4 else failed
        if c == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval = int(msg.param1), msg.param2
            if msg_id not in STREAMABLE[self.config.autopilot]:
                return failed, None
            if interval < 0 or (interval == 0 and msg_id != mavlink.MAVLINK_MSG_ID_HEARTBEAT):
                self._intervals.pop(msg_id, None)
            else:
                self._intervals[msg_id] = interval * 1e-6 if interval > 0 else 1.0
                self._next_send[msg_id] = now
            return ok, None
        if c == mavlink.MAV_CMD_DO_SET_MODE:
            mode = self._requested_mode(msg)
            if mode is None:
                return refused, f'Mode change failed: unknown mode {int(msg.param2)}'
            if mode not in ('STABILIZE', 'LAND') and not self._ready:
                return refused, f'Mode change failed: {mode} requires position'
            if mode == 'OFFBOARD' and not (now - self._last_setpoint < 0.5
                                           and now - self._stream_start > 1.0):
                return refused, 'Switching to Offboard is currently not possible'
            self._set_mode(mode)
            return ok, None
        if c == mavlink.MAV_CMD_NAV_LAND:
            self._set_mode('LAND')
            return ok, None
        if c == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 == 0:
                if self._flying and int(msg.param2) != FORCE_DISARM:
                    return failed, 'Disarm: vehicle is flying'
                self._disarm(None)
                self._flying = False
                return ok, None
            if self._armed:
                return ok, None
            if not self._ready:
                return refused, ('Arming denied: no position estimate' if self._px4
                                 else 'PreArm: Need Position Estimate')
            if self._mode not in ARMABLE[self.config.autopilot]:
                return refused, ('Arming denied: manual control lost' if self._px4
                                 else 'Arm: Mode not armable')
            self._armed, self._armed_at = True, now
            return ok, None
        if c == mavlink.MAV_CMD_NAV_TAKEOFF:
            if self._px4:   # param7: AMSL altitude
                height = (PX4_TAKEOFF_HEIGHT if math.isnan(msg.param7)
                          else msg.param7 - self.config.home[2])
            else:
                height = msg.param7
            if ((not self._px4 and self._mode != 'GUIDED') or not self._armed or self._flying
                    or not height > 0):
                return refused, None
            if self._px4:
                self._set_mode('TAKEOFF')
            self._takeoff_alt, self._flying = height, True
            self._target_time = -math.inf
            return ok, None
        return mavlink.MAV_RESULT_UNSUPPORTED, None

    def _velocity_target(self, msg, now: float) -> None:
        mask = msg.type_mask
        v = (msg.vx, msg.vy, msg.vz)
        self._targets.append(Target(now, msg.coordinate_frame, mask, v, msg.yaw_rate))
        if self._px4:
            if msg.coordinate_frame not in SETPOINT_FRAMES[PX4]:
                return  # PX4 ignores other frames
            if now - self._last_setpoint > 0.5:     # below 2 Hz: the stream starts anew
                self._stream_start = now
            self._last_setpoint = now
        if self._mode != VELOCITY_MODE[self.config.autopilot] or not self._armed or not self._flying:
            return  # dropped silently: on the ground, or not GUIDED / OFFBOARD
        if mask & POSITION_IGNORE != POSITION_IGNORE or mask & VELOCITY_IGNORE:
            return  # position targets are not simulated
        yaw_rate_used = not mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
        values = v + ((msg.yaw_rate,) if yaw_rate_used else ())
        self._takeoff_alt = None  # a velocity target aborts the takeoff climb
        self._target_time = now
        if (msg.coordinate_frame not in SETPOINT_FRAMES[ARDUPILOT]
                or not all(map(math.isfinite, values))
                or max(map(abs, v)) > 1000.0):
            self._v_target, self._yaw_rate_target, self._face_travel = np.zeros(3), 0.0, False
            return  # stop and hold, no error
        if msg.coordinate_frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
            c, s = math.cos(self._yaw), math.sin(self._yaw)
            v = (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])
        self._v_target = np.array(v)
        self._yaw_rate_target = msg.yaw_rate if yaw_rate_used else 0.0
        self._face_travel = bool(mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE) and not yaw_rate_used

    def _requested_mode(self, msg) -> str | None:
        """The simulated mode a DO_SET_MODE asks for, or None."""
        if not int(msg.param1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return None
        custom = (int(msg.param2) << 16 | int(msg.param3) << 24 if self._px4
                  else int(msg.param2))
        return next((name for name, number in CUSTOM_MODES[self.config.autopilot].items()
                     if number == custom), None)

    def _set_mode(self, mode: str) -> None:
        self._mode = mode
        if mode == 'LAND':
            self._land_at = self._estimate()[:2].copy()
        self._takeoff_alt = None
        self._target_time = -math.inf

    def _disarm(self, reason: str | None) -> None:
        self._armed = False
        self._takeoff_alt = None
        if reason:
            self._text(mavlink.MAV_SEVERITY_INFO, reason)

    # ---------------------------------------------------------------- outgoing
    def _text(self, severity: int, text: str) -> None:
        if self._link_up:
            self._conn.mav.statustext_send(severity, text.encode()[:50])

    def _send_due(self, now: float) -> None:
        for msg_id, interval in self._intervals.items():
            if now >= self._next_send.get(msg_id, 0.0):
                self._senders[msg_id](now)
                self._next_send[msg_id] = max(self._next_send.get(msg_id, now) + interval, now)

    def _serve_truth(self, now: float) -> None:
        """The truth port: SET_MESSAGE_INTERVAL for SIM_STATE and EXTENDED_SYS_STATE
        answered, what is due sent."""
        conn = self._truth_conn
        while (msg := conn.recv_msg()) is not None:
            if (msg.get_type() == 'COMMAND_LONG' and msg.target_system in (0, self.config.system_id)
                    and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL):
                result = mavlink.MAV_RESULT_UNSUPPORTED
                if int(msg.param1) in (mavlink.MAVLINK_MSG_ID_SIM_STATE,
                                       mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE):
                    result = mavlink.MAV_RESULT_ACCEPTED
                    if msg.param2 > 0:
                        self._truth_intervals[int(msg.param1)] = msg.param2 * 1e-6
                    else:
                        self._truth_intervals.pop(int(msg.param1), None)
                conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(),
                                          msg.get_srcComponent())
        for msg_id, interval in self._truth_intervals.items():
            if now >= self._truth_next.get(msg_id, 0.0):
                self._truth_senders[msg_id](now, conn)
                self._truth_next[msg_id] = max(self._truth_next.get(msg_id, now) + interval, now)

    def _send_sim_state(self, now: float, conn) -> None:
        """SIM_STATE: the true position, velocity and attitude (level), as SITL's."""
        lat, lon, alt = self._lat_lon_alt(self._p)
        vn, ve, vd = self._v + self._gust
        c, s = math.cos(self._yaw / 2), math.sin(self._yaw / 2)
        conn.mav.sim_state_send(c, 0.0, 0.0, s, 0.0, 0.0, self._yaw, 0.0, 0.0, -9.81,
                                0.0, 0.0, self._yaw_rate, lat, lon, alt, 0.0, 0.0, vn, ve, vd,
                                int(round(lat * 1e7)), int(round(lon * 1e7)))

    def _send_extended_sys_state(self, now: float, conn) -> None:
        landed = mavlink.MAV_LANDED_STATE_IN_AIR if self._flying else \
            mavlink.MAV_LANDED_STATE_ON_GROUND
        conn.mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)

    def _boot_ms(self, now: float) -> int:
        return int((now - self._t0) * 1e3)

    def _send_heartbeat(self, now: float, conn=None) -> None:
        if self._px4:
            base, autopilot = mavutil.px4_map[self._mode][0], mavlink.MAV_AUTOPILOT_PX4
        else:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
            if self._mode == 'GUIDED':
                base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
            autopilot = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        if self._armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        state = mavlink.MAV_STATE_ACTIVE if self._armed else mavlink.MAV_STATE_STANDBY
        (conn or self._conn).mav.heartbeat_send(
            mavlink.MAV_TYPE_QUADROTOR, autopilot, base,
            CUSTOM_MODES[self.config.autopilot][self._mode], state)

    def _send_sys_status(self, now: float) -> None:
        prearm = mavlink.MAV_SYS_STATUS_PREARM_CHECK
        health = prearm if self._ready else 0
        self._conn.mav.sys_status_send(prearm, prearm, health, 200, 12600, -1, 100, 0, 0, 0, 0, 0, 0)

    def _send_ekf_status(self, now: float) -> None:
        flags = EKF_READY if self._ready else EKF_WAITING
        self._conn.mav.ekf_status_report_send(flags, 0.02, 0.02, 0.01, 0.01, 0.0)

    def _send_gps_raw(self, now: float) -> None:
        lat, lon, alt = self._lat_lon_alt(self._p)
        if self._ready:
            fix, eph, sats = mavlink.GPS_FIX_TYPE_3D_FIX, 80, 12
        else:
            fix, eph, sats = mavlink.GPS_FIX_TYPE_NO_FIX, 0xFFFF, 0
        cog = int(math.degrees(math.atan2(self._v[1], self._v[0])) % 360 * 100)
        self._conn.mav.gps_raw_int_send(
            int((now - self._t0) * 1e6), fix, int(lat * 1e7), int(lon * 1e7), int(alt * 1e3),
            eph, eph, int(round(math.hypot(*self._v[:2]) * 100)), cog, sats)

    def _send_attitude(self, now: float) -> None:
        self._conn.mav.attitude_send(self._boot_ms(now), 0.0, 0.0, self._yaw, 0.0, 0.0, self._yaw_rate)

    def _send_local_position(self, now: float) -> None:
        if self._ready:  # no EKF origin before
            self._conn.mav.local_position_ned_send(self._boot_ms(now), *self._estimate(),
                                                   *(self._v + self._gust))

    def _send_odometry(self, now: float) -> None:
        if not self._ready:
            return
        position, orientation, velocity = self.config.odometry_variance
        pose, twist = [math.nan] * 21, [math.nan] * 21
        # the diagonal of the 6x6 upper triangle is at 0, 6, 11, 15, 18, 20
        pose[0], pose[6], pose[11] = position
        pose[15], pose[18], pose[20] = orientation
        twist[0], twist[6], twist[11] = velocity
        c, s = math.cos(self._yaw / 2), math.sin(self._yaw / 2)
        self._conn.mav.odometry_send(
            int((now - self._t0) * 1e6), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED,
            *self._estimate(), [c, 0.0, 0.0, s], *(self._v + self._gust), 0.0, 0.0,
            self._yaw_rate, pose, twist,
            0, mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT, 100)

    def _estimate(self) -> np.ndarray:
        """The autopilot's position estimate, NED [m]: the truth and its drift."""
        return self._p + self._drift

    def _lat_lon_alt(self, ned: np.ndarray) -> tuple[float, float, float]:
        """A local NED position [m] as latitude, longitude [deg] and altitude AMSL [m]."""
        lat, lon, alt = self.config.home
        n, e, d = ned
        lat += math.degrees(n / EARTH_RADIUS)
        lon += math.degrees(e / (EARTH_RADIUS * math.cos(math.radians(lat))))
        return lat, lon, alt - d

    def _send_global_position(self, now: float) -> None:
        lat, lon, alt = self._lat_lon_alt(self._estimate())
        vn, ve, vd = (int(round(x * 100)) for x in self._v + self._gust)
        self._conn.mav.global_position_int_send(
            self._boot_ms(now), int(lat * 1e7), int(lon * 1e7), int(alt * 1e3),
            int(-self._estimate()[2] * 1e3),
            vn, ve, vd, int(math.degrees(self._yaw) % 360 * 100))


def main(argv: list[str] | None = None) -> None:
    """`sim_vehicle`: serve the simulated copter until Ctrl-C."""
    parser = argparse.ArgumentParser(description='Simulated ArduCopter- or PX4-like vehicle behind a '
                                                 'MAVLink endpoint.')
    parser.add_argument('--connection', default=VehicleConfig.connection,
                        help='server side: tcpin:HOST:PORT, udpin:HOST:PORT or udpout:HOST:PORT '
                             '(default %(default)s, like the arducopter binary)')
    parser.add_argument('--rate', type=float, default=VehicleConfig.rate, help='simulation rate [Hz]')
    parser.add_argument('--ready-delay', type=float, default=VehicleConfig.ready_delay,
                        help='seconds before the vehicle is ready to arm')
    parser.add_argument('--guid-timeout', type=float, default=VehicleConfig.guid_timeout,
                        help='seconds a velocity target is flown without a new one')
    parser.add_argument('--system-id', type=int, default=VehicleConfig.system_id)
    parser.add_argument('--autopilot', choices=sorted(CUSTOM_MODES), default=VehicleConfig.autopilot,
                        help="whose MAVLink behaviour to follow (default %(default)s)")
    parser.add_argument('--signing-key-file', help='enforce MAVLink 2 signing with this key')
    args = parser.parse_args(argv)
    key = load_signing_key(args.signing_key_file) if args.signing_key_file else None
    config = VehicleConfig(connection=args.connection, rate=args.rate, ready_delay=args.ready_delay,
                           guid_timeout=args.guid_timeout, system_id=args.system_id, signing_key=key,
                           autopilot=args.autopilot)
    with MavlinkVehicle(config) as vehicle:
        host, port = vehicle.address
        like = 'PX4' if args.autopilot == PX4 else 'ArduCopter'
        print(f'sim_vehicle: {like}-like system {args.system_id} on {args.connection} '
              f'({host}:{port}){", signing enforced" if key else ""}', flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass


if __name__ == '__main__':
    main()
