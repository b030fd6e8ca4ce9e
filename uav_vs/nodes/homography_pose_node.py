"""homography_pose_node: vehicle pose over the ground plane from the onboard camera (section 4).

Subscribes `onboard/image_raw` (sensor_msgs/Image: bgr8, rgb8, bgra8, rgba8, mono8) and
`onboard/image_raw/compressed` (sensor_msgs/CompressedImage: jpeg, png), sensor-data
QoS unless `homography_pose.image_qos` is `reliable`. Intrinsics, the camera's mounting
and the first frame's plane homography come from the params file (config/onboard.yaml,
keys of uav_vs.vision.onboard_config.SETTINGS), not from CameraInfo.

Each frame goes through PlanePoseEstimator: keyframe-to-frame pyramidal L-K tracks
(section 2.1.2), robust homography (section 2.3, Algorithm 1) chained onto the
keyframe's plane homography and decomposed (eq 27), refined on the inliers; after a
loss, the keyframe is found again by descriptor matches (section 2.2, `relocalise.*`).
Publishes `onboard/pose` (geometry_msgs/PoseStamped, frame `homography_pose.frame_id`
= `world` ENU: the base_link pose, stamped with the image's stamp) only for frames that
gave a pose, and /diagnostics: tracked features, inliers, RANSAC trials, reprojection
RMS, re-anchors, relocalisations, lost frames, malformed images and, when lost, why.

The first image initialises the estimator (init.*); until that succeeds (a blurred or
texture-less first frame) every new image retries. Frames reach it through
uav_vs.ros.image_input: decoded once, in stamp order, malformed and future-stamped ones
counted and skipped. When time goes back (a bag loop, a new replay) the estimator starts
again as at start-up: the next frame initialises it from init.*.
"""
import time
from typing import Callable

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from std_msgs.msg import Header

from uav_vs.ros.convert import pose_to_msg, stamp_to_ns
from uav_vs.ros.image_input import QOS_CHOICES, ImageInput, InputLimits, stamp_params
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, run
from uav_vs.ros.params import REQUIRED, LiveParams, Param, T, declare
from uav_vs.vision.onboard_config import SETTINGS, load_onboard_config
from uav_vs.vision.plane_pose import PlanePoseEstimator

_TYPES = {'int': T.INTEGER, 'float': T.DOUBLE, 'str': T.STRING, 'floats': T.DOUBLE_ARRAY}

# The estimator's thresholds, read on every frame, take effect when set at run time; the
# calibration, the first frame's pose and what builds the tracker (klt.*, the features'
# detection) or describes a keyframe (relocalise.features, .max_features) are read-only.
LIVE = {'features.max_features', 'features.min_tracks', 'homography.method',
        'homography.threshold_px', 'homography.confidence', 'homography.max_trials',
        'homography.min_inliers', 'pose.max_rms_px', 'keyframe.reanchor_inliers',
        'keyframe.reanchor_coverage', 'relocalise.after_frames', 'relocalise.ratio',
        'relocalise.max_shift', 'image_quality.blur_level', 'image_quality.min_sharpness'}
ONBOARD_PARAMS = [Param(s.key, _TYPES[s.kind], REQUIRED if s.default is None else s.default,
                        s.description, s.low, s.high, s.choices, s.size or None,
                        live=s.key in LIVE)
                  for s in SETTINGS]

NODE_PARAMS = [
    Param('homography_pose.image_qos', T.STRING, 'sensor_data',
          'image subscriptions: sensor_data (best effort) or reliable', choices=QOS_CHOICES),
    Param('homography_pose.frame_id', T.STRING, 'world', 'frame of the published pose (ENU)'),
    Param('homography_pose.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s '
          '(read-only: the timer is made at start-up)', 0.05, 60.0),
    Param('homography_pose.seed', T.INTEGER, 0, 'random seed of the ransac and lmeds '
          'estimators (repeatable runs)', 0, 2**31 - 1),
    *stamp_params('homography_pose'),
]

STATS = ('sharpness', 'tracked', 'inliers', 'trials', 'rms_px', 'reanchors', 'relocalisations',
         'lost_frames')


class HomographyPoseNode(Node):
    def __init__(self) -> None:
        super().__init__('homography_pose_node')
        onboard = declare(self, ONBOARD_PARAMS)
        self.cfg = cfg = load_onboard_config(onboard)
        p = declare(self, NODE_PARAMS)
        self.frame_id = p['homography_pose.frame_id']
        self.H0 = cfg.initial_homography
        self.new_estimator = lambda: PlanePoseEstimator(self.cfg.camera, self.cfg.params,
                                                        self.cfg.camera_to_body,
                                                        seed=p['homography_pose.seed'])
        self.estimator = self.new_estimator()
        self.pose_pub = self.create_publisher(PoseStamped, 'onboard/pose', 10)
        self.images = ImageInput(self, 'onboard/image_raw', p['homography_pose.image_qos'],
                                 self.on_frame, (cfg.camera.width, cfg.camera.height),
                                 limits=InputLimits.of(p, 'homography_pose'),
                                 on_restart=self.restart)
        self.counts = dict(frames=0, poses=0, lost=0)
        self.last = dict(reason='no image yet', last_loss='', last_loss_stamp='',
                         process_ms=float('nan'), **{k: '' for k in STATS})
        self.diag = Diagnostics(self, hardware_id=cfg.camera.frame_id)
        self.create_timer(p['homography_pose.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(f'{cfg.camera.width}x{cfg.camera.height} camera, initialising '
                               f'from {cfg.init_mode}, homography {cfg.params.method}')
        LiveParams(self, [*ONBOARD_PARAMS, *NODE_PARAMS], {**onboard, **p}, self.reconfigure)

    def reconfigure(self, p: dict, changed: set[str]) -> Callable[[], None]:
        """Checked parameters set at run time -> what makes them take effect: the
        estimator's new thresholds from the next frame on (its tracks are kept)."""
        cfg = load_onboard_config({s.key: p[s.key] for s in SETTINGS})

        def apply() -> None:
            self.cfg = cfg
            self.estimator.params = cfg.params     # frozen; its klt settings are unchanged
            self.images.set_limits(InputLimits.of(p, 'homography_pose'))
        return apply

    def restart(self) -> None:
        """Time went back (a new replay): start again from init.*, as at start-up."""
        self.estimator = self.new_estimator()

    def on_frame(self, gray, header: Header) -> None:
        self.counts['frames'] += 1
        start = time.perf_counter()
        if self.estimator.initialised:
            result = self.estimator.update(gray)
        else:
            result = self.estimator.initialise(gray, self.H0)
            if result.ok:
                self.get_logger().info(f'initialised on the frame stamped '
                                       f'{stamp_to_ns(header.stamp) * 1e-9:.3f} s')
        self.last.update({k: result.stats.get(k, '') for k in STATS},
                         process_ms=round((time.perf_counter() - start) * 1e3, 2),
                         reason=result.reason)
        if not result.ok:
            self.counts['lost'] += 1
            self.last.update(last_loss=result.reason,
                             last_loss_stamp=f'{stamp_to_ns(header.stamp) * 1e-9:.3f}')
            self.get_logger().warn(f'no pose: {result.reason}', throttle_duration_sec=5.0)
            return
        self.counts['poses'] += 1
        self.pose_pub.publish(pose_to_msg(result.position, result.quaternion,
                                          Header(stamp=header.stamp, frame_id=self.frame_id)))

    def publish_diagnostics(self) -> None:
        reason = self.last['reason']
        if not self.estimator.initialised:
            level = ERROR if self.counts['frames'] else WARN
            message = f'not initialised: {reason}'
        elif reason:
            level, message = WARN, f'tracking lost: {reason}'
        else:
            level, message = OK, 'tracking'
        level, message = self.images.diagnose(level, message)
        self.diag.publish(level, message, {**self.counts, **self.images.counts, **self.last})


def main(args: list[str] | None = None) -> None:
    run(HomographyPoseNode, 'homography_pose_node', args)


if __name__ == '__main__':
    main()
