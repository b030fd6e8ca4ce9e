"""Calibration on real data (uav_vs.vision.calibration, uav_vs.vision.rig_calibration).

calibration/visp_intrinsics: `calibrate_camera` on ViSP's five circle-grid images
(pinhole model), next to cv2.calibrateCamera alone on the same points; the intrinsics
against the values ViSP publishes.
calibration/caliscope_rig: `calibrate_camera` for each of caliscope's four webcams and
`calibrate_rig` on the even synchronised sets; its figure is the RMS error of the
neighbour distances (one 54 mm square) of the board's corners triangulated from the
odd sets, left out, next to caliscope's own solution measured the same way, and next
to OpenCV's own solver (`solver='opencv'`, cv2.calibrateMultiview) on the same views.
Detection is not timed (it is OpenCV's own detector).
calibration/caliscope_timed_rig: the same with each webcam's latency measured
(`calibrate_timed_rig`, uav_vs.vision.rig_timing), the odd sets' boards taken at each
set's instant; the target is under 0.6 mm.
calibration/rig_4x100: `calibrate_rig` on four 1280x720 cameras at the corners of a
10 m square seeing a 7 x 10 chessboard (0.1 m squares) in 100 views (0.2 px noise),
intrinsics held fixed and refined, next to cv2.calibrateMultiview on the same views;
the target is under a minute on 2 cores. calibration/rig_partial_views: the same with
each camera seeing a random 60 % of the board's points in every view (as a ChArUco
board partly out of the image), both solvers.
calibration/simulated_rig: the simulated ground station calibrated from rendered
images as docs/calibration.md says (uav_vs.sim.board_scene): each camera's intrinsics
from 150 close-ups of a hand-held chessboard seen whole anywhere in the image, the rig
from an A0 chessboard laid on the ground and waved through the flight area (240 poses,
rendered 6 x 6 rays a pixel where its squares are 5-10 px), judged against the true
cameras (uav_vs.sim.calibration_truth); the targets are every pixel of the image within
0.1 px through our lens, R within 0.05 degrees, t within 2 mm. Times `calibrate_rig`.
"""
import tomllib
from dataclasses import replace

import cv2
import numpy as np

from bench.common import report, timeit
from uav_vs.calibrate import read_sync
from uav_vs.datasets import HOW_TO_GET, shared_data_dir
from uav_vs.sim.board_scene import (BoardScene, close_ups, on_the_ground, seen_points,
                                   through_the_volume)
from uav_vs.sim.calibration_truth import lens_error, pose_error
from uav_vs.vision.calibration import (Board, Intrinsics, calibrate_camera, detect, detect_all,
                                       read_images)
from uav_vs.vision.camera import Camera, look_at
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file
from uav_vs.vision.rig_calibration import calibrate_rig, neighbour_errors
from uav_vs.vision.rig_timing import calibrate_timed_rig, frame_gap, set_instants, timed_views

SUITE = 'calibration'
VISP = (276.509794, 272.9594743, 163.8652259, 113.304585)    # px, py, u0, v0 published


def visp(data) -> None:
    board = Board('circles', 6, 6, 0.034)
    found, size, _ = detect_all(board, read_images([data / 'calibration' / 'visp-circles']))
    result = calibrate_camera(board, found, size, 'pinhole')
    ms = timeit(lambda: calibrate_camera(board, found, size, 'pinhole'), 20, warmup=0)
    objects = board.object_points()
    flags = (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
             | cv2.CALIB_ZERO_TANGENT_DIST)
    ref_ms = timeit(lambda: cv2.calibrateCamera(
        [objects[d.ids] for d in found.values()], [d.points for d in found.values()], size,
        None, None, flags=flags), 20, warmup=0)
    K = result.K
    worst = max(abs(a / b - 1) for a, b in zip((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), VISP))
    report(SUITE, 'calibration/visp_intrinsics', ms, 'cv2.calibrateCamera', ref_ms,
           rms_px=round(result.rms, 4), worst_vs_published_pct=round(100 * worst, 3))


def neighbour_rms_mm(board, cameras, detections, views) -> tuple[float, int]:
    errors = neighbour_errors(board, cameras, detections, [str(v) for v in views])
    return 1000 * float(np.sqrt(np.mean(errors ** 2))), len(errors)


def cameras_of(rig) -> list[Camera]:
    return [Camera(name=c.name, K=c.intrinsics.K, D=c.intrinsics.D, R=c.R, t=c.t)
            for c in rig.cameras]


def caliscope(data) -> None:
    root = data / 'calibration' / 'caliscope' / 'charuco_calibration'
    spec = tomllib.loads((root / 'charuco.toml').read_text())
    square = spec['square_size_override_cm'] / 100
    board = Board('charuco', spec['rows'], spec['columns'], square,
                  spec['aruco_scale'] * square, spec['dictionary'], spec['inverted'])
    sync, stamps = read_sync(root / 'extrinsic' / 'timestamps.csv')
    names = [f'cam_{cam}' for cam in range(4)]
    detections, tracks = [], {}
    for name in names:
        found, _, _ = detect_all(board, read_images([root / 'extrinsic' / f'{name}.mp4']))
        frames = {int(k.rpartition('#')[2]): d for k, d in found.items()}
        detections.append({str(sync[name, f]): d for f, d in frames.items()})
        tracks[name] = {stamps[name, f]: d for f, d in frames.items()}
    train = {n: {v: d for v, d in det.items() if int(v) % 2 == 0}
             for n, det in zip(names, detections)}
    ground = min(set(train['cam_0']) & set(train['cam_1']), key=int)

    held_out = sorted({v for det in detections for v in det
                       if int(v) % 2 == 1 and sum(v in d for d in detections) >= 2})
    reference = tomllib.loads((root / 'camera_array.toml').read_text())['cameras']
    theirs = [Camera(name=n, K=np.array(reference[str(k)]['matrix']),
                     D=np.array(reference[str(k)]['distortions']),
                     R=np.array(reference[str(k)]['rotation']),
                     t=np.array(reference[str(k)]['translation'])) for k, n in enumerate(names)]
    ref_rms, _ = neighbour_rms_mm(board, theirs, detections, held_out)

    def solve(solver='scipy'):
        intrinsics = {n: calibrate_camera(board, views, (1280, 720)) for n, views in train.items()}
        return calibrate_rig(board, train, intrinsics, ground, solver=solver)
    rig, theirs_rig = solve(), solve('opencv')
    ms, ref_ms = timeit(solve, 3, warmup=0), timeit(lambda: solve('opencv'), 3, warmup=0)
    rms, pairs = neighbour_rms_mm(board, cameras_of(rig), detections, held_out)
    opencv_rms, _ = neighbour_rms_mm(board, cameras_of(theirs_rig), detections, held_out)
    report(SUITE, 'calibration/caliscope_rig', ms, 'cv2.calibrateMultiview', ref_ms,
           views=rig.views, rig_rms_px=round(rig.rms, 3),
           held_out_neighbour_rms_mm=round(rms, 3), caliscope_solution_mm=round(ref_rms, 3),
           opencv_solver_mm=round(opencv_rms, 3), pairs=pairs)

    instants = set_instants(sync, stamps, 'cam_0')
    gap = frame_gap(stamps)
    train_at = {v: when for v, when in instants.items() if int(v) % 2 == 0}
    test_at = {v: when for v, when in instants.items() if int(v) % 2 == 1}

    def solve_timed():
        intrinsics = {n: calibrate_camera(board, views, (1280, 720)) for n, views in train.items()}
        return calibrate_timed_rig(board, tracks, train_at, intrinsics, ground, gap)
    rig = solve_timed()
    ms = timeit(solve_timed, 3, warmup=0)
    seen = timed_views(tracks, test_at, rig.latency, gap)
    held_out = sorted(v for v in test_at if sum(v in seen[n] for n in names) >= 2)
    rms, pairs = neighbour_rms_mm(board, cameras_of(rig), [seen[n] for n in names], held_out)
    report(SUITE, 'calibration/caliscope_timed_rig', ms, None, None, views=rig.views,
           rig_rms_px=round(rig.rms, 3), held_out_neighbour_rms_mm=round(rms, 3), pairs=pairs,
           latency_ms={n: round(1000 * s, 1) for n, s in rig.latency.items()})


def rig_4x100() -> None:
    K = np.array([[1000.0, 0.0, 640.0], [0.0, 1000.0, 360.0], [0.0, 0.0, 1.0]])
    D = np.array([-0.2, 0.08, 0.0, 0.0, -0.01])
    cameras = [Camera(f'cam{k}', 1280, 720, K, D, *look_at(np.array([x, y, 3.5]),
                                                              np.array([0.0, 0.0, 1.0])))
               for k, (x, y) in enumerate([(5, 5), (-5, 5), (-5, -5), (5, -5)])]
    board = Board('chessboard', 7, 10, 0.1)
    rng = np.random.default_rng(0)
    waved = through_the_volume(board, 99, rng, half_width=1.5, heights=(0.3, 2.0),
                               max_tilt_deg=40.0)
    poses = {'ground': on_the_ground(), **{str(k): T for k, T in enumerate(waved)}}
    detections = seen_points(cameras, board, poses, 0.2, rng)
    intrinsics = {c.name: Intrinsics(K, D, 'plumb_bob', (1280, 720), np.nan, {}, {}, np.nan)
                  for c in cameras}
    partial = {c: {v: replace(d, ids=d.ids[keep], points=d.points[keep])
                   for v, d in views.items()
                   for keep in [np.sort(rng.choice(len(d.ids), int(0.6 * len(d.ids)),
                                                   replace=False)) if v != 'ground' else
                                np.arange(len(d.ids))]}
               for c, views in detections.items()}

    def worst_t_mm(rig) -> float:
        return 1000 * max(np.linalg.norm(o.t - t.t) for t, o in zip(cameras, rig.cameras))

    cases = [('rig_4x100', detections, False), ('rig_4x100_refined_intrinsics', detections, True),
             ('rig_partial_views', partial, False)]
    for case, seen, refine in cases:
        rig = calibrate_rig(board, seen, intrinsics, 'ground', refine)
        theirs = calibrate_rig(board, seen, intrinsics, 'ground', refine, solver='opencv')
        ms = timeit(lambda: calibrate_rig(board, seen, intrinsics, 'ground', refine), 3,
                    warmup=0)
        ref_ms = timeit(lambda: calibrate_rig(board, seen, intrinsics, 'ground', refine,
                                              solver='opencv'), 3, warmup=0)
        report(SUITE, f'calibration/{case}', ms, 'cv2.calibrateMultiview', ref_ms,
               views=rig.views, rig_rms_px=round(rig.rms, 3),
               worst_t_error_mm=round(worst_t_mm(rig), 2),
               opencv_worst_t_error_mm=round(worst_t_mm(theirs), 2))


def simulated_rig(draw: int = 0) -> None:
    """`draw` picks another random set of poses (docs/calibration.md compares five)."""
    cameras = load_ground_config(read_params_file(default_config_path())).cameras
    hand = Board('chessboard', 11, 16, 0.045)       # an A1 sheet, held 1-2.5 m away
    waved = Board('chessboard', 7, 10, 0.12)        # an A0 sheet
    intrinsics = {}
    for k, cam in enumerate(cameras):
        scene = BoardScene([cam], hand, seed=1 + k)
        poses = close_ups(cam, hand, 150, np.random.default_rng(7 + 10 * draw + k),
                          distance=(1.0, 2.5), tilt_deg=(15, 60), margin=0.0, whole=10)
        found = {str(i): d for i, T in enumerate(poses)
                 if (d := detect(hand, scene.render(T)[0])) is not None}
        intrinsics[cam.name] = calibrate_camera(hand, found, (cam.width, cam.height))
    scene = BoardScene(cameras, waved, supersample=6, seed=1)
    poses = [on_the_ground(), *through_the_volume(waved, 240, np.random.default_rng(11 + draw))]
    detections: dict[str, dict] = {c.name: {} for c in cameras}
    for i, T in enumerate(poses):
        for cam, image in zip(cameras, scene.render(T)):
            if (d := detect(waved, image)) is not None:
                detections[cam.name][str(i)] = d
    rig = calibrate_rig(waved, detections, intrinsics, '0')
    ms = timeit(lambda: calibrate_rig(waved, detections, intrinsics, '0'), 3, warmup=0)
    ours = cameras_of(rig)
    lens = [float(lens_error(t, o).max()) for t, o in zip(cameras, ours)]
    turn, offset = zip(*(pose_error(t, o) for t, o in zip(cameras, ours)))
    # each camera's rotation from the first's: what the world frame (the one board on the
    # ground) does not enter
    relative = [pose_error(replace(t, R=t.R @ cameras[0].R.T), replace(o, R=o.R @ ours[0].R.T))[0]
                for t, o in zip(cameras[1:], ours[1:])]
    report(SUITE, 'calibration/simulated_rig', ms, None, None, views=rig.views,
           close_ups_used=[len(i.view_errors) for i in intrinsics.values()],
           rig_views_seen={c: len(v) for c, v in detections.items()},
           lens_max_px=[round(v, 3) for v in lens], R_deg=[round(v, 3) for v in turn],
           t_mm=[round(1000 * v, 2) for v in offset],
           R_from_the_first_deg=[round(v, 3) for v in relative])


def main() -> None:
    rig_4x100()
    simulated_rig()
    data = shared_data_dir()
    if data is None:
        print(f'calibration: skipped, {HOW_TO_GET}')
        return
    visp(data)
    caliscope(data)


if __name__ == '__main__':
    main()
