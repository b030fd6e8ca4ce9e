"""target_tracker_node: a planar target found in every onboard frame (chapter Fig. 2).

The target (a helipad, a car seen from above) is given by a template image file
(`target.template`; a relative path is found as uav_vs.ros.image_files says, so the
YAML's `uav_vs/sim/assets/box.png` works wherever `ros2 run` starts the node). Its
features are matched in each frame (SIFT, or the free ORB, section 2.2) and a robust
homography (section 2.3, Algorithm 1) maps the template onto the frame.
`target.method` defaults to the library's choice, cv2 RANSAC (uav_vs.vision.homography).

Subscribes `onboard/image_raw` (sensor_msgs/Image: bgr8, rgb8, bgra8, rgba8, mono8) and
`onboard/image_raw/compressed` (sensor_msgs/CompressedImage: jpeg, png), sensor-data
QoS unless `target.image_qos` is `reliable`; images of any size.
Publishes, for every frame where the target is found, `onboard/target`
(geometry_msgs/PolygonStamped, the image's header: stamp and optical frame) with five
points in the image's raw pixel coordinates (x right, y down, z = 0): the template's
outer corners (0, 0), (w, 0), (w, h), (0, h) (top-left, top-right, bottom-right,
bottom-left) mapped into the image, then the target's centre (the template centre
(w/2, h/2) through the homography, not the corners' mean);
`onboard/target_found` (std_msgs/Bool) for every frame processed, true or false;
`onboard/target_outline` (visualization_msgs/ImageMarker, the image's header: the
target's outline, empty when it is not found; the annotation a viewer draws over the
image, only while someone subscribes); and
/diagnostics (frames, found, not found, malformed, stale and future images, restarts,
errors, inliers, reason). A frame without the target publishes nothing on
onboard/target: why is the diagnostics' message and, every 5 s at most, a warning in
the log. Images come through uav_vs.ros.image_input.
"""
import time
from typing import Callable

import cv2
import numpy as np
from geometry_msgs.msg import PolygonStamped
from rclpy.node import Node
from std_msgs.msg import Bool, Header
from visualization_msgs.msg import ImageMarker

from uav_vs.ros.convert import outlines_to_marker, points_to_polygon
from uav_vs.ros.image_files import read_image
from uav_vs.ros.image_input import QOS_CHOICES, ImageInput, InputLimits, stamp_params
from uav_vs.ros.node_main import OK, WARN, Diagnostics, run
from uav_vs.ros.params import LiveParams, Param, ParameterError, T, declare
from uav_vs.vision.features import KINDS
from uav_vs.vision.homography import DEFAULT_METHOD, METHODS
from uav_vs.vision.target_tracking import PlanarTargetTracker

OUTLINE_RGBA = (0.0, 1.0, 0.0, 1.0)     # green

PARAMS = [  # the tracker's: live, a new tracker is built from them (the template file read again)
    Param('target.template', T.STRING, description=(
        'image file of the target as seen from above (any format OpenCV reads)'), live=True),
    Param('target.features', T.STRING, 'sift', 'feature detector and descriptor (section 2.2)',
          choices=KINDS, live=True),
    Param('target.max_features', T.INTEGER, 0, 'features per image (0: every SIFT feature, '
          '5000 ORB)', 0, 100000, live=True),
    Param('target.ratio', T.DOUBLE, 0.75, "Lowe's ratio test: nearest / second nearest",
          0.05, 0.99, live=True),
    Param('target.method', T.STRING, DEFAULT_METHOD, 'robust homography estimator (section 2.3)',
          choices=METHODS, live=True),
    Param('target.threshold_px', T.DOUBLE, 3.0, 'homography inlier distance, px', 0.1, 50.0,
          live=True),
    Param('target.min_inliers', T.INTEGER, 12, 'fewer inliers: not found', 4, 10000, live=True),
    Param('target.image_qos', T.STRING, 'sensor_data',
          'image subscriptions: sensor_data (best effort) or reliable', choices=QOS_CHOICES),
    Param('target.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s (read-only: the '
          'timer is made at start-up)', 0.05, 60.0),
    *stamp_params('target'),
]


STAMP_NAMES = {spec.name for spec in stamp_params('target')}


def tracker_from(p: dict) -> tuple[PlanarTargetTracker, str]:
    """The tracker of the `target.*` parameters and the template file it was read from;
    ParameterError names a bad parameter."""
    template, path = read_image('target.template', p['target.template'], cv2.IMREAD_GRAYSCALE)
    try:
        return PlanarTargetTracker(
            template, kind=p['target.features'], ratio=p['target.ratio'],
            method=p['target.method'], threshold_px=p['target.threshold_px'],
            min_inliers=p['target.min_inliers'], max_features=p['target.max_features']), path
    except ValueError as err:      # too few features in the template
        raise ParameterError(f'target.template: {path}: {err}') from None


class TargetTrackerNode(Node):
    def __init__(self) -> None:
        super().__init__('target_tracker_node')
        p = declare(self, PARAMS)
        self.tracker, path = tracker_from(p)
        width, height = self.tracker.corners[2]
        self.target_pub = self.create_publisher(PolygonStamped, 'onboard/target', 10)
        self.found_pub = self.create_publisher(Bool, 'onboard/target_found', 10)
        self.outline_pub = self.create_publisher(ImageMarker, 'onboard/target_outline', 10)
        self.images = ImageInput(self, 'onboard/image_raw', p['target.image_qos'], self.on_frame,
                                 limits=InputLimits.of(p, 'target'))
        self.counts = dict(frames=0, found=0, not_found=0)
        self.last = dict(reason='no image yet', inliers=0, process_ms=float('nan'))
        self.diag = Diagnostics(self, hardware_id=str(path))
        self.create_timer(p['target.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(f"template {path} ({width:.0f}x{height:.0f} px), "
                               f"{p['target.features']} features")
        LiveParams(self, PARAMS, p, self.reconfigure)

    def reconfigure(self, p: dict, changed: set[str]) -> Callable[[], None]:
        """Checked parameters set at run time -> what makes them take effect."""
        tracker, _ = tracker_from(p) if changed - STAMP_NAMES else (self.tracker, None)

        def apply() -> None:
            self.tracker = tracker
            self.images.set_limits(InputLimits.of(p, 'target'))
        return apply

    def on_frame(self, gray: np.ndarray, header: Header) -> None:
        self.counts['frames'] += 1
        start = time.perf_counter()
        result = self.tracker.find(gray)
        self.last = dict(reason=result.reason, inliers=result.n_inliers,
                         process_ms=round((time.perf_counter() - start) * 1e3, 2))
        self.counts['found' if result.ok else 'not_found'] += 1
        if result.ok:
            self.target_pub.publish(points_to_polygon(np.vstack([result.corners, result.center]),
                                                      header))
        else:
            self.get_logger().warn(f'target not found: {result.reason}',
                                   throttle_duration_sec=5.0)
        self.found_pub.publish(Bool(data=bool(result.ok)))
        if self.outline_pub.get_subscription_count():
            self.outline_pub.publish(outlines_to_marker(
                [result.corners] if result.ok else [], header, OUTLINE_RGBA, ns='target'))

    def publish_diagnostics(self) -> None:
        if self.last['reason']:
            level, message = WARN, f"target not found: {self.last['reason']}"
        else:
            level, message = OK, 'target found'
        level, message = self.images.diagnose(level, message)
        self.diag.publish(level, message, {**self.counts, **self.images.counts, **self.last})


def main(args: list[str] | None = None) -> None:
    run(TargetTrackerNode, 'target_tracker_node', args)


if __name__ == '__main__':
    main()
