"""Setting up the simulated ground station as a real one is set up (docs/calibration.md),
then flying on what it gave: the ground cameras film a printed chessboard (rendered
through their own lenses, uav_vs.sim.board_scene) held before each of them, waved through
the flight area and laid on the ground; `uav_vs_calibrate intrinsics`, `rig` and
`landmarks` turn the frames into a params file, and the section 5 mission flies on it
while the simulator renders the true rig. Judged against the simulator's truth: the
calibrated cameras against the true ones, the flight by the figures the mission meets on
the true calibration (test_closed_loop)."""
import math

import cv2
import numpy as np
import pytest

from uav_vs.calibrate import main
from uav_vs.flight.report import FlightReport
from uav_vs.flight.scenario import Configs, fly
from uav_vs.sim.board_scene import BoardScene, close_ups, on_the_ground, through_the_volume
from uav_vs.sim.calibration_truth import lens_error, pose_error
from uav_vs.sim.ground_scene import GroundScene, Pose, rot_z
from uav_vs.vision.calibration import Board
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file

from test_closed_loop import SCENARIO

BOARD = Board('chessboard', 7, 10, 0.12)     # an A0 sheet: 0.84 x 1.2 m
BOARD_ARGS = ['--kind', 'chessboard', '--rows', '7', '--cols', '10', '--square', '0.12']
PLACEMENT = (0.4, -0.3, 0.3, 90.0)           # the vehicle standing for the survey


def write(folder, images) -> str:
    folder.mkdir(parents=True)
    for k, image in enumerate(images):
        cv2.imwrite(str(folder / f'{k:03d}.png'), image)
    return str(folder)


@pytest.fixture(scope='module')
def calibrated(tmp_path_factory):
    """The frames a user records, through the three commands: (the true cameras, the
    calibrated ones, the params file written)."""
    root = tmp_path_factory.mktemp('setup')
    true = load_ground_config(read_params_file(default_config_path()))
    scene = BoardScene(true.cameras, BOARD, seed=1)
    rng = np.random.default_rng(7)
    out = root / 'calibration'
    for k, cam in enumerate(true.cameras):
        frames = [scene.render(T)[k] for T in close_ups(cam, BOARD, 30, rng)]
        assert main(['intrinsics', *BOARD_ARGS, '--name', cam.name, '--out', str(out),
                     write(root / 'intrinsics' / cam.name, frames)]) == 0
    views = [scene.render(T) for T in [on_the_ground(), *through_the_volume(BOARD, 40, rng)]]
    rig = [f'{cam.name}=' + write(root / 'rig' / cam.name, [v[k] for v in views])
           for k, cam in enumerate(true.cameras)]
    assert main(['rig', *BOARD_ARGS, *(a for spec in rig for a in ('--camera', spec)),
                 '--intrinsics', str(out), '--ground', '0', '--out', str(out)]) == 0
    x, y, z, yaw = PLACEMENT
    stills = GroundScene(true)
    shots = [stills.render(Pose(0.1 * k, np.array([x, y, z]), math.radians(yaw),
                                rot_z(math.radians(yaw))))[0] for k in range(5)]
    survey = [f'{cam.name}=' + write(root / 'stills' / cam.name, [s[k] for s in shots])
              for k, cam in enumerate(true.cameras)]
    assert main(['landmarks', '--config', str(default_config_path()),
                 '--cameras', str(out / 'cameras.yaml'),
                 *(a for spec in survey for a in ('--camera', spec)),
                 '--placement', *map(str, PLACEMENT), '--out', str(out)]) == 0
    params = out / 'ground_trinocular.yaml'
    return true, load_ground_config(read_params_file(params)), params


def flight_volume() -> np.ndarray:
    """Points of the space the mission flies in, world frame, m."""
    axes = np.linspace(-1.5, 1.5, 7), np.linspace(-1.5, 1.5, 7), np.linspace(0.0, 2.5, 6)
    return np.stack(np.meshgrid(*axes), -1).reshape(-1, 3)


def test_the_calibrated_rig_matches_the_true_one(calibrated):
    """Every point of the flight volume each camera sees reprojects within 0.8 px of the
    true camera's pixel (median under 0.25 px), every pixel of the image within 0.6 px
    through our lens, R within 0.15 degrees, t within 12 mm, and the landmarks within
    1 cm of where the vehicle carries them. At 640 x 480 the board's squares are 5-10 px
    wide over the flight area, which bounds the rig's views; the run's own figures are
    printed."""
    true, ours, _ = calibrated
    points = flight_volume()
    for t, o in zip(true.cameras, ours.cameras):
        truth = t.project(points)
        seen = np.all((truth > 0) & (truth < (t.width, t.height)), axis=1)
        error = np.linalg.norm(o.project(points[seen]) - truth[seen], axis=1)
        lens = lens_error(t, o)
        turn, offset = pose_error(t, o)
        print(f'{t.name}: the flight volume reprojected within {error.max():.3f} px (median '
              f'{np.median(error):.3f}), the image through our lens within {lens.max():.3f} '
              f'px (median {np.median(lens):.3f}), R {turn:.3f} deg, t {1000 * offset:.1f} mm')
        assert seen.sum() > 100 and error.max() < 0.8 and np.median(error) < 0.25, t.name
        assert lens.max() < 0.6, t.name
        assert turn < 0.15 and offset < 0.012, (t.name, turn, offset)
    layout = np.linalg.norm(ours.layout - true.layout, axis=1)
    print(f'landmarks within {1000 * layout.max():.1f} mm')
    assert (layout < 0.01).all()


def test_the_mission_flies_on_the_calibrated_rig(calibrated, tmp_path):
    """The figures test_closed_loop asks of a flight on the true calibration."""
    _, _, params = calibrated
    log = fly(SCENARIO, tmp_path, Configs(ground=params, world_ground=default_config_path()),
              record=False)
    report = FlightReport.from_log(log)
    print(report.summary())
    assert log.failure == '', log.failure
    setpoint = report.setpoints[1]
    assert setpoint.reached and setpoint.error_max_m <= 0.2
    assert report.landing is not None and report.landing.touchdown[2] < 0.01
    assert report.landing.error_m <= 0.3
    assert report.sources['ground'].samples > 0
    assert report.sources['ground'].position_rmse_m <= 0.05
