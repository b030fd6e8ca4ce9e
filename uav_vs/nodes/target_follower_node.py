"""target_follower_node: follow a moving target seen by the onboard camera (chapter section 5).

Subscribes `follow.target_topic` (geometry_msgs/PolygonStamped from target_tracker_node:
the template's corners TL, TR, BR, BL and its centre in the raw image) and
`follow.pose_topic` (geometry_msgs/PoseStamped, the vehicle's base_link in
`follow.world_frame`, e.g. ground/pose) and, unless it is empty, `follow.attitude_topic`
(nav_msgs/Odometry, e.g. the relay's autopilot/odom), whose roll and pitch replace the
pose's (a level-only vision pose does not see the tilt that moves the camera). Each
target polygon is placed on the ground plane z = 0 through the onboard camera
(`camera.*`, `camera_to_base_link.*` of config/onboard.yaml) from the vehicle pose and
attitude stamped nearest its image (uav_vs.control.follow); publishes
`setpoint` (PoseStamped in `follow.world_frame`, the image's stamp: the target's
position `follow.lead` s ahead by its estimated velocity, `follow.height` above the
ground, yaw `follow.yaw`) for fuzzy_controller_node, `target/pose` (PoseStamped: the
target's centre on the ground and its heading, the direction of the template's top
edge) and /diagnostics. An image waits for the vehicle pose and attitude at its stamp
(up to `follow.max_wait` s of newer images), which are interpolated between the two
either side of it. While the target is lost or cannot be placed nothing is published:
the controller holds the last setpoint, and why is the diagnostics' message and, every
5 s at most, a warning in the log. Every parameter is read-only.
"""
import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PolygonStamped, PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header

from uav_vs.autopilot.frames import euler_to_quat
from uav_vs.control.follow import FollowConfig, FollowStep, TargetFollower
from uav_vs.nodes.homography_pose_node import ONBOARD_PARAMS
from uav_vs.ros.convert import (MessageError, check_frame, msg_to_odometry, msg_to_pose_in,
                                ns_to_stamp, polygon_to_array, pose_to_msg, stamp_to_ns)
from uav_vs.ros.node_main import OK, WARN, Diagnostics, ThrottledWarnings, run
from uav_vs.ros.params import Param, T, declare
from uav_vs.vision.onboard_config import load_onboard_config

_F = FollowConfig()
PARAMS = [
    Param('follow.target_topic', T.STRING, 'onboard/target', 'tracked target polygon'),
    Param('follow.pose_topic', T.STRING, 'ground/pose',
          'vehicle pose: ground/pose (trinocular) or onboard/pose (homography)'),
    Param('follow.attitude_topic', T.STRING, 'autopilot/odom',
          "vehicle attitude (nav_msgs/Odometry), whose roll and pitch replace the pose's; "
          "'': the pose's own"),
    Param('follow.world_frame', T.STRING, 'world', 'ENU frame of the pose and the setpoint'),
    Param('follow.height', T.DOUBLE, _F.height, 'setpoint height above the ground, m',
          0.2, 100.0),
    Param('follow.yaw', T.DOUBLE, _F.yaw, 'setpoint yaw, rad (ENU, 0 = east)',
          -2 * math.pi, 2 * math.pi),
    Param('follow.lead', T.DOUBLE, _F.lead, 'setpoint ahead of the target by its estimated '
          'velocity times this, s', 0.0, 10.0),
    Param('follow.max_pose_gap', T.DOUBLE, _F.max_pose_gap, 'image and the nearest vehicle '
          'pose (or attitude) stamped further apart, none either side to interpolate '
          'between: target not placed, s', 0.001, 5.0),
    Param('follow.max_pose_interval', T.DOUBLE, _F.max_pose_interval, 'poses (or '
          'attitudes) either side of an image at most this far apart are interpolated, s',
          0.001, 5.0),
    Param('follow.max_wait', T.DOUBLE, _F.max_wait, 'an image waits for a vehicle pose and '
          'attitude stamped at or after it until an image this much newer arrives, s',
          0.001, 5.0),
    Param('follow.velocity_gain', T.DOUBLE, _F.velocity_gain, 'beta of the alpha-beta filter '
          'of the target position (smaller: smoother, slower velocity)', 0.001, 1.0),
    Param('follow.max_speed', T.DOUBLE, _F.max_speed, 'a faster target estimate restarts the '
          'filter, m/s', 0.01, 50.0),
    Param('follow.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.05, 60.0),
]


class TargetFollowerNode(Node):
    def __init__(self) -> None:
        super().__init__('target_follower_node')
        onboard = load_onboard_config(declare(self, [s for s in ONBOARD_PARAMS
                                                     if s.name.startswith('camera')]))
        p = declare(self, PARAMS)
        self.world = p['follow.world_frame']
        self.follower = TargetFollower(onboard.camera, onboard.camera_to_body, FollowConfig(
            p['follow.height'], p['follow.yaw'], p['follow.lead'], p['follow.max_pose_gap'],
            p['follow.velocity_gain'], p['follow.max_speed'], p['follow.max_pose_interval'],
            p['follow.max_wait']), attitude_source=bool(p['follow.attitude_topic']))
        self.setpoint_pub = self.create_publisher(PoseStamped, 'setpoint', 10)
        self.target_pub = self.create_publisher(PoseStamped, 'target/pose', 10)
        self.create_subscription(PoseStamped, p['follow.pose_topic'], self.on_pose, 10)
        self.create_subscription(PolygonStamped, p['follow.target_topic'], self.on_target, 10)
        inputs = [p['follow.target_topic'], p['follow.pose_topic']]
        if p['follow.attitude_topic']:
            self.create_subscription(Odometry, p['follow.attitude_topic'], self.on_attitude, 10)
            inputs.append(p['follow.attitude_topic'])
        self.counts = dict(poses=0, attitudes=0, targets=0, setpoints=0, not_placed=0,
                           malformed=0)
        self.reason = ''
        self.stamps: dict[float, Time] = {}     # of the waiting images, by their seconds
        self.warnings = ThrottledWarnings(self)
        self.diag = Diagnostics(self)
        self.create_timer(p['follow.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(
            f"{', '.join(self.resolve_topic_name(t) for t in inputs)} -> "
            f"{self.resolve_topic_name('setpoint')} at {p['follow.height']:g} m")

    def on_pose(self, msg: PoseStamped) -> None:
        try:
            position, q = msg_to_pose_in(msg, self.world)
        except MessageError as err:
            self._malformed(f'pose: {err}')
            return
        self.counts['poses'] += 1
        self.publish(self.follower.on_pose(stamp_to_ns(msg.header.stamp) * 1e-9,
                                           Rotation.from_quat(q).as_matrix(), position))

    def on_attitude(self, msg: Odometry) -> None:
        try:
            check_frame(msg.header, self.world)
            _, q, _, _ = msg_to_odometry(msg)
        except MessageError as err:
            self._malformed(f'attitude: {err}')
            return
        self.counts['attitudes'] += 1
        self.publish(self.follower.on_attitude(stamp_to_ns(msg.header.stamp) * 1e-9,
                                               Rotation.from_quat(q).as_matrix()))

    def on_target(self, msg: PolygonStamped) -> None:
        points = polygon_to_array(msg)
        if points.shape[0] != 5 or not np.isfinite(points).all():
            self._malformed(f'target: {points.shape[0]} points, expected 5 finite ones')
            return
        self.counts['targets'] += 1
        stamp = stamp_to_ns(msg.header.stamp) * 1e-9
        self.stamps[stamp] = msg.header.stamp
        self.publish(self.follower.on_target(stamp, points[:, :2]))

    def publish(self, steps: list[FollowStep]) -> None:
        """The setpoint and target of each placed image; why not, for the others."""
        for step in steps:
            stamp = self.stamps.pop(step.stamp, None) or ns_to_stamp(round(step.stamp * 1e9))
            self.reason = step.reason
            if step.setpoint is None:
                self.counts['not_placed'] += 1
                self.warnings.warn('not placed', f'target not placed: {step.reason}')
                continue
            header = Header(stamp=stamp, frame_id=self.world)
            x, y, z, yaw = step.setpoint
            self.setpoint_pub.publish(pose_to_msg(np.array([x, y, z]),
                                                  euler_to_quat(0, 0, yaw), header))
            gx, gy = step.target.position
            self.target_pub.publish(pose_to_msg(np.array([gx, gy, 0.0]),
                                                euler_to_quat(0, 0, step.target.heading),
                                                header))
            self.counts['setpoints'] += 1

    def publish_diagnostics(self) -> None:
        waiting = self.follower.waiting_for()
        if self.reason:
            level, message = WARN, f'target not placed: {self.reason}'
        elif self.counts['setpoints'] == 0:
            level, message = WARN, waiting or 'no target yet'
        else:
            level, message = OK, 'following'
        v = self.follower.velocity
        self.diag.publish(level, message, {**self.counts, 'waiting': len(self.follower.waiting),
                                           'waiting_for': waiting, 'target_velocity':
                                           f'{v[0]:.3f} {v[1]:.3f}'})

    def _malformed(self, text: str) -> None:
        self.counts['malformed'] += 1
        self.warnings.skipped(text)


def main(args: list[str] | None = None) -> None:
    run(TargetFollowerNode, 'target_follower_node', args)


if __name__ == '__main__':
    main()
