"""trinocular_pose_node: vehicle pose from the ground cameras' landmark centroids (section 3.1.1).

Subscribes `<camera>/landmarks` (geometry_msgs/PolygonStamped, one point per
landmark in `landmarks.names` order: x, y = raw pixel centroid, z = confidence,
NaN when not found) for every camera in `cameras.names`; synchronises them by stamp
(each camera's `cameras.<name>.latency` taken off its stamps first, so that a frame set
and its pose are stamped with the instant the cameras saw);
triangulates (eq 24-25) and solves yaw + position (eq 26).
Publishes `ground/pose` (PoseStamped, `world` ENU), the same pose with its covariance on
`ground/pose_cov` (PoseWithCovarianceStamped: the landmarks' pixel noise pooled from the
triangulation residuals, never below `trinocular.pixel_sigma_floor`, propagated through
eq 24-26, plus `trinocular.bias_sigma` on the position; uav_vs.vision.pose_covariance;
solved only while something subscribes to it), `ground/landmarks`
(PolygonStamped, 3D landmark positions in `world`, NaN where not triangulated) and
/diagnostics. A frame set that gives no pose publishes none on ground/pose: why is the
diagnostics' message and, every 5 s at most, a warning in the log.

A landmarks message stamped more than `trinocular.future_tolerance` ahead of the node's
clock is dropped (`future`) before it reaches the synchroniser, so a camera clock
glitch cannot hold a frame set; one older than its camera's last by more than
`trinocular.restart_after` (a new replay) restarts the synchroniser (`restarts`). A
frame set whose processing raises is counted (`errors`), logged and skipped. A camera
silent for longer than `trinocular.input_warn_after` makes the diagnostics WARN; every
camera silent for longer than `trinocular.input_error_after`, ERROR.
"""
from typing import Callable

import numpy as np
from geometry_msgs.msg import PolygonStamped, PoseStamped, PoseWithCovarianceStamped
from std_msgs.msg import Header

from uav_vs.ros.convert import (ns_to_stamp, points_to_polygon, polygon_to_array,
                                pose_cov_to_msg, pose_to_msg, stamp_to_ns)
from uav_vs.ros.image_input import InputLimits, error_text, stamp_params
from uav_vs.ros.liveness import Silence
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, QuietPublisherNode, run
from uav_vs.ros.params import LiveParams, Param, ParameterError, T, declare
from uav_vs.vision.body_pose import solve_pose
from uav_vs.vision.frame_sync import FrameSync, ahead_of_clock
from uav_vs.vision.ground_config import load_ground_config
from uav_vs.vision.pose_covariance import PixelNoise, landmark_covariances, pose_covariance
from uav_vs.vision.triangulation import triangulate

from uav_vs.ros.ground_params import declare_cameras, declare_landmarks

NODE_PARAMS = [
    Param('trinocular.method', T.STRING, 'lsq', 'triangulation: lsq (eq 24-25) or opencv (DLT)',
          choices=('lsq', 'opencv'), live=True),
    Param('trinocular.pose_method', T.STRING, 'yaw',
          'yaw: eq 26 (pitch, roll ~ 0); rigid: full 6-DoF SVD alignment', choices=('yaw', 'rigid'),
          live=True),
    Param('trinocular.sync_tolerance', T.DOUBLE, 0.010,
          'max stamp difference between cameras in one frame set, s', 0.0, 1.0, live=True),
    Param('trinocular.max_wait', T.DOUBLE, 0.2,
          'release a frame set without a silent camera after this long, s', 0.0, 10.0, live=True),
    Param('trinocular.min_cameras', T.INTEGER, 2, 'cameras needed for a frame set', 2, 64,
          live=True),
    Param('trinocular.max_reprojection_px', T.DOUBLE, 3.0,
          'a landmark reprojecting worse than this drops its worst camera, px', 0.1, 1000.0,
          live=True),
    Param('trinocular.min_confidence', T.DOUBLE, 0.0,
          'centroids with a lower confidence are ignored', 0.0, 1.0, live=True),
    Param('trinocular.pixel_sigma_floor', T.DOUBLE, 0.5,
          "smallest pixel noise of the centroids ground/pose_cov's covariance assumes, px "
          '(below it the residuals are taken for luck)', 0.01, 100.0, live=True),
    Param('trinocular.bias_sigma', T.DOUBLE, 0.01,
          "standard deviation of a position bias every camera shares (the rig's calibration, "
          "the landmarks' survey), added to ground/pose_cov per axis, m", 0.0, 10.0, live=True),
    Param('trinocular.frame_id', T.STRING, 'world', 'frame of the published pose (ENU)'),
    Param('trinocular.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s (read-only: the '
          'timer is made at start-up)', 0.05, 60.0),
    *stamp_params('trinocular', 'a landmarks message'),
]


class TrinocularPoseNode(QuietPublisherNode):
    def __init__(self, subscribe: bool = True, **node_options) -> None:
        """node_options: rclpy Node's keyword arguments (namespace, cli_args, ...), for a
        process holding several nodes (uav_vs.nodes.ground_station); there, without
        `subscribe`, the cameras' landmarks come by on_landmarks calls, not topics."""
        super().__init__('trinocular_pose_node', **node_options)
        self.cfg = load_ground_config({**declare_cameras(self), **declare_landmarks(self)})
        p = declare(self, NODE_PARAMS)
        self.frame_id = p['trinocular.frame_id']
        n_cams, n_lm = len(self.cfg.cameras), len(self.cfg.landmark_names)
        self.silence = [Silence() for _ in range(n_cams)]
        self.sync = FrameSync(n_cams, **self.sync_settings(p))
        self.pixel_noise = PixelNoise()
        self.use(p)
        self.pose_pub = self.create_publisher(PoseStamped, 'ground/pose', 10)
        self.pose_cov_pub = self.create_publisher(PoseWithCovarianceStamped, 'ground/pose_cov', 10)
        self.landmarks_pub = self.create_publisher(PolygonStamped, 'ground/landmarks', 10)
        for k, cam in enumerate(self.cfg.cameras if subscribe else []):
            self.create_subscription(PolygonStamped, f'{cam.name}/landmarks',
                                     lambda msg, k=k: self.on_landmarks(k, msg), 10)
        self.counts = dict(frame_sets=0, poses=0, no_pose=0, malformed=0, future=0, errors=0)
        self.reported = dict(future=0, errors=0)
        self.last_error = ''
        self.last = dict(reason='no frame set yet', cameras_used=0, landmarks_used=0,
                         reprojection_px=float('nan'), residual_m=float('nan'),
                         pixel_sigma=float('nan'))
        self.n_lm = n_lm
        self.diag = Diagnostics(self)
        self.create_timer(p['trinocular.diagnostics_period'], self.publish_diagnostics)
        LiveParams(self, NODE_PARAMS, p, self.reconfigure)
        inputs = ', '.join(self.resolve_topic_name(f'{cam.name}/landmarks')
                           for cam in self.cfg.cameras)
        self.get_logger().info(
            f"{inputs} -> {self.resolve_topic_name('ground/pose')} ({self.method} "
            f"triangulation, {self.pose_method} pose, at least {p['trinocular.min_cameras']} "
            'cameras)')

    def sync_settings(self, p: dict) -> dict:
        """FrameSync's settings from the parameters; ParameterError names a bad one."""
        n_cams = len(self.cfg.cameras)
        if p['trinocular.min_cameras'] > n_cams:
            raise ParameterError(f'trinocular.min_cameras: expected <= {n_cams} (cameras.names)')
        return dict(tolerance_ns=int(p['trinocular.sync_tolerance'] * 1e9),
                    max_wait_ns=int(p['trinocular.max_wait'] * 1e9),
                    min_sources=p['trinocular.min_cameras'],
                    restart_after_ns=int(p['trinocular.restart_after'] * 1e9))

    def use(self, p: dict) -> None:
        """The node's own settings."""
        self.method, self.pose_method = p['trinocular.method'], p['trinocular.pose_method']
        self.max_reproj = p['trinocular.max_reprojection_px']
        self.min_conf = p['trinocular.min_confidence']
        self.pixel_noise.floor = p['trinocular.pixel_sigma_floor']
        self.bias_sigma = p['trinocular.bias_sigma']
        limits = InputLimits.of(p, 'trinocular')
        self.future_tolerance_ns = int(limits.future_tolerance_s * 1e9)
        for silence in self.silence:
            silence.warn_after_s, silence.error_after_s = limits.warn_after_s, limits.error_after_s

    def reconfigure(self, p: dict, changed: set[str]) -> Callable[[], None]:
        """Checked parameters set at run time -> what makes them take effect; the
        synchroniser keeps the landmarks it holds."""
        settings = self.sync_settings(p)

        def apply() -> None:
            for name, value in settings.items():
                setattr(self.sync, name, value)
            self.use(p)
        return apply

    def on_landmarks(self, k: int, msg: PolygonStamped) -> None:
        self.silence[k].heard()
        pts = polygon_to_array(msg)
        if len(pts) != self.n_lm:
            self.counts['malformed'] += 1
            self.get_logger().warn(
                f'{self.cfg.cameras[k].name}/landmarks: {len(pts)} points, expected {self.n_lm}'
                ' (landmarks.names); skipped', throttle_duration_sec=5.0)
            return
        stamp = stamp_to_ns(msg.header.stamp) - self.cfg.latency_ns(k)   # the instant seen
        if self.from_the_future(k, stamp):
            return
        seen = np.isfinite(pts).all(axis=1) & (pts[:, 2] >= self.min_conf)
        pixels = np.where(seen[:, None], pts[:, :2], np.nan)
        restarts = self.sync.restarts
        frame_sets = self.sync.add(k, stamp, pixels)
        if self.sync.restarts != restarts:
            self.get_logger().warn(f'time went back (a new replay?): {self.cfg.cameras[k].name}'
                                   '/landmarks older than its last; frame sets restarted')
        for frame_set in frame_sets:
            self.process_guarded(frame_set)

    def from_the_future(self, k: int, stamp: int) -> bool:
        """True (counted, logged) if camera k's stamp is too far ahead of the node's clock."""
        now = self.get_clock().now().nanoseconds
        if not ahead_of_clock(stamp, now, self.future_tolerance_ns):
            return False
        self.counts['future'] += 1
        self.get_logger().warn(
            f'{self.cfg.cameras[k].name}/landmarks: stamped {(stamp - now) * 1e-9:.3f} s '
            'ahead of the clock; skipped', throttle_duration_sec=5.0)
        return True

    def process_guarded(self, frame_set) -> None:
        """process(), a raised exception counted (errors), logged and skipped."""
        try:
            self.process(frame_set)
        except Exception as err:        # counted, logged and in the diagnostics
            self.counts['errors'] += 1
            self.last_error = error_text(err)
            self.get_logger().error(f'frame set stamped {frame_set.stamp_ns * 1e-9:.3f} s '
                                    f'failed: {self.last_error}; skipped',
                                    throttle_duration_sec=5.0)

    def process(self, frame_set) -> None:
        """Triangulate and solve one frame set; the pose goes out first, the rest after it."""
        self.counts['frame_sets'] += 1
        absent = np.full((self.n_lm, 2), np.nan)
        pixels = np.stack([absent if item is None else item for item in frame_set.items])
        tri = triangulate(self.cfg.cameras, pixels, method=self.method,
                          max_reproj_px=self.max_reproj)
        pose = solve_pose(self.cfg.layout, tri.points, method=self.pose_method)
        header = Header(stamp=ns_to_stamp(frame_set.stamp_ns), frame_id=self.frame_id)
        sigma = self.pixel_noise.update(tri)
        if pose.ok:
            self.pose_pub.publish(pose_to_msg(pose.position, pose.quaternion, header))
            if self.pose_cov_pub.get_subscription_count():
                cov = pose_covariance(self.cfg.layout, pose,
                                      landmark_covariances(self.cfg.cameras, tri, sigma),
                                      yaw_only=pose.method == 'yaw', bias_sigma=self.bias_sigma)
                self.pose_cov_pub.publish(pose_cov_to_msg(pose.position, pose.quaternion, cov,
                                                          header))
        else:
            self.get_logger().warn(f'no pose: {pose.reason}', throttle_duration_sec=5.0)
        self.counts['poses' if pose.ok else 'no_pose'] += 1
        self.landmarks_pub.publish(points_to_polygon(tri.points, header))
        finite = np.isfinite(tri.reproj_px)
        self.last = dict(reason=pose.reason if not pose.ok else '',
                         cameras_used=frame_set.n_present, landmarks_used=pose.n_used,
                         reprojection_px=float(np.mean(tri.reproj_px[finite])) if finite.any()
                         else float('nan'),
                         residual_m=pose.residual_rms, pixel_sigma=sigma)

    def input_problems(self) -> str:
        """Landmarks dropped as future, frame sets failed, since the last call."""
        new = {k: self.counts[k] - n for k, n in self.reported.items()}
        self.reported = {k: self.counts[k] for k in self.reported}
        problems = []
        if new['future']:
            problems.append(f"{new['future']} landmarks messages stamped in the future dropped")
        if new['errors']:
            problems.append(f"{new['errors']} frame sets failed: {self.last_error}")
        return '; '.join(problems)

    def publish_diagnostics(self) -> None:
        if self.last['reason']:
            level, message = (WARN if self.counts['poses'] else ERROR), self.last['reason']
        else:
            level, message = OK, 'pose ok'
        if problems := self.input_problems():
            level, message = max(level, WARN), f'{message}; {problems}'
        level, message = self.judge_silence(level, message)
        self.diag.publish(level, message, {**self.counts, **self.last,
                                           'sync_dropped': self.sync.dropped,
                                           'restarts': self.sync.restarts})

    def judge_silence(self, level: int, message: str) -> tuple[int, str]:
        """WARN while a camera is silent too long; ERROR when every camera is past the
        error bound."""
        levels = [s.level() for s in self.silence]
        silent = [f'{cam.name} {s.silent_s():.1f} s' for cam, s, lv
                  in zip(self.cfg.cameras, self.silence, levels) if lv != OK]
        if not silent:
            return level, message
        worst = ERROR if all(lv == ERROR for lv in levels) else WARN
        return max(level, worst), f"no landmarks from {', '.join(silent)}; {message}"


def main(args: list[str] | None = None) -> None:
    run(TrinocularPoseNode, 'trinocular_pose_node', args)


if __name__ == '__main__':
    main()
