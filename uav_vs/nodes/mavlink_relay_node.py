"""mavlink_relay_node: velocity commands to an ArduPilot/PX4 autopilot, its estimate back.

The chapter's controllers (sections 5 and 6) command velocities; this node hands them
to the autopilot through uav_vs.autopilot.session (MAVLink, pymavlink) and publishes
what the autopilot estimates, the comparison of Fig. 6.

Subscribes `cmd_vel` (geometry_msgs/TwistStamped): header.frame_id `world_frame`
(ENU) or `body_frame` (FLU) selects the frame; linear x, y, z [m/s] and angular z
[rad/s] are used. Another frame or a non-finite value is counted as malformed and
skipped. A publisher of another type on `cmd_vel` (e.g. geometry_msgs/Twist) is never
heard: the relay warns once per publisher and type, naming both types, and lists it in
the diagnostics (`cmd_vel_wrong_type`), polled with the diagnostics. Optionally
subscribes `vision_pose_topic` (in `world_frame`, of `vision_pose_type`: PoseStamped with
the `vision.*` standard deviations, or PoseWithCovarianceStamped or nav_msgs/Odometry,
e.g. pose_filter_node's fused/odom, with the covariance it carries) and forwards it to
the autopilot's EKF as VISION_POSITION_ESTIMATE (roll and pitch with the yaw's variance:
Session.send_vision_pose); a covariance that is not one is malformed.
Publishes `autopilot/odom` (nav_msgs/Odometry: pose in `world_frame`, twist in
`body_frame`, REP-105; covariances from PX4's ODOMETRY, zero (unknown) from ArduPilot,
which reports none) and link, mode, arming, readiness and command state on /diagnostics.
Services (std_srvs): `arm` (SetBool: true arms, only with `allow_arming`; false
disarms), `takeoff` (Trigger, to `takeoff_height`), `land`, `set_guided` (GUIDED on
ArduPilot, OFFBOARD on PX4) and `install_signing_key` (Trigger).

Threading: one executor thread runs `cmd_vel`, the vision pose and the timers; each
command is handed to the autopilot from its callback, as soon as it is taken, and
written at once unless `max_send_rate` says wait (then the newest goes out within one
interval). The services block for seconds (a takeoff waits for its height), so each
one runs on a worker thread that the executor awaits: their own mutually exclusive
callback group keeps it to one flight command at a time, and the executor is never
held up. `cmd_vel` keeps the last 10 messages (best effort), so a short stall delays
commands and the burst after it is coalesced to its newest. The session's own
watchdog turns stale input into a hover whatever the executor does.
The session's log lines (opened, connected, hovering, link lost, an unknown host, the
autopilot's STATUSTEXT) go to this node's logger at their severity, so to the console
and /rosout, filtered by its level of the moment; an unknown host is retried (a radio,
VPN or DNS may come up later) and named in the diagnostics' `link_reason` meanwhile.

Set at run time, the limits, the fence, the timeouts and the setpoint rates are checked
as at start-up (the fence's corners and the two rates together) and swapped into the
session in one piece (Session.reconfigure); the connection, signing, arming interlock,
frames, topics and timer periods are read-only.
"""
import threading
import time
from typing import Callable

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.duration import Duration
from rclpy.exceptions import NameValidationException
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from std_msgs.msg import Header
from std_srvs.srv import SetBool, Trigger

from uav_vs.autopilot.link import connection_problem, key_file_exposure, load_signing_key
from uav_vs.autopilot.session import (AutopilotError, CommandState, EkfStatus, LinkState, Limits,
                                      Session, SessionConfig)
from uav_vs.ros import log_bridge
from uav_vs.ros.convert import msg_to_pose, msg_to_pose_cov_in, odometry_to_msg, stamp_to_ns
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, ThrottledWarnings, run
from uav_vs.ros.params import LiveParams, Param, ParameterError, T, declare

# cmd_vel: room for the commands of a short executor stall, relayed in order.
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
# vision pose: only the newest is worth forwarding.
NEWEST_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
CMD_VEL_TYPE = 'geometry_msgs/msg/TwistStamped'
# What graph queries name a node whose name has not been discovered yet (it comes after
# its endpoints), and how many diagnostics periods a publisher may stay so before it is
# warned about unnamed (a DDS program that is no ROS node stays so).
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'
UNNAMED_PERIODS = 3
RATES = {'rates.local_position': 'LOCAL_POSITION_NED', 'rates.attitude': 'ATTITUDE',
         'rates.global_position': 'GLOBAL_POSITION_INT', 'rates.sys_status': 'SYS_STATUS',
         'rates.ekf_status': 'EKF_STATUS_REPORT', 'rates.gps_raw': 'GPS_RAW_INT',
         'rates.odometry': 'ODOMETRY'}

# vision_pose_type -> the message type subscribed
VISION_TYPES = {'pose': PoseStamped, 'pose_cov': PoseWithCovarianceStamped, 'odometry': Odometry}

PARAMS = [
    Param('connection', T.STRING, description=(
        'pymavlink connection string: tcp:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT, '
        'or a serial device (/dev/ttyACM0)')),
    Param('baud', T.INTEGER, 115200, 'serial baud rate (serial devices only)', 1200, 4000000),
    Param('source_system', T.INTEGER, 255, 'our MAVLink system id (255: a GCS)', 1, 255),
    Param('source_component', T.INTEGER, 190, 'our component id (190: MISSIONPLANNER)', 0, 255),
    Param('target_system', T.INTEGER, 0, "the autopilot's system id (0: first vehicle heard)",
          0, 255),
    # rates.*: requested when the link comes up or a message stops, hence read-only
    Param('rates.local_position', T.DOUBLE, 20.0, 'LOCAL_POSITION_NED rate requested, Hz',
          0.1, 200.0),
    Param('rates.attitude', T.DOUBLE, 20.0, 'ATTITUDE rate requested, Hz', 0.1, 200.0),
    Param('rates.global_position', T.DOUBLE, 5.0, 'GLOBAL_POSITION_INT rate requested, Hz',
          0.1, 200.0),
    Param('rates.sys_status', T.DOUBLE, 1.0, 'SYS_STATUS rate requested, Hz', 0.1, 50.0),
    Param('rates.ekf_status', T.DOUBLE, 1.0, 'EKF_STATUS_REPORT rate requested (ArduPilot), Hz',
          0.1, 50.0),
    Param('rates.gps_raw', T.DOUBLE, 1.0, 'GPS_RAW_INT rate requested (ArduPilot), Hz', 0.1, 50.0),
    Param('rates.odometry', T.DOUBLE, 20.0, 'ODOMETRY rate requested (PX4: the covariances '
          'of autopilot/odom), Hz', 0.1, 200.0),
    Param('stream_rate', T.DOUBLE, 10.0, 'setpoint re-send rate, Hz (PX4 needs > 2)', 2.5, 100.0,
          live=True),
    Param('max_send_rate', T.DOUBLE, 50.0, 'most setpoints written per second (>= stream_rate): '
          'faster cmd_vel is coalesced, the newest sent within one interval, Hz', 2.5, 1000.0,
          live=True),
    Param('command_timeout', T.DOUBLE, 0.5, 'cmd_vel older than this -> zero velocity (hover), s',
          0.05, 2.5, live=True),
    Param('link_timeout', T.DOUBLE, 3.0, 'no HEARTBEAT (1 Hz) for this long -> link lost, '
          'reconnect, s', 1.5, 60.0, live=True),
    Param('ack_timeout', T.DOUBLE, 1.0, 'wait for each COMMAND_ACK, s', 0.1, 10.0, live=True),
    Param('command_retries', T.INTEGER, 2, 'COMMAND_LONG re-sends without an ACK', 0, 10,
          live=True),
    Param('limits.max_speed', T.DOUBLE, 2.0, 'horizontal speed limit, m/s', 0.0, 30.0, live=True),
    Param('limits.max_climb', T.DOUBLE, 1.0, 'upward speed limit, m/s', 0.0, 10.0, live=True),
    Param('limits.max_descent', T.DOUBLE, 0.7, 'downward speed limit, m/s', 0.0, 10.0, live=True),
    Param('limits.max_yaw_rate', T.DOUBLE, 1.0, 'yaw rate limit, rad/s', 0.0, 6.0, live=True),
    Param('geofence.min', T.DOUBLE_ARRAY, [], 'fence box lower corner [x, y, z] in world ENU, m '
          '(empty: no fence)', live=True),
    Param('geofence.max', T.DOUBLE_ARRAY, [], 'fence box upper corner [x, y, z] in world ENU, m '
          '(empty: no fence)', live=True),
    Param('geofence.approach_time', T.DOUBLE, 1.5, 'outward speed limited to the distance to '
          'the face over this, s', 0.1, 60.0, live=True),
    Param('allow_arming', T.BOOL, False, 'let the arm service arm the motors (read-only: an '
          'interlock is set at launch, not by a parameter call)'),
    Param('takeoff_height', T.DOUBLE, 2.0, 'takeoff service height above home, m', 0.2, 100.0,
          live=True),
    Param('signing_key_file', T.STRING, '', 'file holding the MAVLink 2 signing key '
          "('': no signing)"),
    Param('signing_required', T.BOOL, True, 'with a key: drop unsigned incoming messages'),
    Param('world_frame', T.STRING, 'world', 'ENU world frame: cmd_vel, vision pose, odom header'),
    Param('body_frame', T.STRING, 'base_link', 'FLU body frame: cmd_vel, odom child frame'),
    Param('odom_rate', T.DOUBLE, 20.0, 'autopilot/odom publishing rate, Hz (read-only: the '
          'timer is made at start-up)', 0.5, 200.0),
    Param('diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s (read-only: the timer is '
          'made at start-up)', 0.05, 60.0),
    Param('vision_pose_topic', T.STRING, '', "PoseStamped forwarded as VISION_POSITION_ESTIMATE "
          "('': off)"),
    Param('vision_pose_type', T.STRING, 'pose', "vision_pose_topic's message: 'pose' "
          "(PoseStamped, with vision.position_std and vision.angle_std), 'pose_cov' "
          "(PoseWithCovarianceStamped) or 'odometry' (nav_msgs/Odometry, its pose), the last "
          'two with the covariance they carry', choices=tuple(VISION_TYPES)),
    Param('vision.position_std', T.DOUBLE, 0.1, 'vision position standard deviation, m',
          1e-4, 100.0, live=True),
    Param('vision.angle_std', T.DOUBLE, 0.05, 'vision attitude standard deviation, rad',
          1e-4, 3.2, live=True),
    Param('ekf_origin', T.DOUBLE_ARRAY, [], 'flight without GPS on vision_pose_topic: the EKF '
          'origin [latitude deg, longitude deg, altitude AMSL m], sent as SET_GPS_GLOBAL_ORIGIN '
          'until the autopilot confirms it; readiness then needs no GPS fix ([]: with GPS)'),
]


def session_config(p: dict, logger: RcutilsLogger) -> SessionConfig:
    """SessionConfig from the declared parameters; ParameterError names a bad one, a
    warning about the key file goes to `logger` (the node's)."""
    if problem := connection_problem(p['connection']):
        raise ParameterError(f'connection: {problem}')
    if p['signing_key_file']:
        check_key_file(p['signing_key_file'], logger)
    return SessionConfig(
        connection=p['connection'], baud=p['baud'], source_system=p['source_system'],
        source_component=p['source_component'], target_system=p['target_system'],
        rates={name: p[key] for key, name in RATES.items()}, allow_arming=p['allow_arming'],
        signing_key_file=p['signing_key_file'] or None, signing_required=p['signing_required'],
        ekf_origin=ekf_origin(p), **live_settings(p))


def ekf_origin(p: dict) -> tuple[float, float, float] | None:
    """ekf_origin as (lat, lon, alt), None when empty; ParameterError names a bad one (the
    session checks the ranges)."""
    origin = p['ekf_origin']
    if not origin:
        return None
    if len(origin) != 3:
        raise ParameterError(f'ekf_origin: expected [latitude, longitude, altitude] or [], '
                             f'got {list(origin)}')
    if not p['vision_pose_topic']:
        raise ParameterError('ekf_origin: set without vision_pose_topic: without GPS the EKF '
                             'needs the vision pose')
    return tuple(map(float, origin))


def live_settings(p: dict) -> dict:
    """The SessionConfig fields that may change while running (Session.reconfigure), from
    the parameters, checked together: ParameterError names a bad one."""
    if p['max_send_rate'] < p['stream_rate']:
        raise ParameterError(f"max_send_rate: expected at least stream_rate "
                             f"({p['stream_rate']} Hz), got {p['max_send_rate']}")
    lo, hi = p['geofence.min'], p['geofence.max']
    if len(lo) != len(hi) or len(lo) not in (0, 3):
        raise ParameterError(f'geofence.min: expected 3 numbers with geofence.max (or both empty), '
                             f'got {lo} and {hi}')
    if lo and not all(a < b for a, b in zip(lo, hi)):
        raise ParameterError(f'geofence.min: expected below geofence.max on every axis, '
                             f'got {lo} and {hi}')
    limits = Limits(max_speed=p['limits.max_speed'], max_climb=p['limits.max_climb'],
                    max_descent=p['limits.max_descent'], max_yaw_rate=p['limits.max_yaw_rate'],
                    fence_min=tuple(lo) or None, fence_max=tuple(hi) or None,
                    fence_approach=p['geofence.approach_time'])
    return dict(limits=limits, stream_rate=p['stream_rate'], max_send_rate=p['max_send_rate'],
                command_timeout=p['command_timeout'], link_timeout=p['link_timeout'],
                ack_timeout=p['ack_timeout'], command_retries=p['command_retries'])


def check_key_file(path: str, logger: RcutilsLogger) -> None:
    """ParameterError naming signing_key_file if no key can be read from it (key never shown).

    A key file that group or others may read is used, with a warning naming it and its
    mode: refusing it would leave the operator to fly without signing, and the key may
    already have been read; the fix is a chmod, which the warning gives.
    """
    try:
        load_signing_key(path)
        exposure = key_file_exposure(path)
    except OSError as err:
        raise ParameterError(f'signing_key_file: cannot read {path}: {err.strerror}') from None
    except ValueError as err:
        raise ParameterError(f'signing_key_file: {err}') from None
    if exposure:
        logger.warning(exposure)


def ekf_values(ekf: EkfStatus | None) -> dict[str, str]:
    """EKF_STATUS_REPORT as diagnostics values: flags in hex, innovation test ratios."""
    if ekf is None:
        return {'ekf_flags': ''}
    return {'ekf_flags': f'0x{ekf.flags:x}', 'ekf_navigating': ekf.navigating,
            'ekf_velocity_ratio': f'{ekf.velocity:.3f}', 'ekf_pos_horiz_ratio': f'{ekf.pos_horiz:.3f}',
            'ekf_pos_vert_ratio': f'{ekf.pos_vert:.3f}', 'ekf_compass_ratio': f'{ekf.compass:.3f}'}


class MavlinkRelayNode(Node):
    def __init__(self) -> None:
        super().__init__('mavlink_relay_node')
        p = declare(self, PARAMS)
        config = session_config(p, self.get_logger())
        self.world, self.body = p['world_frame'], p['body_frame']
        self.use_live(p)
        self.counts = dict(cmd_vel=0, sent=0, refused=0, malformed=0, vision=0)
        self.input_warnings = ThrottledWarnings(self, 2.0)      # per kind of bad message
        self.signing_warnings = ThrottledWarnings(self, 10.0)   # per signing problem
        self.wrong_type_seen: dict[bytes, int] = {}   # publisher GID -> periods seen
        self.wrong_type_warned: set[bytes] = set()

        self.cmd_sub = self.create_subscription(TwistStamped, 'cmd_vel', self.on_cmd_vel,
                                                COMMAND_QOS)
        if p['vision_pose_topic']:
            kind, callback = VISION_TYPES[p['vision_pose_type']], self.on_vision_pose
            if kind is not PoseStamped:
                callback = self.on_vision_pose_cov
            try:
                self.create_subscription(kind, p['vision_pose_topic'], callback, NEWEST_QOS)
            except NameValidationException as err:
                raise ParameterError(f'vision_pose_topic: {err}'.splitlines()[0]) from None
        self.odom_pub = self.create_publisher(Odometry, 'autopilot/odom', 10)
        self.diag = Diagnostics(self, hardware_id=p['connection'])
        self.create_timer(1.0 / p['odom_rate'], self.publish_odom)
        self.create_timer(p['diagnostics_period'], self.publish_diagnostics)

        self.log_bridge = log_bridge.forward('uav_vs.autopilot', self.get_logger())
        self.session = Session(config).start()
        flight = MutuallyExclusiveCallbackGroup()
        self.create_service(SetBool, 'arm', self.on_arm, callback_group=flight)
        for name, call in (('takeoff', lambda: self.session.takeoff(self.takeoff_height)),
                           ('land', self.session.land), ('set_guided', self.session.set_guided),
                           ('install_signing_key', self.session.install_signing_key)):
            self.create_service(Trigger, name, self.service(name, call), callback_group=flight)
        LiveParams(self, PARAMS, p, self.reconfigure)
        self.get_logger().info(f"relaying to {p['connection']} (arming "
                               f"{'allowed' if p['allow_arming'] else 'disabled'}, signing "
                               f"{'on' if p['signing_key_file'] else 'off'})")

    def use_live(self, p: dict) -> None:
        """The node's own live settings."""
        self.takeoff_height = p['takeoff_height']
        self.vision_std = dict(pos_std=p['vision.position_std'], angle_std=p['vision.angle_std'])

    def reconfigure(self, p: dict, changed: set[str]) -> Callable[[], None]:
        """Checked parameters set at run time -> what makes them take effect."""
        settings = live_settings(p)

        def apply() -> None:
            self.session.reconfigure(**settings)
            self.use_live(p)
        return apply

    # ---------------------------------------------------------------- topics
    def on_cmd_vel(self, msg: TwistStamped) -> None:
        self.counts['cmd_vel'] += 1
        frame = msg.header.frame_id
        if frame not in (self.world, self.body):
            return self.malformed('cmd_vel frame', f'cmd_vel: frame_id {frame!r} is neither '
                                  f'{self.world!r} nor {self.body!r}')
        v = msg.twist.linear
        try:
            sent = self.session.send_velocity((v.x, v.y, v.z), msg.twist.angular.z,
                                              body=frame == self.body)
        except ValueError as err:
            return self.malformed('cmd_vel value', f'cmd_vel: {err}')
        self.counts['sent' if sent else 'refused'] += 1

    def on_vision_pose(self, msg: PoseStamped) -> None:
        if msg.header.frame_id != self.world:
            return self.malformed('vision frame', f'vision pose: frame_id '
                                  f'{msg.header.frame_id!r}, expected {self.world!r}')
        stamp = stamp_to_ns(msg.header.stamp) * 1e-9
        try:
            position, orientation = msg_to_pose(msg)     # MessageError (a ValueError): no rotation
            if self.session.send_vision_pose(position, orientation, stamp, **self.vision_std):
                self.counts['vision'] += 1
        except ValueError as err:
            self.malformed('vision value', f'vision pose: {err}')

    def on_vision_pose_cov(self, msg: PoseWithCovarianceStamped | Odometry) -> None:
        try:
            position, orientation, covariance = msg_to_pose_cov_in(msg, self.world)
            if self.session.send_vision_pose(position, orientation,
                                             stamp_to_ns(msg.header.stamp) * 1e-9, covariance):
                self.counts['vision'] += 1
        except ValueError as err:        # MessageError too: frame, rotation, covariance
            self.malformed('vision value', f'vision pose: {err}')

    def malformed(self, kind: str, why: str) -> None:
        """Count a bad message; log it, at most every 2 s per kind (all are counted)."""
        self.counts['malformed'] += 1
        self.input_warnings.warn(kind, f'{why}; skipped')

    def wrong_type_publishers(self) -> list[tuple[str, str]]:
        """(node, type) of each publisher on cmd_vel whose type is not TwistStamped: its
        messages never reach the relay. Each is warned about once, when its node's name
        is known (or after UNNAMED_PERIODS without one)."""
        topic = self.cmd_sub.topic_name
        found, before = set(), self.wrong_type_seen
        self.wrong_type_seen = {}   # the publishers gone are forgotten
        for info in self.get_publishers_info_by_topic(topic):
            if info.topic_type == CMD_VEL_TYPE:
                continue
            gid = bytes(info.endpoint_gid)
            seen = self.wrong_type_seen[gid] = before.get(gid, 0) + 1
            named = info.node_name != UNKNOWN_NODE
            node = _node_name(info.node_namespace, info.node_name) if named else 'an unnamed node'
            found.add((node, info.topic_type))
            if gid not in self.wrong_type_warned and (named or seen >= UNNAMED_PERIODS):
                self.wrong_type_warned.add(gid)
                self.get_logger().warn(f'{topic}: {node} publishes {info.topic_type}, the relay '
                                       f'subscribes {CMD_VEL_TYPE}: its commands are ignored')
        self.wrong_type_warned &= set(self.wrong_type_seen)
        return sorted(found)

    def publish_odom(self) -> None:
        tel = self.session.telemetry()
        if tel.position is None or tel.orientation is None:
            return
        age = Duration(nanoseconds=int((time.monotonic() - tel.stamp) * 1e9))
        header = Header(stamp=(self.get_clock().now() - age).to_msg(), frame_id=self.world)
        zero = (0.0, 0.0, 0.0)
        self.odom_pub.publish(odometry_to_msg(
            tel.position, tel.orientation, zero if tel.velocity is None else tel.velocity,
            zero if tel.angular_velocity is None else tel.angular_velocity, header, self.body,
            tel.pose_covariance, tel.twist_covariance))

    def publish_diagnostics(self) -> None:
        s = self.session.status()
        wrong = '; '.join(f'{node} ({kind})' for node, kind in self.wrong_type_publishers())
        if s.link is not LinkState.CONNECTED:
            # frames dropped for their signature: no vehicle will be heard until that is fixed
            level = ERROR if s.link is LinkState.LOST or s.signing_problem else WARN
            message = f'link {s.link.value}' + (f': {s.link_reason}' if s.link_reason else '')
        else:
            level = WARN if s.command is CommandState.HOVER or s.signing_problem else OK
            armed = 'armed' if s.armed else 'disarmed'
            message = f"{s.mode or '?'}, {armed}, command {s.command.value}"
        if wrong:
            level = max(level, WARN)
            message = f'{message}; cmd_vel publishers of another type: {wrong}'
        if s.signing_problem:
            message = f'{message}; {s.signing_problem}'
            self.signing_warnings.warn(s.signing_problem, message)
        self.diag.publish(level, message, {
            'link': s.link.value, 'link_reason': s.link_reason, 'autopilot': s.autopilot,
            'vehicle': s.vehicle_type, 'system_id': s.system_id, 'mode': s.mode, 'armed': s.armed,
            'command': s.command.value,
            'prearm_ok': s.prearm_ok, 'prearm_reasons': '; '.join(s.prearm_reasons),
            'battery_voltage': s.battery_voltage,
            'heartbeat_age': 'none' if s.heartbeat_age is None else f'{s.heartbeat_age:.2f}',
            'reconnects': s.reconnects, 'signing': s.signing, 'vehicle_signs': s.vehicle_signs,
            'rejected_unsigned': s.rejected_unsigned,
            'rejected_bad_signature': s.rejected_bad_signature,
            'rejected_old_timestamp': s.rejected_old_timestamp, **self.counts,
            'held': s.held, 'coalesced': s.coalesced, 'cmd_vel_wrong_type': wrong,
            'statustext': s.statustext[-1] if s.statustext else '',
            'gps_fix': '' if s.gps_fix is None else s.gps_fix,
            'ekf_origin': {None: '', True: 'set', False: 'waiting'}[s.ekf_origin_set],
            **ekf_values(s.ekf)})

    # ---------------------------------------------------------------- services
    async def on_arm(self, request: SetBool.Request,
                     response: SetBool.Response) -> SetBool.Response:
        if request.data:
            return await self.off_executor('arm', self.session.arm, response)
        return await self.off_executor('disarm', self.session.disarm, response)

    def service(self, name: str, call: Callable[[], None]):
        """A Trigger callback running `call` off the executor thread."""
        async def callback(request: Trigger.Request, response: Trigger.Response):
            return await self.off_executor(name, call, response)
        return callback

    async def off_executor(self, name: str, call: Callable[[], None],
                           response: SetBool.Response | Trigger.Response):
        """trigger() on a worker thread, awaited: the executor spins on meanwhile."""
        done, executor = Future(), self.executor

        def work() -> None:
            try:
                done.set_result(self.trigger(name, call, response))
            except Exception as err:   # a bug, not a refusal: raised in the executor
                done.set_exception(err)
            executor.wake()   # rclpy < 7.1.9 resumes an awaiting callback only when woken
        threading.Thread(target=work, name=f'{name} service', daemon=True).start()
        return await done

    def trigger(self, name: str, call: Callable[[], None],
                response: SetBool.Response | Trigger.Response):
        """Run a blocking session call; the autopilot's refusal goes into response.message."""
        try:
            call()
        except (AutopilotError, ValueError) as err:
            response.success, response.message = False, f'{name}: {err}'
            self.get_logger().error(response.message)
            return response
        s = self.session.status()
        response.success = True
        response.message = f"{name}: done ({s.mode}, {'armed' if s.armed else 'disarmed'})"
        self.get_logger().info(response.message)
        return response

    def destroy_node(self) -> None:
        if self.session.status().command is CommandState.ACTIVE:
            self.session.send_velocity((0.0, 0.0, 0.0))  # stop now, not after GUID_TIMEOUT
        self.session.close()
        log_bridge.stop_forwarding('uav_vs.autopilot', self.log_bridge)
        super().destroy_node()


def _node_name(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def main(args: list[str] | None = None) -> None:
    run(MavlinkRelayNode, 'mavlink_relay_node', args, executor='single')   # see node_main


if __name__ == '__main__':
    main()
