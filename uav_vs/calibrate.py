"""uav_vs_calibrate: calibrate real cameras from images of a board (uav_vs.vision.calibration).

Intrinsics of one camera from images, folders of images or videos of a chessboard, a
ChArUco board or a circle grid:

    uav_vs_calibrate intrinsics --board board.yaml --name cam1 cam1_images/
    uav_vs_calibrate intrinsics --kind charuco --rows 5 --cols 4 --square 0.054 \\
        --marker 0.0405 --dictionary DICT_4X4_1000 --inverted --every 3 cam1.mp4
    uav_vs_calibrate intrinsics --kind circles --rows 6 --cols 6 --square 0.034 \\
        --model k1 --out calibration/ circles-*.jpg

writes `<out>/<name>.yaml`, the camera_info file ROS camera drivers load
(camera_calibration's format, read by camera_info_manager), and `<out>/<name>_report.txt`,
and prints the report: K, D, the RMS reprojection error of the whole and of each view,
the views dropped and why (blurred, too oblique, outliers), the image coverage.
The poses of a rig of cameras filming the board together, in the world frame of one
view where the board lies on the ground (REP-103: x along the board's first row, z up):

    uav_vs_calibrate rig --board board.yaml --camera cam1=cam1.mp4 --camera cam2=cam2.mp4 \\
        --camera cam3=cam3.mp4 --intrinsics calibration/ --ground 0

matches the cameras' frames by index (or by a `--sync` CSV of sync_index, camera,
frame_index), solves every camera's R, t (uav_vs.vision.rig_calibration), with
`--latency` (and a frame_time column in the CSV) each camera's latency after the first's
too (uav_vs.vision.rig_timing), and writes
`<out>/cameras.yaml`, the `cameras` block of config/ground_trinocular.yaml, and
`<out>/rig_report.txt`.

The landmarks' positions on the vehicle and their colour samples, from frames of the
calibrated rig with the vehicle standing still at a placement the user chooses (its body
origin in the world and its heading, deg counter-clockwise from east):

    uav_vs_calibrate landmarks --config config/ground_trinocular.yaml \\
        --cameras calibration/cameras.yaml --camera cam1=still1/ --camera cam2=still2/ \\
        --camera cam3=still3/ --placement 1.0 0.5 0.25 90 --out calibration/

finds each landmark by the configured colour ranges (uav_vs.vision.landmark_survey),
triangulates it, and writes `<out>/landmarks.yaml`, the `landmarks` block of
config/ground_trinocular.yaml with `position` in base_link and `sample`, the images
`<out>/<name>.png` it cut, `<out>/landmarks_report.txt`, and the ground station's params
file ready to fly: the `--config` file with the cameras of `--cameras` and these
landmarks, under the same name in `<out>`.

Bad input (no board found, too few views, images of different sizes, a file that is
neither an image nor a decodable video, a camera that never shares a view with the
others) stops it with one line and exit status 2.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np
import yaml

# FFmpeg's own messages (a file that is no video) would come before our one line.
os.environ.setdefault('OPENCV_FFMPEG_LOGLEVEL', '-8')

from uav_vs.vision.calibration import (BOARD_KINDS, MODELS, Board,  # noqa: E402
                                       CalibrationInputError, Limits, calibrate_camera,
                                       camera_info_yaml, detect_all, read_camera_info,
                                       read_images)
from uav_vs.vision.colour_model import models_from_params  # noqa: E402
from uav_vs.vision.ground_config import (flat_params, load_ground_config,  # noqa: E402
                                         read_params_file)
from uav_vs.vision.landmark_survey import (Placement, SurveyError,  # noqa: E402
                                           detector_params, survey)
from uav_vs.vision.rig_calibration import calibrate_rig  # noqa: E402
from uav_vs.vision.rig_timing import calibrate_timed_rig, frame_gap, set_instants  # noqa: E402

EPILOG = """examples:
  uav_vs_calibrate intrinsics --board board.yaml --name cam1 cam1_images/
  uav_vs_calibrate intrinsics --kind charuco --rows 5 --cols 4 --square 0.054 \\
      --marker 0.0405 --dictionary DICT_4X4_1000 --inverted --every 3 cam1.mp4
  uav_vs_calibrate intrinsics --kind circles --rows 6 --cols 6 --square 0.034 \\
      --model k1 circles-01.jpg circles-02.jpg circles-03.jpg
  uav_vs_calibrate rig --board board.yaml --camera cam1=cam1.mp4 --camera cam2=cam2.mp4 \\
      --camera cam3=cam3.mp4 --intrinsics calibration/ --ground 0
  uav_vs_calibrate landmarks --config config/ground_trinocular.yaml \\
      --cameras calibration/cameras.yaml --camera cam1=still1/ --camera cam2=still2/ \\
      --camera cam3=still3/ --placement 1.0 0.5 0.25 90

board.yaml: kind (chessboard, charuco, circles, acircles), rows, cols (squares of a
chessboard or ChArUco board, circles of a grid), square (m: the side of a square, or
the circles' spacing), and for charuco marker (m), dictionary, inverted (true when
printed white on black)."""


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog='uav_vs_calibrate', description='Calibrate cameras from images of a board.',
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG)
    commands = top.add_subparsers(dest='command', required=True)
    intr = commands.add_parser(
        'intrinsics', help='K and D of one camera',
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description='K and lens distortion D of one camera from board images or videos.')
    intr.add_argument('inputs', nargs='+', type=Path,
                      help='image files, folders of images, or videos')
    _board_arguments(intr)
    intr.add_argument('--model', choices=MODELS, default='plumb_bob',
                      help='distortion model (default plumb_bob)')
    intr.add_argument('--name', default='camera', help='camera name (default camera)')
    intr.add_argument('--every', type=int, default=1, help='of a video, every N-th frame')
    intr.add_argument('--blur-ratio', type=float, default=Limits.blur_ratio,
                      help="views whose board is less sharp (the Laplacian's variance) than "
                           "this times the views' median are dropped as blurred (default "
                           "%(default)s; 0 keeps every view)")
    intr.add_argument('--max-tilt', type=float, default=Limits.max_tilt_deg,
                      help='views of a board turned further from the camera are dropped, '
                           'deg (default %(default)s)')
    intr.add_argument('--out', type=Path, default=Path('calibration'),
                      help='output folder (default calibration)')
    rig = commands.add_parser(
        'rig', help='R, t of cameras that film the board together',
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="The poses of two or more calibrated cameras in the world frame of a "
                    "view where the board lies on the ground.")
    _board_arguments(rig)
    rig.add_argument('--camera', action='append', required=True, metavar='NAME=PATH',
                     help="a camera's video or folder of images (once per camera; the "
                          "first is the reference)")
    rig.add_argument('--intrinsics', type=Path, required=True,
                     help='the folder of the cameras\' camera_info files (<name>.yaml)')
    rig.add_argument('--sync', type=Path, help='CSV of sync_index, camera, frame_index '
                     '(and frame_time, s): which frames were taken together (default: the '
                     'same frame index)')
    rig.add_argument('--latency', action='store_true',
                     help="measure each camera's latency after the first's while the board "
                          "moves (cameras not triggered together; needs --sync with "
                          "frame_time) and match their frames by the instant they show")
    rig.add_argument('--ground', type=int, required=True,
                     help='the sync index (frame) in which the board lies on the ground')
    rig.add_argument('--out', type=Path, default=Path('calibration'),
                     help='output folder (default calibration)')
    marks = commands.add_parser(
        'landmarks', help="the landmarks' positions on the vehicle and colour samples",
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Triangulate each landmark of the vehicle standing still before the "
                    "calibrated rig, in the body frame its placement defines, and cut its "
                    "colour sample.")
    marks.add_argument('--config', type=Path, required=True,
                       help='params file with the landmarks (names, hue, saturation, value) '
                            'and camshift settings, e.g. config/ground_trinocular.yaml')
    marks.add_argument('--cameras', type=Path,
                       help="the rig's cameras.yaml (uav_vs_calibrate rig); default: the "
                            "config's cameras")
    marks.add_argument('--camera', action='append', required=True, metavar='NAME=PATH',
                       help="a camera's still frames: images, a folder or a video (once per "
                            "camera, two or more)")
    marks.add_argument('--placement', type=float, nargs=4, required=True,
                       metavar=('X', 'Y', 'Z', 'YAW'),
                       help="base_link's origin in the world (ENU, m) and its heading (deg, "
                            "counter-clockwise from east) as the vehicle stands")
    marks.add_argument('--every', type=int, default=1, help='of a video, every N-th frame')
    marks.add_argument('--out', type=Path, default=Path('calibration'),
                       help='output folder (default calibration)')
    return top


def _board_arguments(command: argparse.ArgumentParser) -> None:
    board = command.add_argument_group('the board (a YAML file, or these flags)')
    board.add_argument('--board', type=Path, help='board YAML (kind, rows, cols, square, ...)')
    board.add_argument('--kind', choices=BOARD_KINDS)
    board.add_argument('--rows', type=int, help='squares (chessboard, charuco) or circles')
    board.add_argument('--cols', type=int, help='squares (chessboard, charuco) or circles')
    board.add_argument('--square', type=float, help='square side or circle spacing, m')
    board.add_argument('--marker', type=float, default=0.0, help='ChArUco marker side, m')
    board.add_argument('--dictionary', default='DICT_4X4_50', help='ChArUco ArUco dictionary')
    board.add_argument('--inverted', action='store_true',
                       help='ChArUco printed white on black')


def board_of(args: argparse.Namespace) -> Board:
    if args.board is not None:
        return Board.load(args.board)
    missing = [flag for flag in ('kind', 'rows', 'cols', 'square')
               if getattr(args, flag) is None]
    if missing:
        raise CalibrationInputError(f'the board: give --board FILE or --{", --".join(missing)}')
    return Board(args.kind, args.rows, args.cols, args.square, args.marker, args.dictionary,
                 args.inverted)


def check_every(args: argparse.Namespace) -> None:
    if args.every < 1:
        raise CalibrationInputError(f'--every: expected a whole number of frames >= 1, got '
                                    f'{args.every}')


def intrinsics(args: argparse.Namespace) -> None:
    check_every(args)
    board = board_of(args)
    found, size, count = detect_all(board, read_images(args.inputs, args.every))
    print(f'{args.name}: the board found in {len(found)} of {count} images', flush=True)
    limits = Limits(blur_ratio=args.blur_ratio, max_tilt_deg=args.max_tilt)
    result = calibrate_camera(board, found, size, args.model, limits)
    report = '\n'.join(result.report(args.name)) + '\n'
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f'{args.name}.yaml').write_text(camera_info_yaml(args.name, result))
    (args.out / f'{args.name}_report.txt').write_text(report)
    print(report + f'wrote {args.out / args.name}.yaml and {args.name}_report.txt')


def rig(args: argparse.Namespace) -> None:
    board = board_of(args)
    sources = {}
    for spec in args.camera:
        name, sep, path = spec.partition('=')
        if not sep or not name or not path:
            raise CalibrationInputError(f'--camera {spec!r}: expected NAME=PATH')
        sources[name] = Path(path)
    sync, stamps = read_sync(args.sync) if args.sync else (None, {})
    if args.latency and not stamps:
        raise CalibrationInputError('--latency needs --sync with a frame_time column (s)')
    detections, intrinsics, tracks = {}, {}, {}
    for name, path in sources.items():
        intrinsics[name] = read_camera_info(args.intrinsics / f'{name}.yaml')
        index: dict[str, int] = {}       # frame index of each image, found or not
        found, size, count = detect_all(board, numbered(read_images([path]), index))
        if size != intrinsics[name].size:
            raise CalibrationInputError(f'{name}: images {size[0]}x{size[1]}, its camera_info '
                                        f'{intrinsics[name].size[0]}x{intrinsics[name].size[1]}')
        frames = {index[key]: det for key, det in found.items()}
        tracks[name] = {stamps[name, f]: det for f, det in frames.items() if (name, f) in stamps}
        if sync is not None:
            frames = {sync[name, f]: det for f, det in frames.items() if (name, f) in sync}
        detections[name] = {str(f): det for f, det in frames.items()}
        print(f'{name}: the board found in {len(found)} of {count} images', flush=True)
    if args.latency:
        ours = {key: when for key, when in stamps.items() if key[0] in sources}
        result = calibrate_timed_rig(board, tracks, set_instants(sync, ours, next(iter(sources))),
                                     intrinsics, str(args.ground), frame_gap(ours))
    else:
        result = calibrate_rig(board, detections, intrinsics, str(args.ground))
    report = '\n'.join(result.report()) + '\n'
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'cameras.yaml').write_text(result.cameras_yaml())
    (args.out / 'rig_report.txt').write_text(report)
    print(report + f'wrote {args.out / "cameras.yaml"} and rig_report.txt')


def landmarks(args: argparse.Namespace) -> None:
    check_every(args)
    try:
        params = read_params_file(args.config)
        if args.cameras is not None:
            params = {k: v for k, v in params.items() if not k.startswith('cameras.')}
            params |= read_cameras_block(args.cameras)
        config = load_ground_config(params)
        detector = detector_params(params)
        models = models_from_params(params, detector.bins)
    except (ValueError, yaml.YAMLError) as err:
        raise CalibrationInputError(f'{args.config}: {err}') from None
    by_name = {c.name: c for c in config.cameras}
    cameras, frames = [], []
    for spec in args.camera:
        name, sep, path = spec.partition('=')
        if not sep or not name or not path:
            raise CalibrationInputError(f'--camera {spec!r}: expected NAME=PATH')
        if name not in by_name:
            raise CalibrationInputError(f'--camera {name}: not a camera of the config '
                                        f'({", ".join(by_name)})')
        cameras.append(by_name[name])
        frames.append([image for _, image in read_images([Path(path)], args.every, True)])
    if len(cameras) < 2:
        raise CalibrationInputError('--camera: two cameras or more are needed')
    x, y, z, yaw = args.placement
    result = survey(cameras, models, detector, frames,
                    Placement(np.array([x, y, z]), math.radians(yaw)))
    args.out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, sample in result.samples.items():
        paths[name] = (args.out / f'{name}.png').resolve()
        cv2.imwrite(str(paths[name]), sample)
    report = '\n'.join(result.report()) + '\n'
    (args.out / 'landmarks.yaml').write_text(result.landmarks_yaml(params, paths))
    (args.out / 'landmarks_report.txt').write_text(report)
    config_out = args.out / args.config.name
    if config_out.resolve() == args.config.resolve():
        config_out = args.out / f'calibrated_{args.config.name}'
    config_out.write_text(calibrated_config(args.config, args.cameras,
                                            result.landmarks_block(params, paths)))
    print(report + f'wrote {args.out / "landmarks.yaml"}, landmarks_report.txt, the '
                   f'samples {", ".join(p.name for p in paths.values())} and {config_out}, '
                   f'the ground station\'s params file with them')


def numbered(images: Iterable[tuple[str, np.ndarray]], index: dict[str, int]
             ) -> Iterator[tuple[str, np.ndarray]]:
    """`images` as they are, noting each one's frame index in `index`: a video frame's
    own ('<video>#<frame>'), else its place among the images."""
    for k, (name, image) in enumerate(images):
        index[name] = int(name.rpartition('#')[2]) if '#' in name else k
        yield name, image


def calibrated_config(config: Path, cameras: Path | None, landmarks_block: dict) -> str:
    """The ground params file `config` with the cameras block of `cameras` (as `rig`
    writes it; None keeps the config's own) and `landmarks_block`: ready for the ground
    station's nodes (`--params-file`)."""
    doc = yaml.safe_load(config.read_text())
    params = doc['/**']['ros__parameters']
    if cameras is not None:
        params['cameras'] = yaml.safe_load(cameras.read_text())['cameras']
    params['landmarks'] = landmarks_block
    return (f'# {config.name} with the cameras calibrated and the landmarks surveyed by\n'
            f'# uav_vs_calibrate; every key is documented in {config.name} as shipped.\n'
            + yaml.safe_dump(doc, sort_keys=False, width=100))


def read_cameras_block(path: Path) -> dict[str, object]:
    """Flat `cameras.*` parameters of a file holding a `cameras` block (as `rig` writes)."""
    doc = yaml.safe_load(path.read_text())
    if not isinstance(doc, dict) or not isinstance(doc.get('cameras'), dict):
        raise CalibrationInputError(f'{path}: expected a cameras block (as uav_vs_calibrate '
                                    f'rig writes)')
    return flat_params(doc['cameras'], 'cameras.')


FrameKey = tuple[str, int]          # (camera, frame index)


def read_sync(path: Path) -> tuple[dict[FrameKey, int], dict[FrameKey, float]]:
    """(camera, frame index) -> sync index, and -> frame_time (s) when the CSV has that
    column, from a CSV with those columns (a camera named by its name, or by its number
    as 'cam_<n>')."""
    try:
        with open(path, newline='') as f:
            rows = list(csv.DictReader(f))
        sync, stamps = {}, {}
        for row in rows:
            key = (row.get('camera') or f"cam_{row['cam_id']}", int(row['frame_index']))
            sync[key] = int(row['sync_index'])
            if row.get('frame_time') not in (None, ''):
                stamps[key] = float(row['frame_time'])
        return sync, stamps
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise CalibrationInputError(f'sync file {path}: expected columns sync_index, camera '
                                    f'(or cam_id), frame_index ({err})') from None


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        {'intrinsics': intrinsics, 'rig': rig, 'landmarks': landmarks}[args.command](args)
    except (CalibrationInputError, SurveyError) as err:
        print(f'uav_vs_calibrate: {err}', file=sys.stderr)
        return 2
    except OSError as err:
        print(f'uav_vs_calibrate: {err}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
