"""Write a rosbag2 (MCAP) of the simulated ground trinocular system (chapter section 3).

For every frame set (one header stamp shared by all its messages):

    camK/image_raw/compressed   sensor_msgs/msg/CompressedImage  JPEG, frame camK_optical
    camK/camera_info            sensor_msgs/msg/CameraInfo       the calibration (eq 15-16)
    truth/pose                  geometry_msgs/msg/PoseStamped    base_link in world (ENU)

Topic names are stored relative, as the nodes use them, so a player resolves them in
its own namespace.

Usage: make_ground_bag --out bags/ground_trinocular [--config ...] [--rate 10]
       [--duration 8] [--seed 0] [--quality 85] [--force]
"""
import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from uav_vs.sim.ground_scene import GroundScene, Pose, figure_eight
from uav_vs.vision.body_pose import quaternion_xyzw
from uav_vs.vision.camera import CalibrationError, Camera
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file

START_NS = 1_700_000_000 * 10**9     # first header stamp (a fixed date, so bags are repeatable)
TYPES = get_typestore(Stores.ROS2_JAZZY)
T = TYPES.types


def write_bag(out: Path, scene: GroundScene, rate: float, duration: float,
              quality: int = 85) -> int:
    """Render `duration` s of the figure-eight at `rate` Hz into an MCAP bag; returns the
    number of frame sets written."""
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        image_conn, info_conn = [], []
        for cam in scene.cameras:
            image_conn.append(writer.add_connection(f'{cam.name}/image_raw/compressed',
                                                    'sensor_msgs/msg/CompressedImage',
                                                    typestore=TYPES))
            info_conn.append(writer.add_connection(f'{cam.name}/camera_info',
                                                   'sensor_msgs/msg/CameraInfo', typestore=TYPES))
        truth_conn = writer.add_connection('truth/pose', 'geometry_msgs/msg/PoseStamped',
                                           typestore=TYPES)
        n = int(round(duration * rate))
        for i in range(n):
            stamp_ns = START_NS + round(i * 1e9 / rate)
            pose = figure_eight(i / rate)
            images, _ = scene.render(pose)
            for cam, img, ic, cc in zip(scene.cameras, images, image_conn, info_conn):
                _, jpeg = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, quality])
                msg = T['sensor_msgs/msg/CompressedImage'](
                    _header(stamp_ns, cam.frame_id), 'jpeg', jpeg.ravel())
                writer.write(ic, stamp_ns, TYPES.serialize_cdr(msg, msg.__msgtype__))
                info = camera_info(cam, stamp_ns)
                writer.write(cc, stamp_ns, TYPES.serialize_cdr(info, info.__msgtype__))
            truth = pose_stamped(pose, stamp_ns)
            writer.write(truth_conn, stamp_ns, TYPES.serialize_cdr(truth, truth.__msgtype__))
    return n


def camera_info(cam: Camera, stamp_ns: int) -> object:
    """sensor_msgs/msg/CameraInfo of a calibration (rosbags message object)."""
    f = cam.camera_info_fields()
    roi = T['sensor_msgs/msg/RegionOfInterest'](0, 0, 0, 0, False)
    return T['sensor_msgs/msg/CameraInfo'](
        _header(stamp_ns, cam.frame_id), f['height'], f['width'], f['distortion_model'],
        np.array(f['d'], np.float64), np.array(f['k'], np.float64),
        np.array(f['r'], np.float64), np.array(f['p'], np.float64), 0, 0, roi)


def pose_stamped(pose: Pose, stamp_ns: int) -> object:
    """geometry_msgs/msg/PoseStamped of base_link in `world` (rosbags message object)."""
    x, y, z = pose.position
    q = quaternion_xyzw(pose.R)
    return T['geometry_msgs/msg/PoseStamped'](
        _header(stamp_ns, 'world'),
        T['geometry_msgs/msg/Pose'](T['geometry_msgs/msg/Point'](x, y, z),
                                    T['geometry_msgs/msg/Quaternion'](*q)))


def _header(stamp_ns: int, frame_id: str) -> object:
    sec, nanosec = divmod(stamp_ns, 10**9)
    return T['std_msgs/msg/Header'](T['builtin_interfaces/msg/Time'](sec, nanosec), frame_id)


def main(argv: list[str] | None = None) -> int:
    """make_ground_bag: render the figure-eight and write the bag; 0 on success, 2 on bad
    arguments or configuration (one line on stderr naming the problem)."""
    parser = argparse.ArgumentParser(prog='make_ground_bag',
                                     description=__doc__.splitlines()[0])
    parser.add_argument('--config', type=Path, default=default_config_path(),
                        help='params file with cameras.* and landmarks.* (default: %(default)s)')
    parser.add_argument('--out', type=Path, default=Path('bags/ground_trinocular'),
                        help='bag directory to create (default: %(default)s)')
    parser.add_argument('--rate', type=float, default=10.0, help='frame sets per second')
    parser.add_argument('--duration', type=float, default=8.0, help='seconds of flight')
    parser.add_argument('--seed', type=int, default=0, help='sensor noise seed')
    parser.add_argument('--quality', type=int, default=85, help='JPEG quality 1..100')
    parser.add_argument('--background', default='aero1.jpg',
                        help='ground photograph in uav_vs/sim/assets (default: %(default)s)')
    parser.add_argument('--force', action='store_true', help='replace an existing bag at --out')
    args = parser.parse_args(argv)
    if not args.rate > 0 or not args.duration > 0 or not 1 <= args.quality <= 100:
        parser.error('--rate and --duration must be > 0, --quality in 1..100')
    try:
        config = load_ground_config(read_params_file(args.config))
    except (OSError, CalibrationError) as exc:
        print(f'make_ground_bag: {args.config}: {exc}', file=sys.stderr)
        return 2
    if args.out.exists() and not (args.force and (args.out / 'metadata.yaml').exists()):
        print(f'make_ground_bag: --out {args.out} exists (pass --force to replace a bag)',
              file=sys.stderr)
        return 2
    try:
        scene = GroundScene(config, background=args.background, seed=args.seed)
    except OSError as exc:
        print(f'make_ground_bag: --background: {exc}', file=sys.stderr)
        return 2
    if args.out.exists():
        shutil.rmtree(args.out)
    n = write_bag(args.out, scene, args.rate, args.duration, args.quality)
    size = sum(p.stat().st_size for p in args.out.iterdir()) / 1e6
    print(f'{args.out}: {n} frame sets x {len(config.cameras)} cameras, {size:.1f} MB')
    return 0


if __name__ == '__main__':
    sys.exit(main())
