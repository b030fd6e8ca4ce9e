"""The rendered calibration board (uav_vs.sim.board_scene) against the camera model:
OpenCV's chessboard detector finds its corners where each ground camera projects them."""
import cv2
import numpy as np
import pytest

from uav_vs.sim.board_scene import BoardScene, in_front_of, on_the_ground
from uav_vs.vision.calibration import Board, Detection, detect
from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file

BOARD = Board('chessboard', 7, 10, 0.12)


@pytest.fixture(scope='module')
def scene() -> BoardScene:
    cameras = load_ground_config(read_params_file(default_config_path())).cameras
    return BoardScene(cameras, BOARD, noise_sigma=2.0, seed=3)


def held_before(cam: Camera, distance: float, rvec=(0.35, -0.25, 0.1)) -> np.ndarray:
    """The board `distance` m before `cam`, a little right of and above its centre, tilted."""
    return in_front_of(cam, BOARD, (0.55 * cam.width, 0.45 * cam.height), distance, rvec)


def corner_errors(cam: Camera, T: np.ndarray, det: Detection) -> tuple[float, np.ndarray]:
    """(RMS, mean offset (2,)) of the detected corners from where `cam` projects the
    board at pose `T`, px."""
    truth = cam.project(BOARD.object_points() @ T[:3, :3].T + T[:3, 3])[det.ids]
    error = det.points - truth
    return float(np.sqrt(np.mean(np.sum(error ** 2, axis=1)))), error.mean(axis=0)


@pytest.mark.parametrize('distance', [2.0, 3.0])
def test_the_corners_are_found_where_each_camera_projects_them(scene, distance):
    """Unbiased and within the detector's own accuracy (squares 25-40 px wide, 2 grey
    levels of noise): RMS under 0.1 px, mean offset under 0.03 px, in every camera, in
    OpenCV's corner order (the board is 7 x 10, so its order is unambiguous)."""
    for k, cam in enumerate(scene.cameras):
        T = held_before(cam, distance)
        det = detect(BOARD, scene.render(T)[k])
        assert det is not None, cam.name
        rms, mean = corner_errors(cam, T, det)
        assert len(det.ids) == 54 and rms < 0.1, (cam.name, rms)
        assert np.all(np.abs(mean) < 0.03), (cam.name, mean)


def test_the_board_on_the_ground_is_found_where_the_cameras_project_it(scene):
    """The view that fixes the world frame: the board flat at the origin, 7-8 m from the
    cameras, its squares 5-10 px. Where a camera finds it whole (cam1 and cam3; cam2 sees
    it too edge-on), RMS under 0.11 px and mean offset under 0.03 px. A bias here turns
    the whole rig: refined in the narrow window alone, cam3's corners sat 0.04 px off
    on average, and the board's pose from them 0.13 deg off about the vertical."""
    T = on_the_ground()
    found = []
    for cam, image in zip(scene.cameras, scene.render(T)):
        det = detect(BOARD, image)
        if det is None:
            continue
        found.append(cam.name)
        rms, mean = corner_errors(cam, T, det)
        assert rms < 0.11, (cam.name, rms)
        assert np.all(np.abs(mean) < 0.03), (cam.name, mean)
    assert len(found) >= 2, found


def test_the_board_seen_from_behind_is_plain_card(scene):
    cam = scene.cameras[0]
    T = held_before(cam, 2.5, rvec=(np.pi, 0.0, 0.0))       # turned to face away
    image = scene.render(T)[0]
    assert detect(BOARD, image) is None
    corners = cam.project(scene.corners_in(T)).astype(np.int32)
    inside = np.zeros(image.shape[:2], np.uint8)
    cv2.fillConvexPoly(inside, cv2.convexHull(corners), 1)
    inside = cv2.erode(inside, np.ones((5, 5), np.uint8)) > 0
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)[inside].astype(float)
    assert inside.sum() > 10000 and abs(grey.mean() - 120) < 2 and grey.std() < 4
