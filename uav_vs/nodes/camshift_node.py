"""camshift_node: one ground camera's colour landmarks (chapter section 3.1, eq 18-19).

One process per camera, in the camera's namespace (`-r __ns:=/cam1 -p camera:=cam1`).
Subscribes `image_raw` (sensor_msgs/Image) and `image_raw/compressed`.
Publishes `landmarks` (geometry_msgs/PolygonStamped, the image's header: one point per
landmark in `landmarks.names` order, x, y = raw pixel centroid, z = confidence 0..1,
all NaN when the landmark is not found), `landmark_windows` (visualization_msgs/
ImageMarker, the image's header: the final CamShift window of every landmark found, the
annotation a viewer draws over the image; only while someone subscribes), `debug_image`
(when `camshift.debug_image`) and /diagnostics (frames, malformed, stale and future
images, restarts, errors, landmarks found, detection and publishing time of the last
frame `process_ms`).
Images come through uav_vs.ros.image_input; when time goes back (a new replay) the
detector forgets its windows and histogram and searches the whole image again.
"""
import time
from typing import Callable

import cv2
import numpy as np
from geometry_msgs.msg import PolygonStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from visualization_msgs.msg import ImageMarker

from uav_vs.ros.convert import bgr_to_image, outlines_to_marker, points_to_polygon, rect_corners
from uav_vs.ros.ground_params import declare_cameras, declare_landmarks
from uav_vs.ros.image_files import read_image
from uav_vs.ros.image_input import QOS_CHOICES, ImageInput, InputLimits, stamp_params
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, QuietPublisherNode, run
from uav_vs.ros.params import LiveParams, Param, T, declare
from uav_vs.vision.colour_model import models_from_params
from uav_vs.vision.landmarks import DetectorParams, LandmarkDetector, centroids

_D = DetectorParams()
WINDOW_RGBA = (1.0, 1.0, 0.0, 1.0)     # yellow, as in debug_image
DETECTOR_PARAMS = [  # all live: a new detector takes over the windows of the old one
    Param('camshift.hue_bins', T.INTEGER, _D.hue_bins, 'H-S histogram bins over hue 0..179',
          1, 180, live=True),
    Param('camshift.saturation_bins', T.INTEGER, _D.saturation_bins,
          'H-S histogram bins over saturation 0..255', 1, 256, live=True),
    Param('camshift.histogram_smoothing', T.DOUBLE, _D.histogram_smoothing,
          'image histogram smoothing over frames (eq 18); 0 = this frame only', 0.0, 0.99,
          live=True),
    Param('camshift.downscale', T.INTEGER, _D.downscale,
          'pixel step of the image histogram and of the whole-image search', 1, 16, live=True),
    Param('camshift.search_margin', T.DOUBLE, _D.search_margin,
          'search region = last window grown by this fraction of its larger side', 0.0, 10.0,
          live=True),
    Param('camshift.min_search_margin_px', T.INTEGER, _D.min_search_margin_px,
          '... and by at least this many pixels', 0, 10000, live=True),
    Param('camshift.min_mass_px', T.DOUBLE, _D.min_mass_px,
          'found: backprojected mass in the window, px', 0.0, 1e7, live=True),
    Param('camshift.min_confidence', T.DOUBLE, _D.min_confidence,
          'found: mean probability over the window', 0.0, 1.0, live=True),
    Param('camshift.reacquire_interval', T.INTEGER, _D.reacquire_interval,
          'frames between whole-image searches for a lost landmark', 1, 10000, live=True),
    Param('camshift.max_iterations', T.INTEGER, _D.max_iterations, 'CamShift iterations', 1, 1000,
          live=True),
    Param('camshift.epsilon_px', T.DOUBLE, _D.epsilon_px,
          'CamShift stops when the window moves less than this, px', 0.0, 100.0, live=True),
]
DETECTOR_NAMES = {spec.name for spec in DETECTOR_PARAMS}
NODE_PARAMS = [
    Param('camera', T.STRING, description='this camera, one of cameras.names'),
    Param('camshift.image_qos', T.STRING, 'sensor_data',
          'image subscription QoS: sensor_data (best effort) or reliable (bag replay)',
          choices=QOS_CHOICES),
    Param('camshift.debug_image', T.BOOL, False, 'publish debug_image with the windows drawn '
          '(read-only: the publisher is made at start-up)'),
    Param('camshift.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s (read-only: the '
          'timer is made at start-up)', 0.05, 60.0),
    *stamp_params('camshift'),
]


class CamshiftNode(QuietPublisherNode):
    def __init__(self, **node_options) -> None:
        """node_options: rclpy Node's keyword arguments (namespace, cli_args, ...), for a
        process holding several nodes (uav_vs.nodes.ground_station)."""
        super().__init__('camshift_node', **node_options)
        p = declare(self, NODE_PARAMS)
        camera = p['camera']
        cams = declare_cameras(self, only=camera)
        size = (cams[f'cameras.{camera}.width'], cams[f'cameras.{camera}.height'])
        self.frame_id = cams[f'cameras.{camera}.frame_id']
        landmarks = declare_landmarks(self)
        area = declare(self, [Param(f'landmarks.{n}.area_px', T.DOUBLE, 400.0,
                                    'expected landmark area in the image, px', 1.0, 1e7)
                              for n in landmarks['landmarks.names']])
        detector = declare(self, DETECTOR_PARAMS)
        params = DetectorParams.from_params(detector)
        self.samples = {}
        for name in landmarks['landmarks.names']:
            if path := landmarks[f'landmarks.{name}.sample']:
                self.samples[name], found = read_image(f'landmarks.{name}.sample', path,
                                                       cv2.IMREAD_UNCHANGED)
                self.get_logger().info(f'landmark {name}: colour model from {found}')
        self.colours = {**landmarks, **area}
        self.detector = LandmarkDetector(
            models_from_params(self.colours, params.bins, self.samples), params)
        self.pub = self.create_publisher(PolygonStamped, 'landmarks', 10)
        self.windows_pub = self.create_publisher(ImageMarker, 'landmark_windows', 10)
        self.debug_pub = (self.create_publisher(Image, 'debug_image', 1)
                          if p['camshift.debug_image'] else None)
        self.input = ImageInput(self, 'image_raw', p['camshift.image_qos'], self.on_image, size,
                                colour=True,
                                limits=InputLimits.of(p, 'camshift'),
                                on_restart=lambda: self.detector.reset())
        self.frames, self.process_ms = 0, float('nan')
        self.found = np.zeros(len(self.detector.models), int)
        self.diag = Diagnostics(self)
        self.create_timer(p['camshift.diagnostics_period'], self.publish_diagnostics)
        LiveParams(self, [*DETECTOR_PARAMS, *NODE_PARAMS], {**p, **detector}, self.reconfigure)
        names = landmarks['landmarks.names']
        self.get_logger().info(
            f"{camera}: {len(names)} landmarks ({', '.join(names)}) in "
            f"{self.resolve_topic_name('image_raw')}[/compressed] ({p['camshift.image_qos']}) "
            f"-> {self.resolve_topic_name('landmarks')}")

    def reconfigure(self, p: dict, changed: set[str]) -> Callable[[], None]:
        """Checked parameters set at run time -> what makes them take effect: for new
        detector settings, a detector with them (and colour models, for new bins) tracking
        on from the windows of the old one."""
        detector = self.new_detector(p) if changed & DETECTOR_NAMES else None

        def apply() -> None:
            if detector is not None:
                detector.reset(self.detector.windows)
                self.detector = detector
            self.input.set_limits(InputLimits.of(p, 'camshift'))
        return apply

    def new_detector(self, p: dict) -> LandmarkDetector:
        params = DetectorParams.from_params({k: v for k, v in p.items() if k in DETECTOR_NAMES})
        models = (self.detector.models if params.bins == self.detector.params.bins
                  else models_from_params(self.colours, params.bins, self.samples))
        return LandmarkDetector(models, params)

    def on_image(self, bgr: np.ndarray, header: Header) -> None:
        t0 = time.perf_counter()
        detections = self.detector.detect(bgr)
        xy, conf = centroids(detections)
        points = np.column_stack([xy, np.where(np.isnan(xy[:, 0]), np.nan, conf)])
        out_header = Header(stamp=header.stamp, frame_id=header.frame_id or self.frame_id)
        self.pub.publish(points_to_polygon(points, out_header))
        if self.windows_pub.get_subscription_count():
            self.windows_pub.publish(outlines_to_marker(
                [rect_corners(*d.window) for d in detections if d.found], out_header,
                WINDOW_RGBA, ns='landmarks'))
        self.process_ms = (time.perf_counter() - t0) * 1e3
        self.frames += 1
        self.found += [d.found for d in detections]
        if self.debug_pub is not None and self.debug_pub.get_subscription_count():
            self.debug_pub.publish(bgr_to_image(self.detector.draw(bgr, detections), header))

    def publish_diagnostics(self) -> None:
        last = [d is not None for d in self.detector.windows]
        if not self.frames:
            level, message = WARN, 'no image yet'
        elif not any(last):
            level, message = ERROR, 'no landmark found in the last frame'
        else:
            level, message = OK, f'{sum(last)}/{len(last)} landmarks found'
        level, message = self.input.diagnose(level, message)
        found = {f'found_{m.name}': int(n) for m, n in zip(self.detector.models, self.found)}
        self.diag.publish(level, message, {'frames': self.frames, **self.input.counts, **found,
                                           'process_ms': round(self.process_ms, 3)})


def main(args: list[str] | None = None) -> None:
    run(CamshiftNode, 'camshift_node', args)


if __name__ == '__main__':
    main()
