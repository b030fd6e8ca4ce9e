"""The landmark survey (uav_vs.vision.landmark_survey, `uav_vs_calibrate landmarks`) against
the simulator's truth: the ground cameras render the vehicle standing still at a known
placement, and the survey must give back the configured layout and samples from which
the detector finds the landmarks in flight."""
import math

import cv2
import numpy as np
import pytest
import yaml

from uav_vs.calibrate import main
from uav_vs.sim.ground_scene import GroundScene, Pose, figure_eight, rot_z
from uav_vs.vision.colour_model import models_from_params
from uav_vs.vision.ground_config import (default_config_path, flat_params, load_ground_config,
                                         read_params_file)
from uav_vs.vision.landmark_survey import Placement, SurveyError, detector_params, survey
from uav_vs.vision.landmarks import LandmarkDetector

# Sun-lit from above, a sphere's colour centroid lies a little above its centre (the
# shaded underside falls out of the value range): up to 6 mm here. The trinocular pose
# sees the same shift in flight, so a surveyed layout keeps it; 1 cm is a tenth of the
# landmarks' radius.
LAYOUT_TOLERANCE = 0.01


@pytest.fixture(scope='module')
def station():
    params = read_params_file(default_config_path())
    config = load_ground_config(params)
    return params, config, GroundScene(config)


def still_frames(scene: GroundScene, origin, yaw_deg: float, n: int = 5) -> list[list]:
    """n frames per camera of the vehicle standing at `origin` heading `yaw_deg`."""
    yaw = math.radians(yaw_deg)
    frames = [[] for _ in scene.cameras]
    for k in range(n):
        images, _ = scene.render(Pose(0.1 * k, np.array(origin, float), yaw, rot_z(yaw)))
        for shots, image in zip(frames, images):
            shots.append(image)
    return frames


def test_placement_takes_world_points_into_the_body_frame():
    placement = Placement(np.array([1.0, 2.0, 0.5]), math.radians(90.0))
    # heading north: the nose (body x) points along world y, the left side (body y) west
    world = np.array([[1.0, 3.0, 0.5], [0.0, 2.0, 0.5], [1.0, 2.0, 1.5]])
    assert np.allclose(placement.to_body(world), np.eye(3), atol=1e-12)


@pytest.mark.parametrize('origin, yaw_deg', [((0.4, -0.3, 0.3), 90.0),
                                             ((-0.5, 0.6, 0.25), -30.0),
                                             ((0.0, 0.0, 1.0), 200.0)])
def test_a_still_vehicle_gives_the_layout_it_carries(station, origin, yaw_deg):
    params, config, scene = station
    detector = detector_params(params)
    found = survey(config.cameras, models_from_params(params, detector.bins), detector,
                   still_frames(scene, origin, yaw_deg), Placement(np.array(origin),
                                                                   math.radians(yaw_deg)))
    errors = np.linalg.norm(found.body - config.layout, axis=1)
    assert (errors < LAYOUT_TOLERANCE).all(), dict(zip(found.names, errors))
    assert (found.n_views == 3).all() and (found.reproj_px < 0.5).all()
    assert found.report()[1].startswith('red: base_link (')


def test_the_samples_find_the_landmarks_in_flight(station):
    """Models from the cut samples find every landmark along the figure eight as near to
    its true centre as the configured ranges do."""
    params, config, scene = station
    detector = detector_params(params)
    ranges = models_from_params(params, detector.bins)
    found = survey(config.cameras, ranges, detector, still_frames(scene, (0.4, -0.3, 0.3), 90.0),
                   Placement(np.array([0.4, -0.3, 0.3]), math.radians(90.0)))
    for sample in found.samples.values():
        assert sample.shape[2] == 4 and 0 < (sample[..., 3] > 0).mean() < 0.8
    errors = {}
    for kind, models in [('ranges', ranges),
                         ('samples', models_from_params(params, detector.bins, found.samples))]:
        detectors = [LandmarkDetector(models, detector) for _ in config.cameras]
        errors[kind] = []
        for k in range(30):
            pose = figure_eight(k / 7.5)
            images, _ = scene.render(pose)
            truth = scene.landmark_discs(pose)[..., :2]
            for cam, (image, det) in enumerate(zip(images, detectors)):
                for i, d in enumerate(det.detect(image)):
                    assert d.found, (kind, cam, d.name, k)
                    errors[kind].append(np.hypot(*(np.array(d.centroid) - truth[cam, i])))
    ours, theirs = np.median(errors['samples']), np.median(errors['ranges'])
    assert ours < 0.5 and ours < 1.5 * theirs, (ours, theirs)


def test_a_landmark_no_camera_finds_is_named(station):
    params, config, scene = station
    params = params | {'landmarks.blue.hue': [140, 150]}       # a colour nothing has
    detector = detector_params(params)
    with pytest.raises(SurveyError, match=r'^blue: found by 0 camera\(s\) \(none\)'):
        survey(config.cameras, models_from_params(params, detector.bins), detector,
               still_frames(scene, (0.4, -0.3, 0.3), 90.0, n=2),
               Placement(np.zeros(3), 0.0))


def write_stills(tmp_path, scene, origin, yaw_deg) -> list[str]:
    args = []
    for cam, shots in zip(scene.cameras, still_frames(scene, origin, yaw_deg, n=3)):
        folder = tmp_path / cam.name
        folder.mkdir()
        for k, image in enumerate(shots):
            cv2.imwrite(str(folder / f'{k:02d}.png'), image)
        args += ['--camera', f'{cam.name}={folder}']
    return args


def test_the_cli_surveys_the_landmarks_end_to_end(station, tmp_path, capsys):
    params, config, scene = station
    cameras = tmp_path / 'cameras.yaml'       # as `uav_vs_calibrate rig` writes it
    block = yaml.safe_load(default_config_path().read_text())['/**']['ros__parameters']
    cameras.write_text(yaml.safe_dump({'cameras': block['cameras']}))
    out = tmp_path / 'out'
    assert main(['landmarks', '--config', str(default_config_path()), '--cameras', str(cameras),
                 *write_stills(tmp_path, scene, (-0.5, 0.6, 0.25), -30.0),
                 '--placement', '-0.5', '0.6', '0.25', '-30', '--out', str(out)]) == 0
    assert 'red: base_link' in capsys.readouterr().out
    surveyed = yaml.safe_load((out / 'landmarks.yaml').read_text())['landmarks']
    new = {k: v for k, v in params.items() if not k.startswith('landmarks.')}
    new |= flat_params(surveyed, 'landmarks.')
    layout = load_ground_config(new).layout
    assert (np.linalg.norm(layout - config.layout, axis=1) < LAYOUT_TOLERANCE).all()
    for name in surveyed['names']:
        sample = cv2.imread(surveyed[name]['sample'], cv2.IMREAD_UNCHANGED)
        assert sample is not None and sample.shape[2] == 4
    assert (out / 'landmarks_report.txt').read_text().startswith('landmarks surveyed from cam')
    # the params file to fly with: the calibrated cameras, the surveyed landmarks, the rest
    # of the config as it was
    ready = read_params_file(out / 'ground_trinocular.yaml')
    assert ready == new | {f'cameras.{k}': v for k, v in flat_params(block['cameras']).items()}


@pytest.mark.parametrize('change, message', [
    (lambda a: a[:a.index('--camera') + 2] + a[a.index('--placement'):],
     '--camera: two cameras or more are needed'),
    (lambda a: [x.replace('cam3=', 'cam9=') for x in a], '--camera cam9: not a camera of'),
    (lambda a: a + ['--every', '0'], '--every: expected a whole number of frames >= 1'),
    (lambda a: [x.replace('config/ground_trinocular.yaml', 'config/onboard.yaml') for x in a],
     'cameras.names: expected a list'),
])
def test_the_cli_names_bad_input_in_one_line(station, tmp_path, capsys, change, message):
    _, _, scene = station
    args = ['landmarks', '--config', str(default_config_path()),
            *write_stills(tmp_path, scene, (0.4, -0.3, 0.3), 90.0),
            '--placement', '0.4', '-0.3', '0.3', '90', '--out', str(tmp_path / 'out')]
    assert main(change(args)) == 2
    err = capsys.readouterr().err
    assert message in err and err.count('\n') == 1, err


def test_frames_of_another_size_are_refused(station, tmp_path, capsys):
    _, _, scene = station
    args = write_stills(tmp_path, scene, (0.4, -0.3, 0.3), 90.0)
    image = cv2.imread(str(tmp_path / 'cam2' / '01.png'))
    cv2.imwrite(str(tmp_path / 'cam2' / '01.png'), cv2.resize(image, (320, 240)))
    assert main(['landmarks', '--config', str(default_config_path()), *args,
                 '--placement', '0', '0', '0', '0', '--out', str(tmp_path / 'out')]) == 2
    assert 'cam2: a frame of 320x240, the camera is 640x480' in capsys.readouterr().err


def with_decoy(shots: list, centre=(60, 40)) -> list:
    """The frames with a red disc a little larger than the landmark painted in a corner,
    where the whole-image search takes it for the landmark."""
    out = []
    for image in shots:
        image = image.copy()
        cv2.circle(image, centre, 10, (0, 0, 210), -1, cv2.LINE_AA)
        out.append(image)
    return out


def test_a_decoy_in_one_camera_is_outvoted_and_in_two_refused(station):
    """A red object in one camera's view: the triangulation leaves that camera out and the
    red landmark is still where it is. In two of the three, no pair of cameras agrees."""
    params, config, scene = station
    detector = detector_params(params)
    models = models_from_params(params, detector.bins)
    frames = still_frames(scene, (0.4, -0.3, 0.3), 90.0, n=2)
    placement = Placement(np.array([0.4, -0.3, 0.3]), math.radians(90.0))
    one = survey(config.cameras, models, detector, [with_decoy(frames[0]), *frames[1:]],
                 placement)
    assert one.n_views[0] == 2 and np.linalg.norm(one.body[0] - config.layout[0]) < LAYOUT_TOLERANCE
    with pytest.raises(SurveyError, match=r'^red: the cameras disagree on where it is'):
        survey(config.cameras, models, detector,
               [with_decoy(frames[0]), with_decoy(frames[1]), frames[2]], placement)
