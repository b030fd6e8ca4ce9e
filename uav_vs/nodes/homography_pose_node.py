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
gave a pose, the same with its covariance on `onboard/pose_cov`
(geometry_msgs/PoseWithCovarianceStamped, uav_vs.vision.plane_pose_covariance: the
refined fit's and the keyframes' drift; while something subscribes), and /diagnostics:
tracked features, inliers, RANSAC trials, reprojection RMS, the pixel noise the
covariance took, re-anchors, relocalisations, lost frames, malformed images and, when
lost, why.

The first image initialises the estimator (init.*); until that succeeds (a blurred or
texture-less first frame) every new image retries. With `init.mode` pose_topic it is
initialised at the pose another source (`init.pose_topic`, e.g. the ground station's
ground/pose) gives at the first frame's stamp: the poses either side of it interpolated,
the frame held until the pose after it has come (the frames meanwhile are lost, for up to
`init.max_wait` s; then a newer frame is held instead); a frame with no pose near it is
lost. Frames reach it through
uav_vs.ros.image_input: decoded once, in stamp order, malformed and future-stamped ones
counted and skipped. When time goes back (a bag loop, a new replay) the estimator starts
again as at start-up: the next frame initialises it from init.*.
"""
import time
from typing import Callable

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header

from uav_vs.control.follow import PoseHistory
from uav_vs.ros.convert import (MessageError, msg_to_pose_in, pose_cov_to_msg, pose_to_msg,
                                stamp_to_ns)
from uav_vs.ros.image_input import QOS_CHOICES, ImageInput, InputLimits, stamp_params
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, run
from uav_vs.ros.params import REQUIRED, LiveParams, Param, T, declare
from uav_vs.vision.camera import CalibrationError
from uav_vs.vision.onboard_config import SETTINGS, load_onboard_config
from uav_vs.vision.plane_pose import PlanePoseEstimator

_TYPES = {'int': T.INTEGER, 'float': T.DOUBLE, 'str': T.STRING, 'floats': T.DOUBLE_ARRAY}

# The initial poses come as the controller takes poses: the newest, lost ones not re-sent.
INIT_POSE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)

# The estimator's thresholds, read on every frame, take effect when set at run time; the
# calibration, the first frame's pose and what builds the tracker (klt.*, the features'
# detection) or describes a keyframe (relocalise.features, .max_features) are read-only.
LIVE = {'features.max_features', 'features.min_tracks', 'homography.method',
        'homography.threshold_px', 'homography.confidence', 'homography.max_trials',
        'homography.min_inliers', 'pose.max_rms_px', 'keyframe.reanchor_inliers',
        'keyframe.reanchor_coverage', 'relocalise.after_frames', 'relocalise.ratio',
        'relocalise.max_shift', 'image_quality.blur_level', 'image_quality.min_sharpness',
        'covariance.pixel_sigma_floor'}
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

STATS = ('sharpness', 'tracked', 'inliers', 'trials', 'rms_px', 'pixel_sigma', 'reanchors',
         'relocalisations', 'lost_frames')


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
        self.pose_cov_pub = self.create_publisher(PoseWithCovarianceStamped, 'onboard/pose_cov',
                                                  10)
        self.images = ImageInput(self, 'onboard/image_raw', p['homography_pose.image_qos'],
                                 self.on_frame, (cfg.camera.width, cfg.camera.height),
                                 limits=InputLimits.of(p, 'homography_pose'),
                                 on_restart=self.restart)
        self.counts = dict(frames=0, poses=0, lost=0)
        self.init_poses = PoseHistory()
        self.pending: tuple[np.ndarray, Header] | None = None   # the first frame, waiting
        if cfg.init_pose is not None:
            self.counts.update(init_poses=0, malformed_init_poses=0)
            self.create_subscription(PoseStamped, cfg.init_pose.topic, self.on_init_pose,
                                     INIT_POSE_QOS)
        self.last = dict(reason='no image yet', last_loss='', last_loss_stamp='',
                         process_ms=float('nan'), **{k: '' for k in STATS})
        self.diag = Diagnostics(self, hardware_id=cfg.camera.frame_id)
        self.create_timer(p['homography_pose.diagnostics_period'], self.publish_diagnostics)
        source = (self.resolve_topic_name(cfg.init_pose.topic) if cfg.init_pose is not None
                  else cfg.init_mode)
        self.get_logger().info(f'{cfg.camera.width}x{cfg.camera.height} camera, initialising '
                               f'from {source}, homography {cfg.params.method}')
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
        self.init_poses, self.pending = PoseHistory(), None

    def on_init_pose(self, msg: PoseStamped) -> None:
        try:
            position, q = msg_to_pose_in(msg, self.frame_id)
        except MessageError as err:
            self.counts['malformed_init_poses'] += 1
            self.get_logger().warn(f'{self.cfg.init_pose.topic}: {err}',
                                   throttle_duration_sec=5.0)
            return
        self.counts['init_poses'] += 1
        self.init_poses.add(stamp_to_ns(msg.header.stamp) * 1e-9,
                            Rotation.from_quat(q).as_matrix(), position)
        if self.pending is not None:
            self.initialise_pending()

    def on_frame(self, gray, header: Header) -> None:
        self.counts['frames'] += 1
        if self.estimator.initialised or self.cfg.init_pose is None:
            self.process(gray, header, self.H0)
            return
        init = self.cfg.init_pose
        if self.pending is not None:
            waited = stamp_to_ns(header.stamp) - stamp_to_ns(self.pending[1].stamp)
            if waited <= init.max_wait * 1e9:
                self.lose(header, f'the first frame waits for {init.topic}')
                return
            self.lose(self.pending[1], f'no {init.topic} pose after the first frame within '
                                       f'{init.max_wait:g} s')
        self.pending = (gray, header)
        self.initialise_pending()

    def initialise_pending(self) -> None:
        """The held first frame, initialised at the pose at its stamp once known."""
        gray, header = self.pending
        stamp, init = stamp_to_ns(header.stamp) * 1e-9, self.cfg.init_pose
        if self.init_poses.newest() < stamp:
            self.last['reason'] = f'waiting for {init.topic} at the first frame'
            return      # the pose after the frame may still come
        self.pending = None
        found = self.init_poses.at(stamp, init.max_gap, init.max_interval)
        if isinstance(found, str):
            self.lose(header, f'no {init.topic} pose at the first frame: {found}')
            return
        try:
            H0 = self.cfg.homography_at(*found)
        except CalibrationError as err:
            self.lose(header, str(err))
            return
        self.process(gray, header, H0)

    def lose(self, header: Header, reason: str) -> None:
        self.counts['lost'] += 1
        self.last.update(reason=reason, last_loss=reason,
                         last_loss_stamp=f'{stamp_to_ns(header.stamp) * 1e-9:.3f}')
        self.get_logger().warn(f'no pose: {reason}', throttle_duration_sec=5.0)

    def process(self, gray, header: Header, H0: np.ndarray | None) -> None:
        start = time.perf_counter()
        with_covariance = self.pose_cov_pub.get_subscription_count() > 0
        if self.estimator.initialised:
            result = self.estimator.update(gray, covariance=with_covariance)
        else:
            result = self.estimator.initialise(gray, H0)
            if result.ok:
                self.get_logger().info(f'initialised on the frame stamped '
                                       f'{stamp_to_ns(header.stamp) * 1e-9:.3f} s')
        self.last.update({k: result.stats.get(k, '') for k in STATS},
                         process_ms=round((time.perf_counter() - start) * 1e3, 2),
                         reason=result.reason)
        if not result.ok:
            self.lose(header, result.reason)
            return
        self.counts['poses'] += 1
        out = Header(stamp=header.stamp, frame_id=self.frame_id)
        self.pose_pub.publish(pose_to_msg(result.position, result.quaternion, out))
        if with_covariance:
            self.pose_cov_pub.publish(pose_cov_to_msg(result.position, result.quaternion,
                                                      result.covariance, out))

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
