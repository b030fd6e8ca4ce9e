"""A MAVLink session with one autopilot (ArduPilot Copter or PX4): what the relay node drives.

The velocity commands of the chapter's controllers (sections 5 and 6) leave the ROS
graph here, and the autopilot's own estimate comes back (the comparison of Fig. 6).

Threading: one background thread owns the link. It parses every incoming message,
sends the GCS heartbeat (1 Hz), re-streams the current setpoint, runs the command
and link watchdogs and reconnects. The public methods are thread-safe.
`send_velocity()` validates, limits, converts and writes its
SET_POSITION_TARGET_LOCAL_NED at once from the caller's thread (lowest latency), unless
that would exceed max_send_rate (a token bucket of SEND_BURST setpoints): then the
thread writes the newest command when the next token comes;
blocking calls (`arm`, `takeoff`, ...) wait on a condition that the thread signals.
The watchdogs run whatever the caller does: a stalled ROS executor still ends in a
hover, never in its last command streamed on and on.

Frames: commands and telemetry are ROS frames (world ENU, base_link FLU); every
conversion goes through `frames`.
"""
import collections
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from . import frames
from .link import (BAD_SIGNATURE, FORCE_DISARM, OLD_TIMESTAMP, UNSIGNED, VELOCITY_YAW_RATE_MASK,
                   connection_problem, load_signing_key, mavlink, mavutil, open_connection,
                   rejection_cause)

log = logging.getLogger(__name__)

ARDUPILOT, PX4, GENERIC = 'ardupilot', 'px4', 'generic'
_AUTOPILOTS = {mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: ARDUPILOT, mavlink.MAV_AUTOPILOT_PX4: PX4}
_NOT_VEHICLES = (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_GIMBAL, mavlink.MAV_TYPE_ADSB,
                 mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_CAMERA)
# Modes in which the autopilot flies our velocity setpoints.
VELOCITY_MODE = {ARDUPILOT: 'GUIDED', PX4: 'OFFBOARD'}
# Body-frame setpoints: ArduPilot reads BODY_OFFSET_NED, PX4 only BODY_NED (both heading-aligned).
BODY_FRAME = {ARDUPILOT: mavlink.MAV_FRAME_BODY_OFFSET_NED, PX4: mavlink.MAV_FRAME_BODY_NED}
_LANDING_MODES = ('LAND',)
_UNSIGNED_OK = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS})  # telemetry radios never sign
# What frames dropped for their signature say while no vehicle is heard, most telling first.
_REJECTED = {
    BAD_SIGNATURE: 'frames rejected: bad signature (wrong key?)',
    OLD_TIMESTAMP: 'frames rejected: signing timestamp not newer than before (replayed?)',
    UNSIGNED: 'frames rejected: unsigned (the vehicle does not sign: install_signing_key '
              'with signing_required false)'}
# Ready to arm on ArduPilot Copter, besides the SYS_STATUS pre-arm bit (see prearm_reasons).
EKF_READY_FLAGS = mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS   # 0x10 | 0x200
GPS_READY_FIX = mavlink.GPS_FIX_TYPE_3D_FIX
# Telemetry only ArduPilot's readiness check reads: PX4 has no EKF_STATUS_REPORT (an
# ardupilotmega message), and its GPS requirement is part of its own pre-arm checks.
_ARDUPILOT_ONLY = frozenset({'EKF_STATUS_REPORT', 'GPS_RAW_INT'})
# ... and only PX4's: ODOMETRY, the one message carrying its estimate's covariances (PX4
# streams it when asked; ArduPilot does not send it).
_PX4_ONLY = frozenset({'ODOMETRY'})
# ODOMETRY's velocity frame (child_frame_id) -> frames.velocity_covariance_to_flu's name.
_VELOCITY_FRAMES = {mavlink.MAV_FRAME_LOCAL_NED: 'local_ned',
                    mavlink.MAV_FRAME_LOCAL_FRD: 'local_ned',
                    mavlink.MAV_FRAME_BODY_FRD: 'body_frd'}
# A connection that cannot be opened is retried every second, and said again this often [s].
OPEN_WARNING_PERIOD = 10.0
# Setpoints that may leave back to back before max_send_rate holds them: a controller
# streaming near that rate with ordinary jitter never waits, a burst is cut to the rate.
SEND_BURST = 3
FLOAT32_MAX = float(np.finfo(np.float32).max)   # MAVLink floats: larger ones cannot be sent
# A refusal's reason: STATUSTEXT from the command's first send until this long after its ACK [s].
_REASON_GRACE = 0.3


class LinkState(str, Enum):
    CONNECTING = 'connecting'  # no vehicle HEARTBEAT yet
    CONNECTED = 'connected'
    LOST = 'lost'              # no HEARTBEAT for link_timeout: commands stopped, reconnecting


class CommandState(str, Enum):
    IDLE = 'idle'      # nothing streamed (no command since connect, takeoff or mode change)
    ACTIVE = 'active'  # fresh commands, re-streamed at stream_rate
    HOVER = 'hover'    # input stale (command watchdog): zero velocity streamed
    LOCKED = 'locked'  # link down, takeoff climb or landing: velocity commands refused


class AutopilotError(RuntimeError):
    """An operation the autopilot refused or that could not be completed."""


class CommandError(AutopilotError):
    """A COMMAND_LONG refused (result is a MAV_RESULT) or never acknowledged (result None)."""

    def __init__(self, command: int, result: int | None, statustext: list[str],
                 hint: str | None = None):
        self.command, self.result, self.statustext = command, result, statustext
        name = _enum_name('MAV_CMD', command)
        what = f'refused: {_enum_name("MAV_RESULT", result)}' if result is not None else 'no COMMAND_ACK'
        said = f"; autopilot says: {' | '.join(statustext)}" if statustext else ''
        why = f': {hint}' if hint else ''
        super().__init__(f'{name} {what}{why}{said}')


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink.enums[enum].get(value)
    return entry.name if entry is not None else f'{enum}({value})'


@dataclass(frozen=True)
class Limits:
    """Command limits applied before anything is sent (SI units, ROS frames)."""
    max_speed: float = 2.0       # horizontal speed [m/s]; faster commands are scaled down
    max_climb: float = 1.0       # upward speed [m/s]
    max_descent: float = 0.7     # downward speed [m/s]
    max_yaw_rate: float = 1.0    # [rad/s]
    fence_min: tuple[float, float, float] | None = None  # world ENU box [m]: outward velocity
    fence_max: tuple[float, float, float] | None = None  # components slowed down near its faces
    fence_approach: float = 1.5  # [s] outward speed <= distance to the face / this

    def __post_init__(self):
        for name in ('max_speed', 'max_climb', 'max_descent', 'max_yaw_rate'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value}')
        if not (math.isfinite(self.fence_approach) and self.fence_approach > 0.0):
            raise ValueError(f'fence_approach must be a finite number > 0, got {self.fence_approach}')


def yaw_only_attitude(covariance: np.ndarray) -> np.ndarray:
    """A 6x6 NED pose covariance as the autopilots can use it in VISION_POSITION_ESTIMATE:
    both take roll and pitch from their own IMU and fuse only the yaw of an external
    attitude (ArduPilot's EK3_SRC1_YAW, PX4's EKF2_EV_CTRL yaw bit), but ArduPilot folds
    the three angles' variances into the one noise of that yaw (the root of their sum).
    So roll and pitch are sent with the yaw's variance and no correlation: a pose whose
    roll and pitch are unknown (huge variances, as pose_filter_node's fused/odom, which
    does not estimate them) does not drown its yaw."""
    out = np.array(covariance, dtype=float)
    out[3:5, :] = 0.0
    out[:, 3:5] = 0.0
    out[3, 3] = out[4, 4] = out[5, 5]
    return out


@dataclass(frozen=True)
class SessionConfig:
    connection: str                         # pymavlink connection string
    baud: int = 115200                      # serial only
    source_system: int = 255                # our MAVLink id (255 = GCS, as MAVProxy)
    source_component: int = mavlink.MAV_COMP_ID_MISSIONPLANNER
    target_system: int = 0                  # 0: the first vehicle heard
    rates: dict = field(default_factory=lambda: {  # telemetry requested [Hz]
        'LOCAL_POSITION_NED': 20.0, 'ATTITUDE': 20.0, 'GLOBAL_POSITION_INT': 5.0, 'SYS_STATUS': 1.0,
        'EKF_STATUS_REPORT': 1.0, 'GPS_RAW_INT': 1.0,    # these two: ArduPilot only
        'ODOMETRY': 20.0})                               # PX4 only
    stream_rate: float = 10.0               # setpoint re-send rate [Hz] (PX4 needs > 2)
    max_send_rate: float = 50.0             # setpoints written at most this often [Hz]
    command_timeout: float = 0.5            # input older than this -> hover [s]
    link_timeout: float = 3.0               # no HEARTBEAT for this -> link lost [s]
    ack_timeout: float = 1.0                # per COMMAND_LONG try [s]
    command_retries: int = 2
    allow_arming: bool = False
    limits: Limits = Limits()
    signing_key_file: str | None = None     # MAVLink 2 signing (see link.load_signing_key)
    signing_required: bool = True           # reject unsigned incoming messages
    # Flight without GPS, on external navigation (send_vision_pose): the EKF origin (latitude
    # and longitude [deg], altitude AMSL [m]) sent as SET_GPS_GLOBAL_ORIGIN until the
    # autopilot answers with GPS_GLOBAL_ORIGIN; readiness then needs that answer, no GPS fix.
    ekf_origin: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class EkfStatus:
    """ArduPilot's EKF_STATUS_REPORT: its flags (EKF_STATUS_FLAGS) and innovation test
    ratios (the fields named *_variance: 1 is the gate, above it a measurement is refused)."""
    flags: int
    velocity: float
    pos_horiz: float
    pos_vert: float
    compass: float

    @property
    def navigating(self) -> bool:
        """An absolute horizontal position, not the constant-position fallback."""
        return bool(self.flags & mavlink.EKF_POS_HORIZ_ABS) and not (
            self.flags & mavlink.EKF_CONST_POS_MODE)


@dataclass(frozen=True)
class Telemetry:
    """The autopilot's estimate in ROS frames (None until the message has arrived)."""
    stamp: float | None = None                    # time.monotonic() of the newest message
    position: np.ndarray | None = None            # world ENU [m] (LOCAL_POSITION_NED)
    velocity: np.ndarray | None = None            # world ENU [m/s]
    orientation: np.ndarray | None = None         # (x, y, z, w) of base_link FLU in world ENU
    angular_velocity: np.ndarray | None = None    # base_link FLU [rad/s]
    height: float | None = None                   # above home [m] (GLOBAL_POSITION_INT)
    latitude: float | None = None                 # [deg]
    longitude: float | None = None                # [deg]
    altitude: float | None = None                 # AMSL [m]
    # ROS covariances (ODOMETRY, PX4): pose in world ENU / base_link FLU rotations, twist
    # in base_link FLU; entries the autopilot does not report are 0.
    pose_covariance: np.ndarray | None = None     # 6x6
    twist_covariance: np.ndarray | None = None    # 6x6


@dataclass(frozen=True)
class Status:
    link: LinkState
    autopilot: str | None            # 'ardupilot', 'px4', 'generic'
    vehicle_type: str | None         # MAV_TYPE without prefix, e.g. 'QUADROTOR'
    system_id: int | None
    mode: str | None
    armed: bool
    command: CommandState
    prearm_ok: bool | None           # ready to arm (see prearm_reasons); None before a HEARTBEAT
    prearm_reasons: tuple[str, ...]  # why not: one entry per failing or unreported check
    battery_voltage: float | None    # [V]
    heartbeat_age: float | None      # [s]
    reconnects: int
    signing: bool                    # we hold a key: outgoing messages signed
    vehicle_signs: bool              # the last vehicle HEARTBEAT carried a signature
    rejected_unsigned: int           # incoming frames dropped: unsigned, signing required
    rejected_bad_signature: int      # dropped: signature not made with our key (wrong key, forged)
    rejected_old_timestamp: int      # dropped: our key, but not newer than its stream (replayed)
    signing_problem: str | None      # what stops signed communication, in plain words
    statustext: tuple[str, ...]      # the autopilot's latest STATUSTEXT, newest last
    held: int                        # commands that waited for a send token (max_send_rate)
    coalesced: int                   # of those, replaced by a newer one before they were sent
    link_reason: str                 # why the connection cannot be opened ('' when it is open)
    ekf: EkfStatus | None            # the latest EKF_STATUS_REPORT (ArduPilot), None before one
    gps_fix: int | None              # GPS_RAW_INT fix_type (ArduPilot), None before one
    ekf_origin_set: bool | None      # with ekf_origin: GPS_GLOBAL_ORIGIN heard; else None


def prearm_reasons(autopilot: str | None, prearm_bit: bool | None, ekf_flags: int | None,
                   gps_fix: int | None, origin_set: bool | None = None) -> list[str]:
    """Why the autopilot is not ready to arm, one entry per check (empty: ready).

    None means not reported yet. ArduPilot Copter arms only with the SYS_STATUS pre-arm
    check bit healthy, EKF_STATUS_REPORT flags 0x10 and 0x200 (absolute horizontal
    position, now and predicted) and a GPS fix >= 3, so all three are checked. Without GPS
    (`origin_set` not None: SessionConfig.ekf_origin) the GPS fix is not needed but the EKF
    origin is: without one it refuses to arm in GUIDED ("waiting for home"). PX4 has no
    EKF_STATUS_REPORT and folds its estimator and GPS checks (GPS is optional there, e.g.
    with vision) into the pre-arm bit: that bit alone decides, as for other autopilots.
    """
    reasons = []
    if prearm_bit is None:
        reasons.append('no SYS_STATUS yet')
    elif not prearm_bit:
        reasons.append('SYS_STATUS pre-arm check not passed')
    if autopilot != ARDUPILOT:
        return reasons
    if ekf_flags is None:
        reasons.append('no EKF_STATUS_REPORT yet')
    elif missing := EKF_READY_FLAGS & ~ekf_flags:
        lacking = ', '.join(_enum_name('EKF_STATUS_FLAGS', bit) for bit in
                            (mavlink.EKF_POS_HORIZ_ABS, mavlink.EKF_PRED_POS_HORIZ_ABS) if missing & bit)
        reasons.append(f'EKF_STATUS_REPORT flags 0x{ekf_flags:x} lack {lacking}')
    if origin_set is not None:
        if not origin_set:
            reasons.append('EKF origin not set yet (SET_GPS_GLOBAL_ORIGIN unanswered)')
    elif gps_fix is None:
        reasons.append('no GPS_RAW_INT yet')
    elif gps_fix < GPS_READY_FIX:
        reasons.append(f'GPS fix {_enum_name("GPS_FIX_TYPE", gps_fix)}, needs 3D')
    return reasons


def statustext_level(severity: int) -> int:
    """The logging level of a STATUSTEXT severity: EMERGENCY to ERROR (ArduPilot's
    'PreArm:' refusals are CRITICAL) log as ERROR, WARNING as WARNING, NOTICE and INFO as
    INFO, DEBUG as DEBUG."""
    if severity <= mavlink.MAV_SEVERITY_ERROR:
        return logging.ERROR
    if severity == mavlink.MAV_SEVERITY_WARNING:
        return logging.WARNING
    return logging.INFO if severity <= mavlink.MAV_SEVERITY_INFO else logging.DEBUG


def open_failure(connection: str, err: Exception) -> str:
    """Why `connection` could not be opened, naming a host that does not resolve."""
    if isinstance(err, socket.gaierror):
        host = connection.split(':', 1)[-1].rpartition(':')[0]
        return f'cannot open {connection}: host {host!r} does not resolve ({err.strerror})'
    return f'cannot open {connection}: {err}'


def limit_velocity(v: tuple[float, float, float], yaw_rate: float,
                   limits: Limits) -> tuple[tuple[float, float, float], float]:
    """Scale horizontal speed to max_speed (direction kept), clamp climb/descent and yaw rate.

    Finite for any finite input, 1e308 and subnormals included (no intermediate
    overflows); ValueError for a non-finite one.
    """
    x, y, z = v
    x, y, z, yaw_rate = float(x), float(y), float(z), float(yaw_rate)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ValueError(f'velocity command is not finite: {[x, y, z]}')
    if not math.isfinite(yaw_rate):
        raise ValueError(f'yaw rate command is not finite: {yaw_rate}')
    x, y = clip_norm(x, y, limits.max_speed)
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f'limited velocity is not finite: {[x, y, z]}')
    z = min(max(z, -limits.max_descent), limits.max_climb)
    yaw_rate = min(max(yaw_rate, -limits.max_yaw_rate), limits.max_yaw_rate)
    return (x, y, z), yaw_rate


def clip_norm(x: float, y: float, limit: float) -> tuple[float, float]:
    """(x, y) scaled down to norm `limit` if longer, direction kept.

    Divided by its largest component first, the vector has norm in [1, sqrt 2], so
    neither the norm nor the scaling can overflow, however large x and y are.
    """
    if abs(x) <= limit and abs(y) <= limit and math.hypot(x, y) <= limit:
        return x, y       # the usual command: within the limit (hypot overflows to inf only)
    m = max(abs(x), abs(y))      # > 0: (0, 0) is within any limit
    ux, uy = x / m, y / m
    n = math.hypot(ux, uy)
    if m <= limit / n:
        return x, y
    return ux * (limit / n), uy * (limit / n)


def fence_velocity(v_world: np.ndarray, position: np.ndarray | None, lo, hi,
                   approach: float) -> np.ndarray:
    """Limit each world-velocity component that points out of the box [lo, hi] to the
    distance from `position` to that face over `approach` seconds: the vehicle slows as
    it nears a face (a first-order approach, so a velocity loop several times faster
    than `approach` stops short of it) and never moves outward on or beyond it.
    Inward components are untouched, so no component ever grows.

    Without a finite position estimate nothing can be checked, so the result is zero
    (hover), as it is for a non-finite velocity.
    """
    v = np.asarray(v_world, dtype=float)
    if position is None or not np.isfinite(position).all() or not np.isfinite(v).all():
        return np.zeros(3)
    p = np.asarray(position, dtype=float)
    with np.errstate(over='ignore'):
        up = np.maximum(np.asarray(hi) - p, 0.0) / approach
        down = np.maximum(p - np.asarray(lo), 0.0) / approach
    return np.clip(v, -down, up)


# SessionConfig fields Session.reconfigure may replace while running.
RECONFIGURABLE = frozenset({'limits', 'stream_rate', 'max_send_rate', 'command_timeout',
                            'link_timeout', 'ack_timeout', 'command_retries'})


def _check_config(config: SessionConfig) -> None:
    if problem := connection_problem(config.connection):
        raise ValueError(f'connection: {problem}')
    if config.stream_rate <= 2.0:
        raise ValueError(f'stream_rate must be above 2 Hz (PX4 needs it), got {config.stream_rate}')
    if not config.max_send_rate >= config.stream_rate:
        raise ValueError(f'max_send_rate must be at least stream_rate ({config.stream_rate} Hz), '
                         f'got {config.max_send_rate}')
    if config.ekf_origin is not None:
        lat, lon, alt = config.ekf_origin
        if not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and -500.0 <= alt <= 10000.0):
            raise ValueError('ekf_origin must be latitude [-90, 90], longitude [-180, 180] deg '
                             f'and altitude [-500, 10000] m, got {config.ekf_origin}')


class Session:
    """MAVLink session: call start(), then the commands below; close() when done."""

    def __init__(self, config: SessionConfig):
        _check_config(config)
        self.config = config
        self._key = load_signing_key(config.signing_key_file) if config.signing_key_file else None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='mavlink-session', daemon=True)
        self._t0 = time.monotonic()
        self._conn = None
        self._opened_at = 0.0
        self._next_open = 0.0
        self._open_error = ''
        self._next_open_warning = 0.0
        self._peer_closed = False
        self._link = LinkState.CONNECTING
        self._reconnects = 0
        self._target: tuple[int, int] | None = None
        self._autopilot = self._vehicle_type = self._mode = None
        self._mav_type = None
        self._armed = False
        self._prearm_bit = self._gps_fix = self._battery = None
        self._ekf: EkfStatus | None = None
        self._origin_set = False
        self._next_origin = 0.0
        self._last_hb = None
        self._vehicle_signs = False        # the last HEARTBEAT carried a signature
        self._heartbeat_verified = False   # ... made with our key
        self._rejected = dict.fromkeys((UNSIGNED, BAD_SIGNATURE, OLD_TIMESTAMP), 0)
        self._rejected_at: dict[str, float] = {}   # cause -> time.monotonic() of the latest
        self._texts = collections.deque(maxlen=20)   # (monotonic time, text)
        self._acks: dict[int, int] = {}
        self._waiting: set[int] = set()
        self._telemetry = Telemetry()
        self._seen: dict[str, float] = {}
        self._next_stream_check = 0.0
        self._next_heartbeat = 0.0
        self._command_state = CommandState.IDLE
        self._setpoint = ((0.0, 0.0, 0.0), 0.0, False)   # ENU/FLU velocity, yaw rate, body?
        self._last_command = 0.0
        self._next_setpoint = 0.0
        self._send_credit = float(SEND_BURST)   # setpoints that may be written now
        self._credit_at = time.monotonic()      # when the credit was last refilled
        self._unsent = False                # the newest command waits for its send slot
        self._held = 0                      # commands that waited for a send token
        self._coalesced = 0                 # commands replaced by a newer one before sending
        self._handlers = {
            'HEARTBEAT': self._on_heartbeat, 'COMMAND_ACK': self._on_ack,
            'STATUSTEXT': self._on_statustext, 'LOCAL_POSITION_NED': self._on_local_position,
            'ATTITUDE': self._on_attitude, 'GLOBAL_POSITION_INT': self._on_global_position,
            'SYS_STATUS': self._on_sys_status, 'EKF_STATUS_REPORT': self._on_ekf_status,
            'GPS_RAW_INT': self._on_gps_raw, 'ODOMETRY': self._on_odometry,
            'GPS_GLOBAL_ORIGIN': self._on_gps_global_origin}

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> 'Session':
        self._thread.start()
        return self

    def close(self) -> None:
        with self._cond:   # a command waiting for its send slot still goes out
            self._cond.wait_for(lambda: not self._unsent_waiting(), 2.0 / self.config.max_send_rate)
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        with self._cond:
            self._close_connection()

    def __enter__(self) -> 'Session':
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def reconfigure(self, **changes) -> None:
        """Replace settings of RECONFIGURABLE while running (limits, timeouts, rates):
        checked as at start, then swapped in one piece under the session's lock, so a
        command is limited and timed by the old settings or the new ones, never a mix.
        Raises ValueError (nothing changed) for another field or a bad value."""
        fixed = set(changes) - RECONFIGURABLE
        if fixed:
            raise ValueError(f'cannot be changed while running: {", ".join(sorted(fixed))}')
        config = replace(self.config, **changes)
        _check_config(config)
        with self._cond:
            self.config = config
            v, yaw_rate, body = self._setpoint     # the one re-streamed obeys the new limits
            self._setpoint = (*limit_velocity(v, yaw_rate, config.limits), body)

    # ---------------------------------------------------------------- state
    def status(self) -> Status:
        with self._cond:
            now = time.monotonic()
            known = self._autopilot is not None
            origin = self._origin_set if self.config.ekf_origin is not None else None
            ekf_flags = None if self._ekf is None else self._ekf.flags
            reasons = tuple(prearm_reasons(self._autopilot, self._prearm_bit, ekf_flags,
                                           self._gps_fix, origin)) if known else ()
            return Status(
                link=self._link, autopilot=self._autopilot, vehicle_type=self._vehicle_type,
                system_id=self._target[0] if self._target else None, mode=self._mode,
                armed=self._armed, command=self._command_state,
                prearm_ok=not reasons if known else None, prearm_reasons=reasons,
                battery_voltage=self._battery,
                heartbeat_age=None if self._last_hb is None else now - self._last_hb,
                reconnects=self._reconnects, signing=self._key is not None,
                vehicle_signs=self._vehicle_signs, rejected_unsigned=self._rejected[UNSIGNED],
                rejected_bad_signature=self._rejected[BAD_SIGNATURE],
                rejected_old_timestamp=self._rejected[OLD_TIMESTAMP],
                signing_problem=self._signing_problem(now),
                statustext=tuple(text for _, text in self._texts), held=self._held, coalesced=self._coalesced,
                link_reason=self._open_error if self._conn is None else '',
                ekf=self._ekf, gps_fix=self._gps_fix, ekf_origin_set=origin)

    def telemetry(self) -> Telemetry:
        with self._cond:
            return self._telemetry

    def wait_connected(self, timeout: float = 10.0) -> Status:
        """Block until a vehicle HEARTBEAT has been heard; raise AutopilotError on timeout."""
        with self._cond:
            self._wait(lambda: self._link is LinkState.CONNECTED, timeout, 'a vehicle HEARTBEAT',
                       need_link=False)
        return self.status()

    # ---------------------------------------------------------------- velocity
    def send_velocity(self, linear, yaw_rate: float = 0.0, body: bool = False) -> bool:
        """Command a velocity: `linear` in world ENU (body=False) or base_link FLU [m/s], yaw
        rate about z-up [rad/s].

        Limited, then sent at once and re-streamed until the next call; after
        command_timeout without a call, zero is streamed (hover). At most max_send_rate
        setpoints are written per second, SEND_BURST back to back: a command arriving when
        that is used up waits for the next token (at most one interval), and a newer
        command replaces it meanwhile (counted as coalesced), so the newest is always the
        one flown.
        Returns False, sending nothing, while the link is down or a takeoff/landing holds
        commands. Raises ValueError for a command that is not three finite numbers and a
        finite yaw rate.
        """
        v = tuple(linear)
        if len(v) != 3:
            raise ValueError(f'velocity command needs 3 components, got {len(v)}')
        with self._cond:
            v, yaw_rate = limit_velocity(v, yaw_rate, self.config.limits)
            if self._link is not LinkState.CONNECTED or self._command_state is CommandState.LOCKED:
                return False
            now = time.monotonic()
            self._setpoint = (v, yaw_rate, bool(body))
            self._last_command = now
            if self._unsent and self._command_state is not CommandState.IDLE:
                self._coalesced += 1            # the held command, replaced before it was sent
            self._command_state = CommandState.ACTIVE
            credit = self._refill(now)
            if credit >= 1.0:
                self._send_setpoint(now, credit)
            else:
                self._unsent = True   # the link thread sends it when the next token comes
                self._held += 1
                self._next_setpoint = now + (1.0 - self._send_credit) / self.config.max_send_rate
            return True

    def send_vision_pose(self, position, orientation, stamp: float,
                         covariance: np.ndarray | None = None, pos_std: float = 0.1,
                         angle_std: float = 0.05, reset_counter: int = 0) -> bool:
        """Forward a world ENU pose (position [m], FLU->ENU quaternion x, y, z, w) as
        VISION_POSITION_ESTIMATE (NED, FRD Euler angles), as external navigation is fed
        to the ArduPilot/PX4 EKFs.

        `stamp` is the pose time (UNIX seconds); `covariance` a 6x6 ROS pose covariance
        (ENU position, FLU rotation), or None for diag(pos_std^2, angle_std^2); see
        yaw_only_attitude for what is sent of its rotation block.
        """
        p = frames.enu_to_ned(position)
        roll, pitch, yaw = frames.attitude_enu_to_ned(orientation)
        if covariance is None:
            covariance = np.diag([pos_std ** 2] * 3 + [angle_std ** 2] * 3)
        ned = yaw_only_attitude(frames.pose_covariance_enu_to_ned(covariance))
        cov = ned[np.triu_indices(6)]
        values = np.concatenate([p, [roll, pitch, yaw], cov])
        if not (np.abs(values) <= FLOAT32_MAX).all():   # NaN fails too
            raise ValueError('vision pose or covariance is not finite in float32 (the wire type)')
        if not 0.0 <= stamp < 2.0 ** 64 / 1e6:
            raise ValueError(f'vision pose stamp {stamp} s is not a time since the epoch')
        with self._cond:
            if self._link is not LinkState.CONNECTED:
                return False
            self._conn.mav.vision_position_estimate_send(
                int(stamp * 1e6), *p, float(roll), float(pitch), float(yaw), cov.tolist(),
                reset_counter)
            return True

    # ---------------------------------------------------------------- commands
    def set_mode(self, name: str, timeout: float = 5.0) -> None:
        """Change flight mode by MAV_CMD_DO_SET_MODE and wait until HEARTBEAT reports it.

        Names are the autopilot's own (ArduPilot: GUIDED, LAND, LOITER, ...; PX4:
        OFFBOARD, POSCTL, LAND, ...). PX4 enters OFFBOARD only while setpoints flow, so
        zero velocity is streamed for 1.5 s before (PX4 wants more than a second) and during
        the switch.
        """
        name = name.upper()
        with self._cond:
            self._require_link()
            if self._autopilot == PX4:
                if name not in mavutil.px4_map:
                    raise ValueError(f'unknown PX4 mode {name}; known: {sorted(mavutil.px4_map)}')
                _, main, sub = mavutil.px4_map[name]
                params = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)
                if name == 'OFFBOARD':
                    self._command_state = CommandState.HOVER
                    self._wait(lambda: False, 1.5, 'the OFFBOARD setpoint stream', raise_on_timeout=False)
            else:
                modes = mavutil.mode_mapping_byname(self._mav_type) or {}
                if name not in modes:
                    raise ValueError(f'unknown mode {name} for {self._vehicle_type}; known: {sorted(modes)}')
                params = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, modes[name], 0)
            self._command(mavlink.MAV_CMD_DO_SET_MODE, *params)
            self._wait(lambda: self._mode == name, timeout, f'HEARTBEAT to report mode {name}')
            if name in _LANDING_MODES:
                self._command_state = CommandState.LOCKED
            elif self._command_state is not CommandState.HOVER:
                self._command_state = CommandState.IDLE

    def set_guided(self, timeout: float = 5.0) -> None:
        """Enter the mode that flies velocity setpoints: ArduPilot GUIDED, PX4 OFFBOARD."""
        with self._cond:
            self._require_link()
            mode = VELOCITY_MODE.get(self._autopilot, 'GUIDED')
        self.set_mode(mode, timeout)

    def arm(self, timeout: float = 5.0) -> None:
        """Arm (only with allow_arming) and wait for HEARTBEAT to say so."""
        if not self.config.allow_arming:
            raise AutopilotError('arming is disabled: set allow_arming to let the relay arm')
        with self._cond:
            self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            self._wait(lambda: self._armed, timeout, 'HEARTBEAT to report armed')

    def disarm(self, force: bool = False, timeout: float = 5.0) -> None:
        """Disarm; `force` overrides the autopilot's in-flight refusal (motors stop!)."""
        with self._cond:
            self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, FORCE_DISARM if force else 0)
            self._wait(lambda: not self._armed, timeout, 'HEARTBEAT to report disarmed')

    def takeoff(self, height: float, timeout: float | None = None) -> None:
        """MAV_CMD_NAV_TAKEOFF to `height` above home, then wait until it is reached.

        Velocity commands are refused meanwhile: ArduPilot aborts the climb on the first
        velocity target. ArduPilot needs GUIDED and armed; PX4 takes its AMSL altitude.
        """
        if not (math.isfinite(height) and height > 0):
            raise ValueError(f'takeoff height must be a positive number of metres, got {height}')
        timeout = 10.0 + 2.0 * height if timeout is None else timeout
        with self._cond:
            self._require_link()
            self._command_state = CommandState.LOCKED
            try:
                if self._autopilot == PX4:
                    tel = self._telemetry
                    if tel.altitude is None or tel.height is None:
                        raise AutopilotError('no GLOBAL_POSITION_INT yet: PX4 needs an AMSL takeoff altitude')
                    nan = math.nan
                    self._command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, nan, nan, nan,
                                  tel.altitude - tel.height + height)
                else:
                    self._command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, height)
                self._wait(lambda: (self._telemetry.height or 0.0) >= 0.95 * height, timeout,
                           f'takeoff height {height:.2f} m')
            finally:
                self._command_state = CommandState.IDLE

    def land(self, timeout: float = 5.0) -> None:
        """Land where we are (ArduPilot LAND mode, PX4 MAV_CMD_NAV_LAND); commands stop."""
        with self._cond:
            self._require_link()
            self._command_state = CommandState.LOCKED
            if self._autopilot != PX4:
                self.set_mode('LAND', timeout)
                return
            nan = math.nan
            self._command(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, nan, nan, nan, nan)
            self._wait(lambda: self._mode == 'LAND', timeout, 'HEARTBEAT to report LAND')

    def install_signing_key(self, timeout: float = 3.0) -> None:
        """Send SETUP_SIGNING with our key and wait for a signed vehicle HEARTBEAT.

        SETUP_SIGNING has no ACK and the autopilot refuses it while armed. Run with
        signing_required=False to reach a vehicle that does not sign yet.
        """
        if self._key is None:
            raise AutopilotError('no signing key: set signing_key_file')
        with self._cond:
            self._require_link()
            if self._armed:
                raise AutopilotError('SETUP_SIGNING is refused while armed: disarm first')
            self._heartbeat_verified = False
            self._conn.mav.setup_signing_send(*self._target, list(self._key),
                                              self._conn.mav.signing.timestamp)
            self._wait(lambda: self._heartbeat_verified, timeout, 'a signed HEARTBEAT')

    # ---------------------------------------------------------------- internals (lock held)
    def _require_link(self) -> None:
        if self._link is not LinkState.CONNECTED:
            problem = self._signing_problem(time.monotonic())
            raise AutopilotError(f'no link to the autopilot ({self._link.value})'
                                 + (f': {problem}' if problem else ''))

    def _signing_problem(self, now: float) -> str | None:
        """What stops signed communication, in plain words, or None.

        Connected: a vehicle whose HEARTBEAT is signed when we have no key (it drops
        every unsigned command on a link where it enforces signing), or signed with
        another key. Not connected: the frames dropped for their signature in the last
        link_timeout, which say why no vehicle is heard.
        """
        if self._link is LinkState.CONNECTED:
            if self._vehicle_signs and self._key is None:
                return 'vehicle signs its messages, we have no key (set signing_key_file)'
            if self._vehicle_signs and not self._heartbeat_verified:
                return 'vehicle signs with another key (wrong key?)'
            return None
        recent = [cause for cause in _REJECTED
                  if now - self._rejected_at.get(cause, -math.inf) < self.config.link_timeout]
        return _REJECTED[recent[0]] if recent else None

    def _wait(self, predicate, timeout: float, what: str, need_link: bool = True,
              raise_on_timeout: bool = True) -> bool:
        """Wait (lock released) until predicate(); raise if the link drops or the session closes."""
        lost = (lambda: self._link is not LinkState.CONNECTED) if need_link else (lambda: False)
        self._cond.wait_for(lambda: predicate() or lost() or self._stop.is_set(), timeout)
        if predicate():
            return True
        if lost():
            raise AutopilotError(f'link lost while waiting for {what}')
        if self._stop.is_set():
            raise AutopilotError(f'session closed while waiting for {what}')
        if raise_on_timeout:
            raise AutopilotError(f'timed out after {timeout:.1f} s waiting for {what}')
        return False

    def _command(self, command: int, *params: float) -> None:
        """COMMAND_LONG, retried with rising confirmation until a COMMAND_ACK; raise unless ACCEPTED."""
        self._require_link()
        p = (list(params) + [0.0] * 7)[:7]
        sent = time.monotonic()
        self._acks.pop(command, None)
        self._waiting.add(command)
        try:
            for confirmation in range(self.config.command_retries + 1):
                self._conn.mav.command_long_send(*self._target, command, confirmation, *p)
                while self._wait(lambda: command in self._acks, self.config.ack_timeout,
                                 _enum_name('MAV_CMD', command), raise_on_timeout=False):
                    result = self._acks.pop(command)
                    if result == mavlink.MAV_RESULT_IN_PROGRESS:
                        continue
                    if result == mavlink.MAV_RESULT_ACCEPTED:
                        return
                    # the reason usually comes just before the ACK, sometimes just after
                    until = time.monotonic() + _REASON_GRACE
                    self._cond.wait_for(lambda: self._texts_between(sent, until), _REASON_GRACE)
                    raise CommandError(command, result, self._texts_between(sent, until))
            now = time.monotonic()
            raise CommandError(command, None, self._texts_between(sent, now),
                               self._signing_problem(now))
        finally:
            self._waiting.discard(command)

    def _texts_between(self, start: float, end: float) -> list[str]:
        """STATUSTEXT received in [start, end] (time.monotonic()), oldest first."""
        return [text for stamp, text in self._texts if start <= stamp <= end]

    def _send_setpoint(self, now: float, credit: float) -> None:
        """Write the current setpoint (zero when hovering), fenced, in the autopilot's frame;
        `credit` is the send credit refilled to `now`."""
        v, yaw_rate, body = self._setpoint
        if self._command_state is CommandState.HOVER:
            v, yaw_rate = (0.0, 0.0, 0.0), 0.0
        limits = self.config.limits
        if limits.fence_min is not None and limits.fence_max is not None:
            v, body = self._fenced(v, body), False
        if body:
            frame, (vx, vy, vz) = BODY_FRAME.get(self._autopilot, mavlink.MAV_FRAME_BODY_NED), frames.flu_to_frd(v)
        else:
            frame, (vx, vy, vz) = mavlink.MAV_FRAME_LOCAL_NED, frames.enu_to_ned(v)
        self._conn.mav.set_position_target_local_ned_send(
            int((now - self._t0) * 1e3) & 0xFFFFFFFF, *self._target, frame, VELOCITY_YAW_RATE_MASK,
            0.0, 0.0, 0.0, vx, vy, vz, 0.0, 0.0, 0.0, 0.0, float(frames.yaw_rate_enu_to_ned(yaw_rate)))
        self._send_credit = max(credit - 1.0, 0.0)
        self._next_setpoint = now + 1.0 / self.config.stream_rate
        if self._unsent:
            self._unsent = False
            self._cond.notify_all()     # close() waits for a held command to go out

    def _refill(self, now: float) -> float:
        """The send credit, refilled at max_send_rate since the last refill, at most SEND_BURST."""
        elapsed, self._credit_at = now - self._credit_at, now
        if elapsed > 0.0:
            self._send_credit = min(float(SEND_BURST),
                                    self._send_credit + elapsed * self.config.max_send_rate)
        return self._send_credit

    def _unsent_waiting(self) -> bool:
        """A coalesced command waits for its send slot (dropped if the stream stopped)."""
        return self._unsent and self._command_state in (CommandState.ACTIVE, CommandState.HOVER) \
            and self._link is LinkState.CONNECTED

    def _fenced(self, v, body: bool) -> np.ndarray:
        """The world velocity of a command, limited by the fence; zero without a finite
        estimate of the position (or, for a body command, of the heading)."""
        tel = self._telemetry
        if body:
            yaw = frames.yaw_of(tel.orientation) if tel.orientation is not None else math.nan
            if not math.isfinite(yaw):
                return np.zeros(3)
            v = frames.body_to_world(v, yaw)
        limits = self.config.limits
        return fence_velocity(v, tel.position, limits.fence_min, limits.fence_max,
                              limits.fence_approach)

    # ---------------------------------------------------------------- background thread
    def _run(self) -> None:
        while not self._stop.is_set():
            conn = self._conn
            if conn is None:
                self._open(time.monotonic())
                continue
            conn.select(self._poll_timeout(time.monotonic()))
            with self._cond:
                try:
                    while (msg := conn.recv_msg()) is not None:
                        self._handle(msg)
                except OSError as e:
                    log.warning('MAVLink link error: %s', e)
                    self._peer_closed = True
                self._tick(time.monotonic())

    def _poll_timeout(self, now: float) -> float:
        """How long the link thread may wait for input: 10 ms, less when a coalesced
        command's send slot comes sooner."""
        if not self._unsent_waiting():
            return 0.01
        return min(0.01, max(self._next_setpoint - now, 0.0))

    def _open(self, now: float) -> None:
        if now < self._next_open:
            self._stop.wait(min(self._next_open - now, 0.1))
            return
        self._next_open = now + 1.0
        cfg = self.config
        try:
            conn = open_connection(cfg.connection, cfg.baud, cfg.source_system, cfg.source_component)
        except (OSError, ValueError) as e:
            self._open_failed(e, now)
            return
        if isinstance(conn, mavutil.mavtcp):
            conn.handle_eof = conn.handle_disconnect = self._on_peer_closed
        if self._key is not None:
            if cfg.signing_required:
                def allow(mav, msg_id): return msg_id in _UNSIGNED_OK
            else:
                def allow(mav, msg_id): return True
            conn.setup_signing(self._key, sign_outgoing=True, allow_unsigned_callback=allow)
        with self._cond:
            self._conn, self._opened_at, self._peer_closed = conn, now, False
        log.info('opened %s', cfg.connection)

    def _open_failed(self, err: Exception, now: float) -> None:
        """Say why the connection cannot be opened: at once, then every
        OPEN_WARNING_PERIOD while the same reason lasts.

        Retrying goes on whatever the reason, an unknown host included: a GCS radio or
        VPN link, or the DNS itself, may come up after the relay (at boot, in the field),
        and an operator watching the diagnostics sees the reason meanwhile.
        """
        reason = open_failure(self.config.connection, err)
        with self._cond:
            repeated = reason == self._open_error and now < self._next_open_warning
            self._open_error = reason
        if not repeated:
            self._next_open_warning = now + OPEN_WARNING_PERIOD
            log.warning('%s; retrying every second', reason)

    def _on_peer_closed(self) -> None:
        self._peer_closed = True

    def _close_connection(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None

    def _tick(self, now: float) -> None:
        last = max(self._last_hb or 0.0, self._opened_at)
        if self._peer_closed or now - last > self.config.link_timeout:
            self._lose_link(now)
            return
        if now >= self._next_heartbeat:
            self._conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                          0, 0, mavlink.MAV_STATE_ACTIVE)
            self._next_heartbeat = now + 1.0
        if self._link is not LinkState.CONNECTED:
            return
        if now >= self._next_stream_check:
            self._request_streams(now)
        if self.config.ekf_origin is not None and not self._origin_set and now >= self._next_origin:
            self._send_origin(now)
        state = self._command_state
        if state is CommandState.ACTIVE and now - self._last_command > self.config.command_timeout:
            self._command_state = state = CommandState.HOVER
            log.info('command input stale for %.2f s: hovering', now - self._last_command)
        if state in (CommandState.ACTIVE, CommandState.HOVER) and now >= self._next_setpoint:
            self._send_setpoint(now, self._refill(now))

    def _lose_link(self, now: float) -> None:
        if self._link is LinkState.CONNECTED:
            log.warning('link lost: no HEARTBEAT for %.1f s; reconnecting', now - (self._last_hb or now))
        self._close_connection()
        if self._link is LinkState.CONNECTED:
            self._link = LinkState.LOST
        self._command_state = CommandState.IDLE
        self._setpoint = ((0.0, 0.0, 0.0), 0.0, False)
        self._acks.clear()
        self._last_hb = None
        self._prearm_bit = self._gps_fix = self._ekf = None   # re-read: it may have rebooted
        self._origin_set = False
        self._cond.notify_all()

    def _send_origin(self, now: float) -> None:
        """SET_GPS_GLOBAL_ORIGIN (1e-7 deg, mm), once a second until GPS_GLOBAL_ORIGIN comes:
        an EKF still starting ignores it."""
        lat, lon, alt = self.config.ekf_origin
        self._conn.mav.set_gps_global_origin_send(self._target[0], round(lat * 1e7),
                                                  round(lon * 1e7), round(alt * 1e3),
                                                  int(time.time() * 1e6))
        self._next_origin = now + 1.0

    def _request_streams(self, now: float) -> None:
        """SET_MESSAGE_INTERVAL for every wanted message not seen lately (per link, lost on reboot)."""
        for name, rate in self.config.rates.items():
            if (name in _ARDUPILOT_ONLY and self._autopilot != ARDUPILOT
                    or name in _PX4_ONLY and self._autopilot != PX4):
                continue
            if now - self._seen.get(name, -math.inf) > max(1.0, 3.0 / rate):
                self._conn.mav.command_long_send(
                    *self._target, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                    getattr(mavlink, f'MAVLINK_MSG_ID_{name}'), 1e6 / rate, 0, 0, 0, 0, 0)
        self._next_stream_check = now + 2.0

    # ---------------------------------------------------------------- message handlers
    def _handle(self, msg) -> None:
        kind = msg.get_type()
        if kind == 'BAD_DATA':
            if self._key is not None and 'signature' in str(getattr(msg, 'reason', '')):
                cause = rejection_cause(self._key, msg.data)
                self._rejected[cause] += 1
                self._rejected_at[cause] = time.monotonic()
            return
        handler = self._handlers.get(kind)
        if handler is None:
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == 'HEARTBEAT':
            handler(msg, src)
        elif self._target is not None and src[0] == self._target[0] and (
                kind == 'STATUSTEXT' or src[1] == self._target[1]):
            self._seen[kind] = time.monotonic()
            handler(msg)

    def _on_heartbeat(self, msg, src) -> None:
        if msg.type in _NOT_VEHICLES or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
            return
        if self._target is None:
            if self.config.target_system not in (0, src[0]):
                return
            self._target = src
        if src != self._target:
            return
        now = time.monotonic()
        self._last_hb = now
        self._vehicle_signs = bool(msg.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED)
        self._heartbeat_verified = msg.get_signed()   # pymavlink: only with our key
        self._autopilot = _AUTOPILOTS.get(msg.autopilot, GENERIC)
        self._mav_type = msg.type
        self._vehicle_type = _enum_name('MAV_TYPE', msg.type).removeprefix('MAV_TYPE_')
        self._mode = mavutil.mode_string_v10(msg)
        self._armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if self._link is not LinkState.CONNECTED:
            if self._link is LinkState.LOST:
                self._reconnects += 1
            self._link = LinkState.CONNECTED
            self._seen.clear()
            self._next_stream_check = now
            log.info('connected to %s %s (system %d)', self._autopilot, self._vehicle_type, src[0])
        self._cond.notify_all()

    def _on_ack(self, msg) -> None:
        """A COMMAND_ACK is ours when its (target_system, target_component) are our own
        (source_system, source_component), or both 0: an autopilot that predates these
        MAVLink 2 extension fields leaves them 0. Any other ack answers another ground
        station's command: a MAVProxy beside the relay also sends as system 255, so the
        system alone cannot tell its acks (refusals included) from ours."""
        target = (msg.target_system, msg.target_component)
        if target not in ((0, 0), (self.config.source_system, self.config.source_component)):
            return
        if msg.command in self._waiting:
            # A retry sent because the first ACK was late is refused by an autopilot
            # already carrying the command out: its refusal may arrive right after the
            # first copy's ACCEPTED, before the caller has seen it, and must not hide it.
            if self._acks.get(msg.command) != mavlink.MAV_RESULT_ACCEPTED:
                self._acks[msg.command] = msg.result
            self._cond.notify_all()
        elif msg.result != mavlink.MAV_RESULT_ACCEPTED:
            log.warning('%s refused: %s', _enum_name('MAV_CMD', msg.command),
                        _enum_name('MAV_RESULT', msg.result))

    def _on_statustext(self, msg) -> None:
        text = msg.text.rstrip('\x00') if isinstance(msg.text, str) else msg.text.decode(errors='replace')
        self._texts.append((time.monotonic(), text))
        log.log(statustext_level(msg.severity), 'autopilot: %s', text)
        self._cond.notify_all()

    def _update(self, **fields) -> None:
        self._telemetry = replace(self._telemetry, stamp=time.monotonic(), **fields)
        self._cond.notify_all()

    def _on_local_position(self, msg) -> None:
        self._update(position=frames.ned_to_enu([msg.x, msg.y, msg.z]),
                     velocity=frames.ned_to_enu([msg.vx, msg.vy, msg.vz]))

    def _on_attitude(self, msg) -> None:
        self._update(orientation=frames.attitude_ned_to_enu(msg.roll, msg.pitch, msg.yaw),
                     angular_velocity=frames.frd_to_flu([msg.rollspeed, msg.pitchspeed, msg.yawspeed]))

    def _on_odometry(self, msg) -> None:
        """The covariances of PX4's estimate (its pose and velocity come from
        LOCAL_POSITION_NED and ATTITUDE, as for ArduPilot). An attitude that is no rotation
        (zero or non-finite) leaves the twist covariance unknown."""
        pose = frames.covariance_from_upper(msg.pose_covariance)
        velocity = frames.covariance_from_upper(msg.velocity_covariance)
        frame = _VELOCITY_FRAMES.get(msg.child_frame_id)
        w, x, y, z = msg.q
        norm = math.hypot(w, x, y, z)
        twist = None
        if velocity is not None and frame is not None and 0.0 < norm < math.inf:
            q_enu_flu = frames.quat_ned_to_enu(np.array([x, y, z, w]) / norm)
            twist = np.zeros((6, 6))
            twist[:3, :3] = frames.velocity_covariance_to_flu(velocity[:3, :3], frame, q_enu_flu)
            twist[3:, 3:] = frames.R_FLU_FRD @ velocity[3:, 3:] @ frames.R_FLU_FRD.T
        self._update(pose_covariance=None if pose is None else frames.pose_covariance_ned_to_enu(pose),
                     twist_covariance=twist)

    def _on_global_position(self, msg) -> None:
        self._update(height=msg.relative_alt * 1e-3, latitude=msg.lat * 1e-7,
                     longitude=msg.lon * 1e-7, altitude=msg.alt * 1e-3)

    def _on_sys_status(self, msg) -> None:
        bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
        self._prearm_bit = bool(msg.onboard_control_sensors_present & bit) and bool(
            msg.onboard_control_sensors_health & bit)
        self._battery = msg.voltage_battery * 1e-3 if msg.voltage_battery != 0xFFFF else None

    def _on_ekf_status(self, msg) -> None:
        self._ekf = EkfStatus(msg.flags, msg.velocity_variance, msg.pos_horiz_variance,
                              msg.pos_vert_variance, msg.compass_variance)

    def _on_gps_global_origin(self, msg) -> None:
        if self.config.ekf_origin is not None and not self._origin_set:
            log.info('EKF origin set: %.7f, %.7f, %.2f m', msg.latitude * 1e-7,
                     msg.longitude * 1e-7, msg.altitude * 1e-3)
        self._origin_set = True

    def _on_gps_raw(self, msg) -> None:
        self._gps_fix = msg.fix_type
