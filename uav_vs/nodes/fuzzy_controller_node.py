"""fuzzy_controller_node: pose or image error to velocity commands (chapter section 6).

Pose mode (`controller.mode: pose`): subscribes the vehicle pose
(`controller.pose_topic`: `ground/pose` from the trinocular station or `onboard/pose`
from the homography node) and `setpoint` (both geometry_msgs/PoseStamped in
`controller.world_frame`); one fuzzy PD axis each for x, y, z and yaw.
Tracking mode (`controller.mode: tracking`): subscribes `onboard/target`
(PolygonStamped from target_tracker_node, the centre is the last point) and turns the
target's column offset from `controller.image_center_x` into a yaw rate.

Publishes `cmd_vel` (geometry_msgs/TwistStamped) as soon as each measurement has been
evaluated, stamped with that measurement's stamp (so image-to-command latency can be
measured), and from the `controller.rate` timer whenever no measurement has produced a
command for a period (the last command again, or zero, stamped now when zero); the
header.frame_id is `controller.world_frame` (ENU) or `controller.body_frame` (FLU) per
`controller.command_frame`. Also /diagnostics. The command is zero while the node is
disabled (std_srvs/SetBool `controller/enable`, relative to the namespace like the relay's
services; `controller.enabled` is the start state), without
a setpoint, when the last measurement arrived more than `controller.timeout` ago, when
its stamp is more than `controller.max_stamp_age` behind the node's clock (ROS time:
/clock under use_sim_time), or when that clock has not moved for `controller.timeout`.
A measurement stamped 0, too old, or more than `controller.max_future_stamp` ahead of
the clock is counted and dropped. The timers run on the steady clock, so zero commands
follow even when /clock stops. Limits (`controller.max_*`) apply to every command.

Set at run time, the limits and timing take effect from the held command on, and a
changed `fuzzy.*` key rebuilds the controller, which replaces the running one only if
it is valid (else the change is refused with the reason); the mode, topics, frames,
start state and timer periods are read-only.
"""
import math
import time
from typing import Callable

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PolygonStamped, PoseStamped, TwistStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import SetBool

from uav_vs.control.controllers import PoseController, TrackingController, config_from_params
from uav_vs.control.servo import Limits, Now, ServoLoop, Timing, Verdict
from uav_vs.ros.convert import (MessageError, check_frame, msg_to_pose, polygon_to_array,
                                stamp_to_ns, twist_to_msg, yaw_of)
from uav_vs.ros.fuzzy_params import fuzzy_params
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, ThrottledWarnings, run
from uav_vs.ros.params import LiveParams, Param, T, declare

# Measurements (pose, target): best effort. A late one is worth less than none: across a
# lossy radio link a reliable one lost is sent again a heartbeat later, hundreds of ms
# old. Reliable publishers (the vision nodes, bags) match it.
MEASUREMENT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)

PARAMS = [
    Param('controller.mode', T.STRING, 'pose', 'pose (x, y, z, yaw) or tracking (heading)',
          choices=('pose', 'tracking')),
    Param('controller.pose_topic', T.STRING, 'ground/pose',
          'vehicle pose: ground/pose (trinocular) or onboard/pose (homography)'),
    Param('controller.target_topic', T.STRING, 'onboard/target', 'tracked target (tracking mode)'),
    Param('controller.image_center_x', T.DOUBLE, 319.5,
          'image column the target is steered to (tracking mode), px', 0.0, 100000.0, live=True),
    Param('controller.rate', T.DOUBLE, 20.0,
          'least cmd_vel rate (a command also follows every measurement), Hz (read-only: the '
          'timer is made at start-up)', 1.0, 500.0),
    Param('controller.timeout', T.DOUBLE, 0.25,
          'a measurement older than this (since it arrived), or the clock standing still '
          'this long, gives zero command, s', 0.01, 10.0, live=True),
    Param('controller.max_stamp_age', T.DOUBLE, 0.5,
          "a measurement stamped further behind the node's clock is dropped and gives zero "
          'command, s (0: stamps not aged, for replayed bags)', 0.0, 60.0, live=True),
    Param('controller.max_future_stamp', T.DOUBLE, 0.1,
          "a measurement stamped further ahead of the node's clock is dropped, s", 0.0, 10.0,
          live=True),
    Param('controller.command_frame', T.STRING, 'world', 'cmd_vel frame: world (ENU) or body (FLU)',
          choices=('world', 'body')),
    Param('controller.world_frame', T.STRING, 'world', 'ENU frame of pose, setpoint and commands'),
    Param('controller.body_frame', T.STRING, 'base_link', 'FLU body frame of body commands'),
    Param('controller.enabled', T.BOOL, False, 'start enabled (else wait for controller/enable; '
          'read-only: controller/enable switches it at run time)'),
    Param('controller.max_horizontal_speed', T.DOUBLE, 1.0, 'limit on |(vx, vy)|, m/s', 0.0, 20.0,
          live=True),
    Param('controller.max_vertical_speed', T.DOUBLE, 0.5, 'limit on |vz|, m/s', 0.0, 10.0,
          live=True),
    Param('controller.max_yaw_rate', T.DOUBLE, 0.8, 'limit on |yaw rate|, rad/s', 0.0, 6.0,
          live=True),
    Param('controller.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s (read-only: '
          'the timer is made at start-up)', 0.05, 60.0),
]


def limits_and_timing(p: dict) -> tuple[Limits, Timing]:
    """The command limits and the measurement timing of the `controller.*` parameters."""
    return (Limits(p['controller.max_horizontal_speed'], p['controller.max_vertical_speed'],
                   p['controller.max_yaw_rate']),
            Timing(p['controller.timeout'], p['controller.max_stamp_age'],
                   p['controller.max_future_stamp']))


# Zero-command reasons that are a WARN (input still to come, or outside the rules' ranges);
# the others (stale input, stamps the clock cannot believe, a stopped clock) are an ERROR.
WAITING = ('no cycle yet', 'no setpoint', 'no measurement yet',
           'controller input out of its domain')


class FuzzyControllerNode(Node):
    def __init__(self) -> None:
        # Undeclared names are allowed so that LiveParams, not rclpy, refuses an unknown one
        # at run time, naming it.
        super().__init__('fuzzy_controller_node', allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True)
        p = declare(self, PARAMS)
        known = {spec.name for spec in PARAMS}
        for name in self.get_parameters_by_prefix('controller'):
            if f'controller.{name}' not in known:
                raise ValueError(f'controller.{name}: unknown parameter')
        rules = fuzzy_params(f'fuzzy.{n}' for n in sorted(self.get_parameters_by_prefix('fuzzy')))
        p.update(declare(self, rules))
        tracking = p['controller.mode'] == 'tracking'
        self.controller_kind = TrackingController if tracking else PoseController
        body = p['controller.command_frame'] == 'body'
        self.loop = ServoLoop(self.controller_from(p), *limits_and_timing(p), body,
                              p['controller.enabled'])
        self.world = p['controller.world_frame']
        self.cmd_frame = p['controller.body_frame'] if body else self.world
        self.center_x = p['controller.image_center_x']
        self.counts = dict(commands=0, active=0, measurements=0, malformed=0, old_stamps=0,
                           future_stamps=0)
        self.reason = 'no cycle yet'
        self.period = 1.0 / p['controller.rate']
        self.measured: Time | None = None     # stamp of the last measurement taken
        self.measured_at = -math.inf           # when it arrived (the floor counts from it)
        self.pub = self.create_publisher(TwistStamped, 'cmd_vel', 10)
        if tracking:
            self.create_subscription(PolygonStamped, p['controller.target_topic'],
                                     self.on_target, MEASUREMENT_QOS)
        else:
            self.create_subscription(PoseStamped, p['controller.pose_topic'], self.on_pose,
                                     MEASUREMENT_QOS)
            self.create_subscription(PoseStamped, 'setpoint', self.on_setpoint, 10)
        self.create_service(SetBool, 'controller/enable', self.on_enable)
        self.warnings = ThrottledWarnings(self)
        self.diag = Diagnostics(self)
        steady = Clock(clock_type=ClockType.STEADY_TIME)    # runs on when /clock stops
        self.create_timer(self.period, self.on_cycle, clock=steady)
        self.create_timer(p['controller.diagnostics_period'], self.publish_diagnostics,
                          clock=steady)
        LiveParams(self, [*PARAMS, *rules], p, self.reconfigure)
        inputs = ([p['controller.target_topic']] if tracking
                  else [p['controller.pose_topic'], 'setpoint'])
        state = 'enabled' if p['controller.enabled'] else 'disabled until controller/enable'
        self.get_logger().info(
            f"{p['controller.mode']} mode: "
            f"{' and '.join(self.resolve_topic_name(t) for t in inputs)} -> "
            f"{self.resolve_topic_name('cmd_vel')} ({self.cmd_frame}, at least "
            f"{p['controller.rate']:g} Hz), {state}")

    def controller_from(self, p: dict) -> PoseController | TrackingController:
        """The controller of the `fuzzy.*` parameters; ValueError says what is wrong."""
        rules = {n.removeprefix('fuzzy.'): v for n, v in p.items() if n.startswith('fuzzy.')}
        try:
            return self.controller_kind.from_config(config_from_params(rules, prefix=''))
        except (TypeError, AttributeError, KeyError) as err:   # a value of the wrong shape
            raise ValueError(f'fuzzy: malformed controller configuration ({err})') from None

    def reconfigure(self, p: dict, changed: set[str]) -> Callable[[], None]:
        """Checked parameters set at run time -> what makes them take effect; new rules or
        gains rebuild the controller, which replaces the old one only if it is valid."""
        limits, timing = limits_and_timing(p)
        controller = (self.controller_from(p) if any(n.startswith('fuzzy.') for n in changed)
                      else None)

        def apply() -> None:
            self.loop.set_limits(limits)
            self.loop.set_timing(timing)
            if controller is not None:
                self.loop.set_controller(controller)
            self.center_x = p['controller.image_center_x']
        return apply

    def now(self) -> Now:
        """The steady time and the node's (ROS) time."""
        return Now(time.monotonic(), self.get_clock().now().nanoseconds * 1e-9)

    def on_pose(self, msg: PoseStamped) -> None:
        pose = self._pose(msg, 'pose')
        if pose is None:
            return
        verdict = self.loop.on_pose(self.now(), stamp_to_ns(msg.header.stamp) * 1e-9, *pose)
        self._judged(verdict, msg.header.stamp, 'pose: non-finite position')

    def on_setpoint(self, msg: PoseStamped) -> None:
        pose = self._pose(msg, 'setpoint')
        if pose is None:
            return
        if not all(map(math.isfinite, pose[0])):
            self._malformed('setpoint: non-finite position')
            return
        self.loop.set_setpoint(*pose)

    def on_target(self, msg: PolygonStamped) -> None:
        points = polygon_to_array(msg)
        if len(points) == 0:
            self._malformed('target: empty polygon')
            return
        verdict = self.loop.on_target(self.now(), stamp_to_ns(msg.header.stamp) * 1e-9,
                                      self.center_x - points[-1, 0])
        self._judged(verdict, msg.header.stamp, 'target: non-finite centre')

    def on_enable(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        self.loop.enable(request.data)
        response.success = True
        response.message = 'enabled' if request.data else 'disabled'
        self.get_logger().info(f'controller {response.message}')
        return response

    def _judged(self, verdict: Verdict, stamp: Time, non_finite: str) -> None:
        """Act on what the loop made of a measurement."""
        if verdict is Verdict.TAKEN:
            self.on_measurement(stamp)
        elif verdict is Verdict.NON_FINITE:
            self._malformed(non_finite)
        else:
            self.counts['future_stamps' if verdict is Verdict.FUTURE else 'old_stamps'] += 1
            self.warnings.warn(verdict.value, f'{self.loop.refused}; dropped')

    def on_measurement(self, stamp: Time) -> None:
        """The command computed from a new measurement, sent at once."""
        self.counts['measurements'] += 1
        self.measured, self.measured_at = stamp, time.monotonic()
        self.publish_command()

    def on_cycle(self) -> None:
        """The fixed-rate floor: a command every period even without measurements, which
        turns to zero once they are stale."""
        if time.monotonic() - self.measured_at >= self.period:
            self.publish_command()

    def publish_command(self) -> None:
        cmd, self.reason = self.loop.command(self.now())
        stamp = self.measured if not self.reason else self.get_clock().now().to_msg()
        header = Header(stamp=stamp, frame_id=self.cmd_frame)
        self.pub.publish(twist_to_msg(cmd[:3], [0.0, 0.0, cmd[3]], header))
        self.counts['commands'] += 1
        self.counts['active'] += not self.reason

    def publish_diagnostics(self) -> None:
        if not self.reason:
            level, message = OK, 'commanding'
        elif self.reason == 'disabled':
            level, message = OK, 'disabled: zero command'
        else:
            level, message = (WARN if self.reason in WAITING else ERROR), \
                f'{self.reason}: zero command'
        self.diag.publish(level, message, {**self.counts, 'enabled': self.loop.enabled,
                                           'frame': self.cmd_frame})

    def _pose(self, msg: PoseStamped, what: str) -> tuple[np.ndarray, float] | None:
        """(position, yaw) of a pose in the world frame with a rotation for orientation;
        None (counted as malformed) otherwise."""
        try:
            check_frame(msg.header, self.world)
            position, q = msg_to_pose(msg)
        except MessageError as err:
            self._malformed(f'{what}: {err}')
            return None
        return position, yaw_of(q)

    def _malformed(self, text: str) -> None:
        self.counts['malformed'] += 1
        self.warnings.skipped(text)


def main(args: list[str] | None = None) -> None:
    run(FuzzyControllerNode, 'fuzzy_controller_node', args)


if __name__ == '__main__':
    main()
