"""frames_node: the graph's TF tree (REP-105) on /tf_static and /tf.

/tf_static (tf2_msgs/TFMessage; reliable, transient local, depth 1, as tf2_ros's
StaticTransformBroadcaster offers it, so a late subscriber such as RViz still gets it):
one message with every static transform, sent at start-up:
- `frames.world_frame` -> each ground camera's `cameras.<name>.frame_id`, its pose taken
  from the calibration of config/ground_trinocular.yaml (x_c = R x_w + t, so the camera
  sits at -R^T t, oriented R^T), when `frames.ground_cameras`;
- `frames.base_link_frame` -> the onboard camera's `camera.frame_id`, its mounting
  `camera_to_base_link.*` of config/onboard.yaml, when `frames.onboard_camera`.

/tf (reliable, volatile, depth 100, as tf2_ros's TransformBroadcaster): for every pose
of a source in `frames.sources` (ground and onboard: geometry_msgs/PoseStamped; odom:
nav_msgs/Odometry), `frames.world_frame` -> `frames.<source>.child_frame`, stamped with
the pose's stamp; the source named by `frames.base_link_source` places
`frames.base_link_frame` too. A pose in another frame than `frames.world_frame`, with a
quaternion that is no rotation or a non-finite position is counted (`malformed`),
logged (at most every 5 s per source and kind of defect) and skipped. Also /diagnostics:
WARN while a source that has placed its frame sends none for `frames.silence_timeout`
(its frame in /tf, and base_link if it places that, is going stale).
Every parameter is read-only: frames, topics and calibration are the tree's at start-up.
"""
import time
from typing import Callable

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from uav_vs.ros.convert import (MessageError, check_frame, msg_to_odometry, msg_to_pose,
                                transform_to_msg)
from uav_vs.ros.ground_params import declare_cameras
from uav_vs.ros.node_main import OK, WARN, Diagnostics, QuietPublisherNode, ThrottledWarnings, run
from uav_vs.ros.params import Param, T, declare
from uav_vs.vision.camera import Camera, finite_numbers
from uav_vs.vision.frame_tree import (Transform, camera_transform, frame_name_problem,
                                      mounting_transform)
from uav_vs.vision.onboard_config import SETTINGS, camera_to_body

STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)

# Reads (position, unit quaternion xyzw) from a pose message; MessageError if it cannot.
Reader = Callable[[PoseStamped | Odometry], tuple[np.ndarray, np.ndarray]]
# Pose sources: message type and its reader.
SOURCES: dict[str, tuple[type, Reader]] = {
    'ground': (PoseStamped, msg_to_pose),
    'onboard': (PoseStamped, msg_to_pose),
    'odom': (Odometry, lambda msg: msg_to_odometry(msg)[:2]),
}

PARAMS = [
    Param('frames.world_frame', T.STRING, 'world', 'ENU world frame: parent of the cameras and '
          'of the vehicle frames; poses in another frame are refused'),
    Param('frames.base_link_frame', T.STRING, 'base_link',
          'FLU body frame: parent of the onboard camera, placed by frames.base_link_source'),
    Param('frames.base_link_source', T.STRING, 'ground',
          'pose source that also places base_link: ground, onboard, odom or none',
          choices=(*SOURCES, 'none')),
    Param('frames.sources', T.STRING_ARRAY, list(SOURCES),
          'pose sources subscribed, each placing its own child_frame', choices=tuple(SOURCES)),
    Param('frames.ground.topic', T.STRING, 'ground/pose',
          'ground station pose (PoseStamped, trinocular_pose_node)'),
    Param('frames.ground.child_frame', T.STRING, 'base_link_ground',
          'vehicle frame the ground station pose places'),
    Param('frames.onboard.topic', T.STRING, 'onboard/pose',
          'onboard camera pose (PoseStamped, homography_pose_node)'),
    Param('frames.onboard.child_frame', T.STRING, 'base_link_onboard',
          'vehicle frame the onboard pose places'),
    Param('frames.odom.topic', T.STRING, 'autopilot/odom',
          "autopilot's estimate (nav_msgs/Odometry, mavlink_relay_node)"),
    Param('frames.odom.child_frame', T.STRING, 'base_link_odom',
          "vehicle frame the autopilot's estimate places"),
    Param('frames.ground_cameras', T.BOOL, True,
          'publish world -> each ground camera (cameras.* of ground_trinocular.yaml)'),
    Param('frames.onboard_camera', T.BOOL, True, 'publish base_link -> the onboard camera '
          '(camera.frame_id, camera_to_base_link.* of onboard.yaml)'),
    Param('frames.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.05, 60.0),
    Param('frames.silence_timeout', T.DOUBLE, 1.0, 'a source that has placed its frame and '
          'then places none for this long, s, is reported silent (WARN)', 0.05, 3600.0),
]

_MOUNTING = {'camera.frame_id': T.STRING, 'camera_to_base_link.xyz': T.DOUBLE_ARRAY,
             'camera_to_base_link.rpy': T.DOUBLE_ARRAY}
MOUNTING_PARAMS = [Param(s.key, _MOUNTING[s.key], s.default, s.description, size=s.size)
                   for s in SETTINGS if s.key in _MOUNTING]


class FramesNode(QuietPublisherNode):
    def __init__(self) -> None:
        super().__init__('frames_node')
        p = declare(self, PARAMS)
        self.world, self.base_link = p['frames.world_frame'], p['frames.base_link_frame']
        self.base_link_source = p['frames.base_link_source']
        sources = list(dict.fromkeys(p['frames.sources']))
        if self.base_link_source not in (*sources, 'none'):
            raise ValueError(f'frames.base_link_source: {self.base_link_source!r} is not in '
                             f'frames.sources {sources} (or none)')
        self.children = {s: p[f'frames.{s}.child_frame'] for s in sources}
        static = self.static_transforms(p)
        self.check_frame_names(static)
        self.static_pub = self.create_publisher(TFMessage, '/tf_static', STATIC_QOS)
        self.tf_pub = self.create_publisher(TFMessage, '/tf', TF_QOS)
        self.publish_static(list(static.values()))
        self.counts = {**{s: 0 for s in sources}, 'malformed': 0}
        self.static_count, self.reported_malformed, self.last_malformed = len(static), 0, ''
        self.silence_timeout = p['frames.silence_timeout']
        self.last_placed: dict[str, float] = {}     # source -> time.monotonic() of its last pose
        self.warnings = ThrottledWarnings(self)
        for source in sources:
            msg_type, read = SOURCES[source]
            self.create_subscription(msg_type, p[f'frames.{source}.topic'],
                                     lambda msg, s=source, r=read: self.on_pose(s, r, msg), 10)
        self.diag = Diagnostics(self)
        self.create_timer(p['frames.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(
            f'static: {", ".join(f"{t.parent} -> {t.child}" for t in static.values()) or "none"}'
            f'; poses: {", ".join(f"{s} -> {c}" for s, c in self.children.items()) or "none"}'
            f'; {self.base_link} placed by {self.base_link_source.replace("none", "no source")}')

    def check_frame_names(self, static: dict[str, Transform]) -> None:
        """ValueError naming the parameter if the configured frames cannot make one tree."""
        problem = frame_name_problem({
            'frames.world_frame': self.world, 'frames.base_link_frame': self.base_link,
            **{f'frames.{s}.child_frame': child for s, child in self.children.items()},
            **{param: t.child for param, t in static.items()}})
        if problem:
            raise ValueError(problem)

    def static_transforms(self, p: dict) -> dict[str, Transform]:
        """The static transforms, by the parameter that names their child frame."""
        static = {}
        if p['frames.ground_cameras']:
            flat = declare_cameras(self)
            for name in flat['cameras.names']:
                key = f'cameras.{name}.'
                sub = {k.removeprefix(key): v for k, v in flat.items() if k.startswith(key)}
                static[key + 'frame_id'] = camera_transform(
                    self.world, Camera.from_params(name, sub, key))
        if p['frames.onboard_camera']:
            m = declare(self, MOUNTING_PARAMS)
            xyz, rpy = (finite_numbers(m[k], 3, k) for k in
                        ('camera_to_base_link.xyz', 'camera_to_base_link.rpy'))
            static['camera.frame_id'] = mounting_transform(self.base_link, m['camera.frame_id'],
                                                           camera_to_body(xyz, rpy))
        return static

    def publish_static(self, transforms: list[Transform]) -> None:
        """Every static transform in one message (a depth-1 transient-local topic keeps one)."""
        if not transforms:
            return
        stamp = self.get_clock().now().to_msg()
        self.static_pub.publish(TFMessage(transforms=[
            transform_to_msg(t.translation, t.quaternion, Header(stamp=stamp, frame_id=t.parent),
                             t.child) for t in transforms]))

    def on_pose(self, source: str, read: Reader, msg: PoseStamped | Odometry) -> None:
        """world -> the source's frame (and base_link) from one pose, or the pose counted
        as malformed."""
        try:
            check_frame(msg.header, self.world)
        except MessageError as err:
            return self.malformed(source, 'frame', str(err))
        try:
            position, quaternion = read(msg)
        except MessageError as err:
            return self.malformed(source, 'rotation', str(err))
        if not np.all(np.isfinite(position)):
            return self.malformed(source, 'position', f'non-finite position {position.tolist()}')
        header = Header(stamp=msg.header.stamp, frame_id=self.world)
        children = [self.children[source]]
        if source == self.base_link_source:
            children.append(self.base_link)
        self.tf_pub.publish(TFMessage(transforms=[
            transform_to_msg(position, quaternion, header, child) for child in children]))
        self.counts[source] += 1
        self.last_placed[source] = time.monotonic()

    def malformed(self, source: str, kind: str, why: str) -> None:
        """Count and log (at most every 5 s per source and kind of defect) a skipped pose."""
        self.counts['malformed'] += 1
        self.last_malformed = f'{source} pose: {why}'
        self.warnings.warn(f'{source} {kind}', f'{self.last_malformed}; skipped')

    def publish_diagnostics(self) -> None:
        new = self.counts['malformed'] - self.reported_malformed
        self.reported_malformed = self.counts['malformed']
        level = OK
        message = (f'{self.static_count} static transforms, vehicle frames from '
                   f'{", ".join(self.children) or "no source"}')
        if new:
            level = WARN
            message += f'; {new} malformed poses skipped: {self.last_malformed}'
        now = time.monotonic()
        silent = {s: now - t for s, t in self.last_placed.items() if now - t > self.silence_timeout}
        if silent:
            level = WARN
            message += '; silent: ' + ', '.join(f'{s} for {age:.1f} s' for s, age in silent.items())
        self.diag.publish(level, message, {**self.counts, 'static': self.static_count,
                                           'base_link_source': self.base_link_source,
                                           'silent': ' '.join(silent)})


def main(args: list[str] | None = None) -> None:
    run(FramesNode, 'frames_node', args)


if __name__ == '__main__':
    main()
