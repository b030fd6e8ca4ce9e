"""trinocular_pose_node: vehicle pose from the ground cameras' landmark centroids (section 3.1.1).

Subscribes `<camera>/landmarks` (geometry_msgs/PolygonStamped, one point per
landmark in `landmarks.names` order: x, y = raw pixel centroid, z = confidence,
NaN when not found) for every camera in `cameras.names`; synchronises them by stamp;
triangulates (eq 24-25) and solves yaw + position (eq 26).
Publishes `ground/pose` (PoseStamped, `world` ENU), `ground/landmarks`
(PolygonStamped, 3D landmark positions in `world`, NaN where not triangulated) and
/diagnostics.
"""
import numpy as np
from geometry_msgs.msg import PolygonStamped, PoseStamped
from std_msgs.msg import Header

from uav_vs.ros.convert import (ns_to_stamp, points_to_polygon, polygon_to_array, pose_to_msg,
                                stamp_to_ns)
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, QuietPublisherNode, run
from uav_vs.ros.params import Param, T, declare
from uav_vs.vision.body_pose import solve_pose
from uav_vs.vision.frame_sync import FrameSync
from uav_vs.vision.ground_config import load_ground_config
from uav_vs.vision.triangulation import triangulate

from uav_vs.ros.ground_params import declare_cameras, declare_landmarks

NODE_PARAMS = [
    Param('trinocular.method', T.STRING, 'lsq', 'triangulation: lsq (eq 24-25) or opencv (DLT)',
          choices=('lsq', 'opencv')),
    Param('trinocular.pose_method', T.STRING, 'yaw',
          'yaw: eq 26 (pitch, roll ~ 0); rigid: full 6-DoF SVD alignment', choices=('yaw', 'rigid')),
    Param('trinocular.sync_tolerance', T.DOUBLE, 0.010,
          'max stamp difference between cameras in one frame set, s', 0.0, 1.0),
    Param('trinocular.max_wait', T.DOUBLE, 0.2,
          'release a frame set without a silent camera after this long, s', 0.0, 10.0),
    Param('trinocular.min_cameras', T.INTEGER, 2, 'cameras needed for a frame set', 2, 64),
    Param('trinocular.max_reprojection_px', T.DOUBLE, 3.0,
          'a landmark reprojecting worse than this drops its worst camera, px', 0.1, 1000.0),
    Param('trinocular.min_confidence', T.DOUBLE, 0.0,
          'centroids with a lower confidence are ignored', 0.0, 1.0),
    Param('trinocular.frame_id', T.STRING, 'world', 'frame of the published pose (ENU)'),
    Param('trinocular.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.05, 60.0),
]


class TrinocularPoseNode(QuietPublisherNode):
    def __init__(self) -> None:
        super().__init__('trinocular_pose_node')
        self.cfg = load_ground_config({**declare_cameras(self), **declare_landmarks(self)})
        p = declare(self, NODE_PARAMS)
        self.method, self.pose_method = p['trinocular.method'], p['trinocular.pose_method']
        self.max_reproj = p['trinocular.max_reprojection_px']
        self.min_conf = p['trinocular.min_confidence']
        self.frame_id = p['trinocular.frame_id']
        n_cams, n_lm = len(self.cfg.cameras), len(self.cfg.landmark_names)
        if p['trinocular.min_cameras'] > n_cams:
            raise ValueError(f'trinocular.min_cameras: expected <= {n_cams} (cameras.names)')
        self.sync = FrameSync(n_cams, int(p['trinocular.sync_tolerance'] * 1e9),
                              int(p['trinocular.max_wait'] * 1e9), p['trinocular.min_cameras'])
        self.pose_pub = self.create_publisher(PoseStamped, 'ground/pose', 10)
        self.landmarks_pub = self.create_publisher(PolygonStamped, 'ground/landmarks', 10)
        for k, cam in enumerate(self.cfg.cameras):
            self.create_subscription(PolygonStamped, f'{cam.name}/landmarks',
                                     lambda msg, k=k: self.on_landmarks(k, msg), 10)
        self.counts = dict(frame_sets=0, poses=0, no_pose=0, malformed=0)
        self.last = dict(reason='no frame set yet', cameras_used=0, landmarks_used=0,
                         reprojection_px=float('nan'), residual_m=float('nan'))
        self.n_lm = n_lm
        self.diag = Diagnostics(self)
        self.create_timer(p['trinocular.diagnostics_period'], self.publish_diagnostics)

    def on_landmarks(self, k: int, msg: PolygonStamped) -> None:
        pts = polygon_to_array(msg)
        if len(pts) != self.n_lm:
            self.counts['malformed'] += 1
            self.get_logger().warn(
                f'{self.cfg.cameras[k].name}/landmarks: {len(pts)} points, expected {self.n_lm}'
                ' (landmarks.names); skipped', throttle_duration_sec=5.0)
            return
        seen = np.isfinite(pts).all(axis=1) & (pts[:, 2] >= self.min_conf)
        pixels = np.where(seen[:, None], pts[:, :2], np.nan)
        for frame_set in self.sync.add(k, stamp_to_ns(msg.header.stamp), pixels):
            self.process(frame_set)

    def process(self, frame_set) -> None:
        """Triangulate and solve one frame set; the pose goes out first, the rest after it."""
        self.counts['frame_sets'] += 1
        absent = np.full((self.n_lm, 2), np.nan)
        pixels = np.stack([absent if item is None else item for item in frame_set.items])
        tri = triangulate(self.cfg.cameras, pixels, method=self.method,
                          max_reproj_px=self.max_reproj)
        pose = solve_pose(self.cfg.layout, tri.points, method=self.pose_method)
        header = Header(stamp=ns_to_stamp(frame_set.stamp_ns), frame_id=self.frame_id)
        if pose.ok:
            self.pose_pub.publish(pose_to_msg(pose.position, pose.quaternion, header))
        self.counts['poses' if pose.ok else 'no_pose'] += 1
        self.landmarks_pub.publish(points_to_polygon(tri.points, header))
        finite = np.isfinite(tri.reproj_px)
        self.last = dict(reason=pose.reason if not pose.ok else '',
                         cameras_used=frame_set.n_present, landmarks_used=pose.n_used,
                         reprojection_px=float(np.mean(tri.reproj_px[finite])) if finite.any()
                         else float('nan'),
                         residual_m=pose.residual_rms)

    def publish_diagnostics(self) -> None:
        if self.last['reason']:
            level, message = (WARN if self.counts['poses'] else ERROR), self.last['reason']
        else:
            level, message = OK, 'pose ok'
        self.diag.publish(level, message, {**self.counts, **self.last,
                                           'sync_dropped': self.sync.dropped})


def main(args: list[str] | None = None) -> None:
    run(TrinocularPoseNode, 'trinocular_pose_node', args)


if __name__ == '__main__':
    main()
