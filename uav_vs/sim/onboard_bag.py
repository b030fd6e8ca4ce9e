"""make_onboard_bag: a rosbag2 (MCAP) of the simulated onboard camera with ground truth.

The down-looking camera of config/onboard.yaml flies `Trajectory` (take-off hover at
1 m, climb to 3 m, move and turn, descend) over the aerial-photo ground plane of
`OnboardScene`. Every frame writes, with the same stamp:

- `onboard/image_raw/compressed` sensor_msgs/msg/CompressedImage, JPEG, frame
  `onboard_camera_optical` (camera.frame_id)
- `onboard/camera_info`          sensor_msgs/msg/CameraInfo (plumb bob)
- `truth/pose`                   geometry_msgs/msg/PoseStamped, frame `world`: base_link

With `--follow` the camera instead flies above the target of the follow scenario
(`assets/box.png`, 0.4 m wide, driving round a 0.4 m circle at 8 cm/s:
uav_vs.sim.ground_target), which every frame shows, and writes its truth too:

- `truth/target`                 geometry_msgs/msg/PoseStamped, frame `world`: its centre
                                 on the ground (z = 0), heading as yaw

Written with the pure-Python `rosbags` library (no ROS needed):
    make_onboard_bag --out bags/onboard --rate 15 --duration 10 --seed 0
    make_onboard_bag --follow --out bags/onboard_follow --rate 10 --duration 10 --seed 0
"""
import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from uav_vs.sim.ground_target import CirclePath, GroundTarget
from uav_vs.sim.onboard_scene import ASSETS, OnboardScene, Trajectory, fly, following
from uav_vs.vision.camera import CalibrationError
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config

START_NS = 1_700_000_000 * 10**9     # stamp of the first frame
TOPICS = {'image': ('onboard/image_raw/compressed', 'sensor_msgs/msg/CompressedImage'),
          'info': ('onboard/camera_info', 'sensor_msgs/msg/CameraInfo'),
          'truth': ('truth/pose', 'geometry_msgs/msg/PoseStamped'),
          'target': ('truth/target', 'geometry_msgs/msg/PoseStamped')}
FOLLOW_DURATION = 10.0    # s of the --follow flight when no --duration is given


def follow_target() -> GroundTarget:
    """The target of the follow scenario (sim_world's ground_target defaults)."""
    return GroundTarget(cv2.imread(str(ASSETS / 'box.png')), 0.4, CirclePath())


def default_config() -> Path:
    """config/onboard.yaml of the source tree, else of the installed share directory."""
    for base in (Path(__file__).resolve().parents[2], Path(sys.prefix) / 'share' / 'uav_vs'):
        if (base / 'config' / 'onboard.yaml').is_file():
            return base / 'config' / 'onboard.yaml'
    return Path('config/onboard.yaml')


def write_bag(out: Path, config: Path, rate: float, duration: float | None, seed: int,
              quality: int = 90, follow: bool = False) -> int:
    """Render and write the bag (`follow`: above the moving target); return the number of
    frames."""
    cfg = load_onboard_config(read_params_file(config))
    cam = cfg.camera
    scene = OnboardScene(cam, cfg.camera_to_body, seed=seed)
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    Time, Header = T['builtin_interfaces/msg/Time'], T['std_msgs/msg/Header']
    info = cam.camera_info_fields()
    roi = T['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                do_rectify=False)
    target = follow_target() if follow else None
    trajectory = Trajectory() if target is None else \
        following(target, FOLLOW_DURATION if duration is None else duration)
    topics = {k: v for k, v in TOPICS.items() if k != 'target' or follow}
    frames = 0
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {k: writer.add_connection(topic, msgtype, typestore=ts)
                 for k, (topic, msgtype) in topics.items()}
        for t, image, R_wb, p_wb in fly(scene, trajectory, rate, duration, target):
            ns = START_NS + int(round(t * 1e9))
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            ok, jpeg = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, quality])
            msgs = {
                'image': T[TOPICS['image'][1]](header=Header(stamp=stamp, frame_id=cam.frame_id),
                                               format='jpeg', data=jpeg.ravel()),
                'info': T[TOPICS['info'][1]](
                    header=Header(stamp=stamp, frame_id=cam.frame_id), height=info['height'],
                    width=info['width'], distortion_model=info['distortion_model'],
                    d=np.array(info['d']), k=np.array(info['k']), r=np.array(info['r']),
                    p=np.array(info['p']), binning_x=0, binning_y=0, roi=roi),
                'truth': _pose(T, Header(stamp=stamp, frame_id='world'), R_wb, p_wb),
            }
            if target is not None:
                (x, y), heading = target.path.pose(t)
                msgs['target'] = _pose(T, Header(stamp=stamp, frame_id='world'),
                                       Rotation.from_euler('z', heading).as_matrix(),
                                       np.array([x, y, 0.0]))
            for key, msg in msgs.items():
                writer.write(conns[key], ns, ts.serialize_cdr(msg, TOPICS[key][1]))
            frames += 1
    return frames


def _pose(T: dict, header: object, R_wb: np.ndarray, p_wb: np.ndarray) -> object:
    x, y, z, w = Rotation.from_matrix(R_wb).as_quat()
    pose = T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=float(p_wb[0]), y=float(p_wb[1]), z=float(p_wb[2])),
        orientation=T['geometry_msgs/msg/Quaternion'](x=x, y=y, z=z, w=w))
    return T['geometry_msgs/msg/PoseStamped'](header=header, pose=pose)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog='make_onboard_bag', description=__doc__.split('\n')[0])
    ap.add_argument('--config', type=Path, default=default_config(),
                    help='onboard params file (camera, mounting); default config/onboard.yaml')
    ap.add_argument('--out', type=Path, default=Path('bags/onboard'),
                    help='bag directory to create')
    ap.add_argument('--rate', type=float, default=15.0, help='frame rate, Hz')
    ap.add_argument('--duration', type=float, default=None,
                    help='seconds from the start (default: the whole 10 s trajectory)')
    ap.add_argument('--seed', type=int, default=0, help='sensor-noise seed')
    ap.add_argument('--quality', type=int, default=90, help='JPEG quality 1..100')
    ap.add_argument('--follow', action='store_true',
                    help='fly above the moving target of the follow scenario (truth/target)')
    ap.add_argument('--overwrite', action='store_true', help='replace an existing --out')
    args = ap.parse_args(argv)
    if not args.rate > 0:
        ap.error(f'--rate: expected a positive number, got {args.rate}')
    if args.duration is not None and not args.duration >= 0:
        ap.error(f'--duration: expected a non-negative number, got {args.duration}')
    if not 1 <= args.quality <= 100:
        ap.error(f'--quality: expected 1..100, got {args.quality}')
    if not args.config.is_file():
        ap.error(f'--config: no such file {args.config}')
    if args.out.exists():
        if not args.overwrite:
            ap.error(f'--out: {args.out} exists (use --overwrite to replace it)')
        shutil.rmtree(args.out)
    try:
        n = write_bag(args.out, args.config, args.rate, args.duration, args.seed, args.quality,
                      args.follow)
    except (CalibrationError, ValueError) as exc:
        sys.exit(f'make_onboard_bag: {args.config}: {exc}')
    size = sum(f.stat().st_size for f in args.out.iterdir())
    print(f'{args.out}: {n} frames x {4 if args.follow else 3} topics, {size / 1e6:.1f} MB')


if __name__ == '__main__':
    main()
