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
disabled (std_srvs/SetBool `~/enable`; `controller.enabled` is the start state), without
a setpoint, or when the last measurement arrived more than `controller.timeout` ago.
Limits (`controller.max_*`) apply to every command.
"""
import math
import time

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PolygonStamped, PoseStamped, TwistStamped
from rclpy.node import Node
from std_msgs.msg import Header
from std_srvs.srv import SetBool

from uav_vs.control.controllers import PoseController, TrackingController, config_from_params
from uav_vs.control.servo import Limits, ServoLoop
from uav_vs.ros.convert import msg_to_pose, polygon_to_array, stamp_to_ns, twist_to_msg, yaw_of
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, ThrottledWarnings, run
from uav_vs.ros.params import Param, T, declare

PARAMS = [
    Param('controller.mode', T.STRING, 'pose', 'pose (x, y, z, yaw) or tracking (heading)',
          choices=('pose', 'tracking')),
    Param('controller.pose_topic', T.STRING, 'ground/pose',
          'vehicle pose: ground/pose (trinocular) or onboard/pose (homography)'),
    Param('controller.target_topic', T.STRING, 'onboard/target', 'tracked target (tracking mode)'),
    Param('controller.image_center_x', T.DOUBLE, 319.5,
          'image column the target is steered to (tracking mode), px', 0.0, 100000.0),
    Param('controller.rate', T.DOUBLE, 20.0,
          'least cmd_vel rate (a command also follows every measurement), Hz', 1.0, 500.0),
    Param('controller.timeout', T.DOUBLE, 0.25,
          'a measurement older than this gives zero command, s', 0.01, 10.0),
    Param('controller.command_frame', T.STRING, 'world', 'cmd_vel frame: world (ENU) or body (FLU)',
          choices=('world', 'body')),
    Param('controller.world_frame', T.STRING, 'world', 'ENU frame of pose, setpoint and commands'),
    Param('controller.body_frame', T.STRING, 'base_link', 'FLU body frame of body commands'),
    Param('controller.enabled', T.BOOL, False, 'start enabled (else wait for ~/enable)'),
    Param('controller.max_horizontal_speed', T.DOUBLE, 1.0, 'limit on |(vx, vy)|, m/s', 0.0, 20.0),
    Param('controller.max_vertical_speed', T.DOUBLE, 0.5, 'limit on |vz|, m/s', 0.0, 10.0),
    Param('controller.max_yaw_rate', T.DOUBLE, 0.8, 'limit on |yaw rate|, rad/s', 0.0, 6.0),
    Param('controller.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.05, 60.0),
]


class FuzzyControllerNode(Node):
    def __init__(self) -> None:
        super().__init__('fuzzy_controller_node', allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True)
        p = declare(self, PARAMS)
        known = {spec.name for spec in PARAMS}
        for name in self.get_parameters_by_prefix('controller'):
            if f'controller.{name}' not in known:
                raise ValueError(f'controller.{name}: unknown parameter')
        fuzzy = config_from_params({n: v.value for n, v in
                                    self.get_parameters_by_prefix('fuzzy').items()}, prefix='')
        tracking = p['controller.mode'] == 'tracking'
        controller = (TrackingController if tracking else PoseController).from_config(fuzzy)
        limits = Limits(p['controller.max_horizontal_speed'], p['controller.max_vertical_speed'],
                        p['controller.max_yaw_rate'])
        body = p['controller.command_frame'] == 'body'
        self.loop = ServoLoop(controller, limits, p['controller.timeout'], body,
                              p['controller.enabled'])
        self.world = p['controller.world_frame']
        self.cmd_frame = p['controller.body_frame'] if body else self.world
        self.center_x = p['controller.image_center_x']
        self.counts = dict(commands=0, active=0, measurements=0, malformed=0)
        self.reason = 'no cycle yet'
        self.period = 1.0 / p['controller.rate']
        self.measured: Time | None = None     # stamp of the last measurement taken
        self.measured_at = -math.inf           # when it arrived (the floor counts from it)
        self.pub = self.create_publisher(TwistStamped, 'cmd_vel', 10)
        if tracking:
            self.create_subscription(PolygonStamped, p['controller.target_topic'],
                                     self.on_target, 10)
        else:
            self.create_subscription(PoseStamped, p['controller.pose_topic'], self.on_pose, 10)
            self.create_subscription(PoseStamped, 'setpoint', self.on_setpoint, 10)
        self.create_service(SetBool, '~/enable', self.on_enable)
        self.warnings = ThrottledWarnings(self)
        self.diag = Diagnostics(self)
        self.create_timer(self.period, self.on_cycle)
        self.create_timer(p['controller.diagnostics_period'], self.publish_diagnostics)

    def on_pose(self, msg: PoseStamped) -> None:
        if not self._in_world(msg, 'pose'):
            return
        position, q = msg_to_pose(msg)
        if self.loop.on_pose(time.monotonic(), stamp_to_ns(msg.header.stamp) * 1e-9,
                             position, yaw_of(q)):
            self.on_measurement(msg.header.stamp)
        else:
            self._malformed('pose: non-finite position or orientation')

    def on_setpoint(self, msg: PoseStamped) -> None:
        if not self._in_world(msg, 'setpoint'):
            return
        position, q = msg_to_pose(msg)
        yaw = yaw_of(q)
        if not (all(map(math.isfinite, position)) and math.isfinite(yaw)):
            self._malformed('setpoint: non-finite position or orientation')
            return
        self.loop.set_setpoint(position, yaw)

    def on_target(self, msg: PolygonStamped) -> None:
        points = polygon_to_array(msg)
        if len(points) == 0:
            self._malformed('target: empty polygon')
            return
        if self.loop.on_target(time.monotonic(), stamp_to_ns(msg.header.stamp) * 1e-9,
                               self.center_x - points[-1, 0]):
            self.on_measurement(msg.header.stamp)
        else:
            self._malformed('target: non-finite centre')

    def on_enable(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        self.loop.enable(request.data)
        response.success = True
        response.message = 'enabled' if request.data else 'disabled'
        self.get_logger().info(f'controller {response.message}')
        return response

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
        cmd, self.reason = self.loop.command(time.monotonic())
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
            level, message = (ERROR if 'stale' in self.reason else WARN), \
                f'{self.reason}: zero command'
        self.diag.publish(level, message, {**self.counts, 'enabled': self.loop.enabled,
                                           'frame': self.cmd_frame})

    def _in_world(self, msg: PoseStamped, what: str) -> bool:
        if msg.header.frame_id == self.world:
            return True
        self._malformed(f'{what}: frame {msg.header.frame_id!r}, expected {self.world!r}')
        return False

    def _malformed(self, text: str) -> None:
        self.counts['malformed'] += 1
        self.warnings.warn(' '.join(text.split()[:2]), f'{text}; skipped')   # kind: first words


def main(args: list[str] | None = None) -> None:
    run(FuzzyControllerNode, 'fuzzy_controller_node', args)


if __name__ == '__main__':
    main()
