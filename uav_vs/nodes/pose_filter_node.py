"""pose_filter_node: one latency-compensated estimate from every pose source (uav_vs.control.
pose_filter; the chapter's Fig. 6 compares the vision poses with a Kalman-filtered state).

Subscribes each of `pose_filter.pose_topics` (geometry_msgs/PoseStamped in
`pose_filter.world_frame`: ground/pose, onboard/pose), each with its own standard
deviations (`pose_filter.position_sigmas`, `.yaw_sigmas`, one per topic); each of
`pose_filter.covariance_topics` (geometry_msgs/PoseWithCovarianceStamped, e.g.
trinocular_pose_node's ground/pose_cov) with the covariance it carries (its x, y, z and
rotation-about-z block; a covariance that is not finite, symmetric and positive
semi-definite with a positive diagonal makes the message malformed); and, unless it
is empty, `pose_filter.odometry_topic` (nav_msgs/Odometry, the relay's autopilot/odom:
its velocity in base_link and yaw rate, and its position and yaw, each with its
`pose_filter.odometry_*_sigma`). Every measurement is applied at its header stamp.

Publishes at `pose_filter.rate` Hz, stamped with the node's clock, the state predicted to
that time: `fused/odom` (nav_msgs/Odometry, pose in `world_frame`, twist in
`body_frame`, with the filter's covariances; roll and pitch, which it does not estimate,
carry a variance of 1e6) and `fused/pose` (PoseStamped, level, for fuzzy_controller_node:
`-p controller.pose_topic:=fused/pose`), and /diagnostics: per source the measurements
applied, refused by the gate, too old, the resets the filter started from it (none
applied for `pose_filter.reset_after` s), and the age of the newest. Nothing is published
before the first measurement or when the newest is more than `pose_filter.timeout` s
behind the clock: a consumer sees the estimate go stale, as it would a vision pose.
A malformed message (a frame other than `world_frame`, no rotation, non-finite numbers)
is counted, logged (throttled) and skipped. Every parameter is read-only.
"""
import math

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from std_msgs.msg import Header

from uav_vs.control.pose_filter import (FilterParams, PoseFilter, odometry_measurement,
                                        pose_measurement, rot_z)
from uav_vs.ros.convert import (MessageError, check_frame, msg_to_odometry, msg_to_pose_cov_in,
                                msg_to_pose_in, odometry_to_msg, pose_to_msg, stamp_to_ns,
                                yaw_of, yaw_quaternion)
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, ThrottledWarnings, run
from uav_vs.ros.params import ParameterError, Param, T, declare
from uav_vs.vision.pose_covariance import UNKNOWN

_F = FilterParams()
PARAMS = [
    Param('pose_filter.pose_topics', T.STRING_ARRAY, ['ground/pose', 'onboard/pose'],
          'vehicle poses (PoseStamped) to fuse'),
    Param('pose_filter.position_sigmas', T.DOUBLE_ARRAY, [0.03, 0.05],
          'standard deviation of each pose topic\'s position, m per axis', 1e-4, 100.0),
    Param('pose_filter.yaw_sigmas', T.DOUBLE_ARRAY, [0.03, 0.05],
          'standard deviation of each pose topic\'s yaw, rad', 1e-4, 10.0),
    Param('pose_filter.covariance_topics', T.STRING_ARRAY, [],
          'vehicle poses with their own covariance (PoseWithCovarianceStamped) to fuse'),
    Param('pose_filter.odometry_topic', T.STRING, 'autopilot/odom',
          "the autopilot's odometry (nav_msgs/Odometry, the relay's autopilot/odom); '': none"),
    Param('pose_filter.odometry_position_sigma', T.DOUBLE, 1000.0,
          "standard deviation of the odometry's position, m (large: its origin is the "
          "autopilot's own)", 1e-4, 1e6),
    Param('pose_filter.odometry_yaw_sigma', T.DOUBLE, 0.1,
          "standard deviation of the odometry's yaw, rad", 1e-4, 1e3),
    Param('pose_filter.odometry_velocity_sigma', T.DOUBLE, 0.1,
          "standard deviation of the odometry's base_link velocity, m/s", 1e-4, 100.0),
    Param('pose_filter.odometry_yaw_rate_sigma', T.DOUBLE, 0.05,
          "standard deviation of the odometry's yaw rate, rad/s", 1e-4, 100.0),
    Param('pose_filter.accel_sigma', T.DOUBLE, _F.accel_sigma,
          'white acceleration of the motion model, m/s^2 per axis', 1e-3, 100.0),
    Param('pose_filter.yaw_accel_sigma', T.DOUBLE, _F.yaw_accel_sigma,
          'white yaw acceleration of the motion model, rad/s^2', 1e-3, 100.0),
    Param('pose_filter.gate_probability', T.DOUBLE, _F.gate_probability,
          'an innovation beyond this chi-square quantile is refused', 0.5, 1.0 - 1e-12),
    Param('pose_filter.history', T.DOUBLE, _F.history,
          'a measurement up to this much older than the newest is applied in its place, s',
          0.0, 10.0),
    Param('pose_filter.reset_after', T.DOUBLE, _F.reset_after,
          'measurements refused this long, none applied: the filter starts again from the '
          'newest, s', 0.05, 60.0),
    Param('pose_filter.rate', T.DOUBLE, 50.0, 'publishing rate, Hz', 1.0, 1000.0),
    Param('pose_filter.timeout', T.DOUBLE, 0.5, 'nothing is published while the newest '
          "measurement is further behind the node's clock, s", 0.01, 60.0),
    Param('pose_filter.world_frame', T.STRING, 'world', 'ENU frame of poses and estimate'),
    Param('pose_filter.body_frame', T.STRING, 'base_link', 'FLU body frame of the twist'),
    Param('pose_filter.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.05, 60.0),
]


class PoseFilterNode(Node):
    def __init__(self) -> None:
        super().__init__('pose_filter_node')
        p = declare(self, PARAMS)
        topics = p['pose_filter.pose_topics']
        for key in ('pose_filter.position_sigmas', 'pose_filter.yaw_sigmas'):
            if len(p[key]) != len(topics):
                raise ParameterError(f'{key}: expected one per pose_filter.pose_topics '
                                     f'({len(topics)}), got {len(p[key])}')
        covariance_topics = p['pose_filter.covariance_topics']
        if not topics and not covariance_topics and not p['pose_filter.odometry_topic']:
            raise ParameterError('pose_filter.pose_topics: expected a topic (or one in '
                                 'covariance_topics, or an odometry_topic), got none')
        self.world, self.body = p['pose_filter.world_frame'], p['pose_filter.body_frame']
        self.timeout = p['pose_filter.timeout']
        self.filter = PoseFilter(FilterParams(
            p['pose_filter.accel_sigma'], p['pose_filter.yaw_accel_sigma'],
            p['pose_filter.gate_probability'], p['pose_filter.history'],
            reset_after=p['pose_filter.reset_after']))
        for topic, sigma, yaw_sigma in zip(topics, p['pose_filter.position_sigmas'],
                                           p['pose_filter.yaw_sigmas']):
            cov = np.diag([sigma ** 2] * 3 + [yaw_sigma ** 2])
            self.create_subscription(PoseStamped, topic,
                                     lambda msg, t=topic, c=cov: self.on_pose(msg, t, c), 10)
        for topic in covariance_topics:
            self.create_subscription(PoseWithCovarianceStamped, topic,
                                     lambda msg, t=topic: self.on_pose_cov(msg, t), 10)
        self.odometry = p['pose_filter.odometry_topic']
        if self.odometry:
            self.odometry_cov = np.diag(
                [p['pose_filter.odometry_position_sigma'] ** 2] * 3
                + [p['pose_filter.odometry_yaw_sigma'] ** 2]
                + [p['pose_filter.odometry_velocity_sigma'] ** 2] * 3
                + [p['pose_filter.odometry_yaw_rate_sigma'] ** 2])
            self.create_subscription(Odometry, self.odometry, self.on_odometry, 10)
        self.odom_pub = self.create_publisher(Odometry, 'fused/odom', 10)
        self.pose_pub = self.create_publisher(PoseStamped, 'fused/pose', 10)
        self.counts = dict(published=0, malformed=0, stale=0)
        self.warnings = ThrottledWarnings(self)
        self.diag = Diagnostics(self)
        self.create_timer(1.0 / p['pose_filter.rate'], self.publish)
        self.create_timer(p['pose_filter.diagnostics_period'], self.publish_diagnostics)
        inputs = [*topics, *covariance_topics, *([self.odometry] if self.odometry else [])]
        self.get_logger().info(f"{', '.join(self.resolve_topic_name(t) for t in inputs)} -> "
                               f"{self.resolve_topic_name('fused/odom')} at "
                               f"{p['pose_filter.rate']:g} Hz")

    def on_pose(self, msg: PoseStamped, topic: str, cov: np.ndarray) -> None:
        try:
            position, q = msg_to_pose_in(msg, self.world)
            yaw = yaw_of(q)
        except MessageError as err:
            self._malformed(f'{topic}: {err}')
            return
        self.filter.add(pose_measurement(topic, stamp_to_ns(msg.header.stamp) * 1e-9,
                                         position, yaw, cov))

    def on_pose_cov(self, msg: PoseWithCovarianceStamped, topic: str) -> None:
        try:
            position, q, cov = msg_to_pose_cov_in(msg, self.world)
            yaw = yaw_of(q)
        except MessageError as err:
            self._malformed(f'{topic}: {err}')
            return
        index = [0, 1, 2, 5]                   # x, y, z, yaw in the message's 6 x 6
        self.filter.add(pose_measurement(topic, stamp_to_ns(msg.header.stamp) * 1e-9,
                                         position, yaw, cov[np.ix_(index, index)]))

    def on_odometry(self, msg: Odometry) -> None:
        try:
            check_frame(msg.header, self.world)
            position, q, v_body, w_body = msg_to_odometry(msg)
            yaw = yaw_of(q)
        except MessageError as err:
            self._malformed(f'{self.odometry}: {err}')
            return
        if not (np.isfinite(position).all() and np.isfinite(v_body).all()
                and np.isfinite(w_body).all()):
            self._malformed(f'{self.odometry}: non-finite numbers')
            return
        self.filter.add(odometry_measurement(self.odometry, stamp_to_ns(msg.header.stamp) * 1e-9,
                                             position, yaw, v_body, w_body[2], self.odometry_cov))

    def newest(self) -> float:
        return max((c.last_stamp for c in self.filter.counts.values()), default=-math.inf)

    def publish(self) -> None:
        if not self.filter.initialised:
            return
        now = self.get_clock().now()
        t = now.nanoseconds * 1e-9
        if t - self.newest() > self.timeout:
            self.counts['stale'] += 1
            return
        est = self.filter.estimate(t)
        header = Header(stamp=now.to_msg(), frame_id=self.world)
        q = yaw_quaternion(est.yaw)
        P = est.P
        pose_cov = np.diag([0.0, 0.0, 0.0, UNKNOWN, UNKNOWN, 0.0])
        index = [0, 1, 2, 5]                   # x, y, z, yaw in the message's 6 x 6
        pose_cov[np.ix_(index, index)] = P[np.ix_([0, 1, 2, 6], [0, 1, 2, 6])]
        R = rot_z(est.yaw)
        twist_cov = np.diag([0.0, 0.0, 0.0, UNKNOWN, UNKNOWN, P[7, 7]])
        twist_cov[:3, :3] = R.T @ P[3:6, 3:6] @ R
        self.odom_pub.publish(odometry_to_msg(est.position, q, est.velocity,
                                              np.array([0.0, 0.0, est.x[7]]), header, self.body,
                                              pose_cov, twist_cov))
        self.pose_pub.publish(pose_to_msg(est.position, q, header))
        self.counts['published'] += 1

    def publish_diagnostics(self) -> None:
        t = self.get_clock().now().nanoseconds * 1e-9
        values: dict[str, object] = dict(self.counts)
        for source, c in self.filter.counts.items():
            values[f'{source}.applied'] = c.applied
            values[f'{source}.gated'] = c.gated
            values[f'{source}.too_old'] = c.too_old
            values[f'{source}.resets'] = c.resets
            values[f'{source}.age'] = f'{t - c.last_stamp:.3f}'
        if not self.filter.initialised:
            level, message = WARN, 'no measurement yet'
        elif t - self.newest() > self.timeout:
            level, message = ERROR, f'no measurement for {t - self.newest():.1f} s'
        else:
            level, message = OK, 'fusing'
        self.diag.publish(level, message, values)

    def _malformed(self, text: str) -> None:
        self.counts['malformed'] += 1
        self.warnings.skipped(text)


def main(args: list[str] | None = None) -> None:
    run(PoseFilterNode, 'pose_filter_node', args)


if __name__ == '__main__':
    main()
