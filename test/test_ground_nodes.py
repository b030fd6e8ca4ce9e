"""Ground nodes as separate processes, started from their console scripts with the YAML.

Truth is independent of the code under test: the simulator's exact poses recorded in
the sample bag, or landmark pixels projected analytically through the calibration.
"""
import math
import subprocess
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PolygonStamped, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from visualization_msgs.msg import ImageMarker

from conftest import REPO, wait_for
from uav_vs.flight.ground_replay import DEFAULT_LAYOUT, replay_ground_bag
from uav_vs.graph import executable
from uav_vs.ros.convert import (bgr_to_image, msg_to_pose, ns_to_stamp, points_to_polygon,
                                polygon_to_array, stamp_to_ns, yaw_of)
from uav_vs.vision.ground_config import load_ground_config, read_params_file

CONFIG = REPO / 'config' / 'ground_trinocular.yaml'
BAG = REPO / 'bags' / 'ground_trinocular'
CAMERAS = ['cam1', 'cam2', 'cam3']
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


def _replay(tmp_path: Path, layout: str):
    """The sample bag through the ground station in `layout`; the images go reliably
    (`camshift.image_qos: reliable`, as for any bag replay)."""
    report = replay_ground_bag(BAG, CONFIG, tmp_path / layout, CAMERAS, layout=layout,
                               extra_args=['-p', 'camshift.image_qos:=reliable'])
    print(layout, report.summary())
    return report


def test_sample_bag_through_the_graph_meets_accuracy(tmp_path):
    """Every synchronised frame set gives a pose: <= 2 cm position, <= 1 deg yaw RMSE.
    On a loaded machine the pose node may still give up on a set whose last camera is
    later than `trinocular.max_wait`, hence 95 %. Every process of the default layout
    exits 0."""
    report = _replay(tmp_path, DEFAULT_LAYOUT)
    assert report.frame_sets >= 50
    assert report.poses >= 0.95 * report.frame_sets
    assert report.position_rmse_m <= 0.02
    assert report.yaw_rmse_deg <= 1.0
    assert report.return_codes == [0] * {'one_process': 1, 'processes': 4}[DEFAULT_LAYOUT]


def test_one_process_station_gives_the_poses_of_the_separate_processes(tmp_path):
    """The same bag through both layouts: the same frame sets give a pose, most of them
    the very same pose (the same images, the same detectors); a few differ by less than
    the accuracy (a landmark missed in the first frames, a frame set released without a
    late camera: `trinocular.max_wait`). Both are near the simulator's truth."""
    apart, together = _replay(tmp_path, 'processes'), _replay(tmp_path, 'one_process')
    common = sorted(set(apart.messages) & set(together.messages))
    assert len(common) >= 0.9 * apart.frame_sets
    shift_m, turn_deg = [], []
    for stamp in common:
        (p1, q1), (p2, q2) = (msg_to_pose(r.messages[stamp]) for r in (apart, together))
        shift_m.append(np.linalg.norm(p1 - p2))
        turn_deg.append(math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(q1, q2)))))))
    print(f'difference median {np.median(shift_m) * 1e3:.4f} mm, max {max(shift_m) * 1e3:.3f} mm')
    assert np.median(shift_m) <= 1e-4 and np.median(turn_deg) <= 0.01
    assert max(shift_m) <= 0.02 and max(turn_deg) <= 1.0
    assert together.position_rmse_m <= 0.02 and together.yaw_rmse_deg <= 1.0


def _broken_config(tmp_path: Path, path: list[str], value) -> Path:
    doc = yaml.safe_load(CONFIG.read_text())
    node = doc['/**']['ros__parameters']
    for key in path[:-1]:
        node = node[key]
    if value is None:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    out = tmp_path / 'broken.yaml'
    out.write_text(yaml.safe_dump(doc))
    return out


@pytest.mark.parametrize('path, value, expected', [
    (['cameras', 'cam2', 'R'], None, 'cameras.cam2.R: missing'),
    (['cameras', 'cam1', 'K'], [500.0, 0.0, 320.0, 0.0, 500.0, 240.0], 'cameras.cam1.K: expected 9'),
    (['cameras', 'cam3', 't'], ['a', 'b', 'c'], 'cameras.cam3.t: expected 3 numbers'),
    (['cameras', 'cam1', 'R'], [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0],
     'cameras.cam1.R: expected a rotation matrix'),
    (['landmarks', 'red', 'position'], None, 'landmarks.red.position: missing'),
    (['cameras', 'cam2', 'latency'], 2.0, 'cameras.cam2.latency: expected a number in [-1, 1]'),
])
def test_bad_calibration_stops_pose_node_with_one_line(tmp_path, path, value, expected):
    cfg = _broken_config(tmp_path, path, value)
    run = subprocess.run([executable('trinocular_pose_node'), '--ros-args', '--params-file',
                          str(cfg)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and expected in fatal[0], run.stderr


K1 = 'K: [598.0, 0.0, 322.5, 0.0, 601.0, 237.1, 0.0, 0.0, 1.0]'


@pytest.mark.parametrize('k1, expected', [
    ('K: [598, 0.0, 322.5, 0.0, 601.0, 237.1, 0.0, 0.0, 1.0]',
     'cameras.cam1.K: list mixes integer (598) and double (0.0)'),
    ('K: [598.0, abc, 322.5, 0.0, 601.0, 237.1, 0.0, 0.0, 1.0]',
     'cameras.cam1.K: list mixes double (598.0) and string (abc)'),
    ('K: [598.0, 0.0, 322.5, 0.0, 601.0, 237.1, 0.0, 0.0, 1.0', 'not valid YAML'),
    (None, 'params.yaml: cannot read it'),
])
def test_params_file_rcl_would_refuse_stops_pose_node_with_one_line(tmp_path, k1, expected):
    """A list of mixed types, a file that is not YAML or not there: rcl would refuse it
    with a traceback from rclpy.init (exit 1); the node says why in one line first."""
    cfg = tmp_path / 'params.yaml'
    if k1 is not None:
        assert K1 in CONFIG.read_text()
        cfg.write_text(CONFIG.read_text().replace(K1, k1))
    run = subprocess.run([executable('trinocular_pose_node'), '--ros-args', '--params-file',
                          str(cfg)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and 'FATAL' in lines[0] and expected in lines[0], run.stderr


@pytest.mark.parametrize('path, value, expected', [
    (['cameras', 'cam2', 'R'], None, 'cameras.cam2.R: missing'),
    (['landmarks', 'blue', 'hue'], [100, 300], 'landmarks.blue.hue'),
])
def test_bad_parameter_stops_the_one_process_station_with_one_line(tmp_path, path, value,
                                                                   expected):
    """A parameter of the pose node or of the camera nodes: one FATAL line, exit 2."""
    cfg = _broken_config(tmp_path, path, value)
    run = subprocess.run([executable('ground_station'), '--ros-args', '--params-file',
                          str(cfg)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and expected in fatal[0], run.stdout + run.stderr


def test_bad_landmark_colour_stops_camshift_node(tmp_path):
    cfg = _broken_config(tmp_path, ['landmarks', 'blue', 'hue'], [100, 300])
    run = subprocess.run([executable('camshift_node'), '--ros-args', '--params-file', str(cfg),
                          '-p', 'camera:=cam1'], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert 'landmarks.blue.hue' in run.stderr + run.stdout


def test_camshift_node_takes_a_landmark_colour_from_a_sample_image(tmp_path, ros_node,
                                                                  processes):
    """landmarks.red.sample, a PNG cut from one frame, replaces red's hue and saturation:
    on another frame the node finds red at its true centroid."""
    from uav_vs.sim.ground_scene import GroundScene, figure_eight
    scene = GroundScene(load_ground_config(read_params_file(CONFIG)), seed=1)
    images, info = scene.render(figure_eight(0.0))
    u, v = np.round(info.full_centroid[0, 0]).astype(int)
    cv2.imwrite(str(tmp_path / 'red.png'), images[0][v - 6:v + 7, u - 6:u + 7])
    cfg = _broken_config(tmp_path, ['landmarks', 'red', 'hue'], None)
    processes('camshift_node', ['--params-file', str(cfg), '-r', '__ns:=/cam1',
                                '-p', 'camera:=cam1', '-p', 'camshift.image_qos:=reliable',
                                '-p', f"landmarks.red.sample:={tmp_path / 'red.png'}"],
              label='cam1')
    out: list[PolygonStamped] = []
    windows: list[ImageMarker] = []
    ros_node.create_subscription(PolygonStamped, '/cam1/landmarks', out.append, 10)
    marker_sub = ros_node.create_subscription(ImageMarker, '/cam1/landmark_windows',
                                              windows.append, 10)
    pub = ros_node.create_publisher(Image, '/cam1/image_raw', 10)
    assert wait_for(lambda: pub.get_subscription_count() > 0
                    and marker_sub.get_publisher_count() > 0, 30)
    images, info = scene.render(figure_eight(3.0))
    assert info.visible[0, 0] > 0.98
    pub.publish(bgr_to_image(images[0], Header(stamp=ns_to_stamp(1), frame_id='cam1_optical')))
    assert wait_for(lambda: len(out) == 1 and len(windows) == 1, 10)
    assert np.linalg.norm(polygon_to_array(out[0])[0, :2] - info.centroid[0, 0]) < 1.5
    assert f"landmark red: colour model from {tmp_path / 'red.png'}" in processes.log('cam1')
    # The annotation: one window (4 edges) around each landmark found, same header.
    [marker] = windows
    found = polygon_to_array(out[0])
    found = found[~np.isnan(found[:, 0]), :2]
    edges = np.array([(p.x, p.y) for p in marker.points]).reshape(-1, 4, 2, 2)
    assert (marker.header, marker.type) == (out[0].header, ImageMarker.LINE_LIST)
    assert len(edges) == len(found) > 0
    for (x, y), window in zip(found, edges):
        corners = window[:, 0]
        assert corners[:, 0].min() <= x <= corners[:, 0].max()
        assert corners[:, 1].min() <= y <= corners[:, 1].max()


@pytest.mark.parametrize('sample, expected', [
    ('no/such/red.png', "landmarks.red.sample: cannot read an image from 'no/such/red.png'"),
    (str(CONFIG), 'landmarks.red.sample: cannot read an image from'),
])
def test_unusable_sample_stops_camshift_node_with_one_line(tmp_path, sample, expected):
    run = subprocess.run([executable('camshift_node'), '--ros-args', '--params-file',
                          str(CONFIG), '-p', 'camera:=cam1', '-p', f'landmarks.red.sample:={sample}'],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert run.returncode == 2
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and expected in fatal[0], run.stdout + run.stderr


def _last_diagnostics(store: dict, name: str) -> dict:
    status = store.get(name)
    return {} if status is None else {kv.key: kv.value for kv in status.values}


def _collect_diagnostics(ros_node, store: dict) -> None:
    def on(msg: DiagnosticArray) -> None:
        for status in msg.status:
            store[status.name] = status
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', on, 50)


def test_malformed_images_are_counted_skipped_and_the_node_goes_on(ros_node, processes):
    proc = processes('camshift_node', ['--params-file', str(CONFIG), '-r', '__ns:=/cam1',
                                       '-p', 'camera:=cam1', '-p', 'camshift.diagnostics_period:=0.2',
                                       '-p', 'camshift.image_qos:=reliable',
                                       '-p', 'camshift.input_warn_after:=0.3',
                                       '-p', 'camshift.input_error_after:=1.0'], label='cam1')
    diags: dict = {}
    _collect_diagnostics(ros_node, diags)
    out: list[PolygonStamped] = []
    ros_node.create_subscription(PolygonStamped, '/cam1/landmarks', out.append, 10)
    pub = ros_node.create_publisher(Image, '/cam1/image_raw', 10)
    assert wait_for(lambda: pub.get_subscription_count() > 0, 30)
    frames = iter(range(1, 1000))
    header = lambda: Header(stamp=ns_to_stamp(next(frames) * 10**9),  # noqa: E731
                            frame_id='cam1_optical')
    good = lambda: bgr_to_image(np.full((480, 640, 3), 90, np.uint8), header())  # noqa: E731
    # What goes out before the node's subscription matches this publisher never arrives:
    # good images go out until one is answered, then the malformed ones.
    deadline = time.monotonic() + 30
    while not out and time.monotonic() < deadline:
        pub.publish(good())
        wait_for(lambda: bool(out), 0.5)
    assert out
    answered = len(out)
    wrong_encoding = Image(header=header(), height=480, width=640, encoding='32FC1', step=2560)
    wrong_encoding.data = bytes(480 * 2560)
    pub.publish(wrong_encoding)
    pub.publish(bgr_to_image(np.zeros((240, 320, 3), np.uint8), header()))    # wrong size
    pub.publish(good())
    assert wait_for(lambda: len(out) == answered + 1, 10)
    assert wait_for(lambda: _last_diagnostics(diags, '/cam1/camshift_node').get('malformed') == '2',
                    10), diags
    assert proc.poll() is None
    assert polygon_to_array(out[0]).shape == (4, 3)
    log = processes.log('cam1')
    assert 'unsupported encoding' in log and 'expected 640x480' in log
    assert 'cam1: 4 landmarks (red, green, blue, yellow) in /cam1/image_raw' in log
    # No image since: the input's silence is in the diagnostics, ERROR past its bound.
    assert wait_for(lambda: diags['/cam1/camshift_node'].message.startswith('no image for'), 10)
    assert wait_for(lambda: diags['/cam1/camshift_node'].level == ERROR, 10)


def _project_layout(cfg, position, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    world = cfg.layout @ R.T + position
    return [cam.project(world) for cam in cfg.cameras]


def _trinocular(ros_node, processes, *params: str):
    """A trinocular_pose_node on CONFIG and `params`; its config, process, the poses and
    diagnostics it sends, and a landmarks publisher per camera, matched both ways."""
    cfg = load_ground_config(read_params_file(CONFIG))
    proc = processes('trinocular_pose_node', ['--params-file', str(CONFIG), *params])
    poses: list[PoseStamped] = []
    sub = ros_node.create_subscription(PoseStamped, '/ground/pose', poses.append, 10)
    diags: dict = {}
    _collect_diagnostics(ros_node, diags)
    pubs = [ros_node.create_publisher(PolygonStamped, f'/{c}/landmarks', 10) for c in CAMERAS]
    assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                    and sub.get_publisher_count() > 0, 30)
    return cfg, proc, poses, diags, pubs


def test_pose_survives_a_landmark_lost_in_one_camera_and_needs_two_landmarks(ros_node, processes):
    cfg, _, poses, diags, pubs = _trinocular(ros_node, processes,
                                             '-p', 'trinocular.diagnostics_period:=0.2')

    truth_pos, truth_yaw = np.array([0.4, -0.3, 1.2]), 2.5
    pixels = _project_layout(cfg, truth_pos, truth_yaw)

    def publish(stamp_ns: int, hide: dict[int, list[int]]) -> None:
        for k, (pub, px) in enumerate(zip(pubs, pixels)):
            pts = np.column_stack([px, np.ones(len(px))])
            pts[hide.get(k, []), :2] = np.nan
            pub.publish(points_to_polygon(pts, Header(stamp=ns_to_stamp(stamp_ns))))

    publish(1_000_000_000, {0: [1]})                 # landmark 1 lost by cam1 only
    assert wait_for(lambda: len(poses) == 1, 10)
    p, q = msg_to_pose(poses[0])
    assert np.linalg.norm(p - truth_pos) < 1e-6
    assert abs(yaw_of(q) - truth_yaw) < 1e-6

    everyone = list(range(len(cfg.landmark_names)))
    publish(2_000_000_000, {k: everyone[1:] for k in range(3)})   # one landmark left
    name = '/trinocular_pose_node'
    assert wait_for(lambda: _last_diagnostics(diags, name).get('no_pose') == '1', 10), diags
    assert len(poses) == 1
    assert 'landmark' in diags[name].message


def test_a_camera_latency_is_taken_off_its_stamps_before_the_match(ros_node, processes):
    """cam2 stamps its frames 80 ms after the instant they show (cameras.cam2.latency
    0.08, far beyond trinocular.sync_tolerance): its frames match the others' of the same
    instant, and the pose is stamped with that instant, not cam2's stamp."""
    cfg, _, poses, diags, pubs = _trinocular(ros_node, processes,
                                             '-p', 'cameras.cam2.latency:=0.08')
    truth_pos, truth_yaw = np.array([0.4, -0.3, 1.2]), 2.5
    pixels = _project_layout(cfg, truth_pos, truth_yaw)
    instants = [1_000_000_000 + k * 66_666_667 for k in range(3)]
    for when in instants:
        for k, (pub, px) in enumerate(zip(pubs, pixels)):
            late = 80_000_000 if CAMERAS[k] == 'cam2' else 0
            pts = np.column_stack([px, np.ones(len(px))])
            pub.publish(points_to_polygon(pts, Header(stamp=ns_to_stamp(when + late))))
    assert wait_for(lambda: len(poses) >= 2, 10), diags
    time.sleep(0.5)
    assert [stamp_to_ns(p.header.stamp) for p in poses] == instants[:len(poses)]
    name = '/trinocular_pose_node'
    assert wait_for(lambda: _last_diagnostics(diags, name).get('cameras_used') == '3', 10)
    assert np.linalg.norm(msg_to_pose(poses[0])[0] - truth_pos) < 1e-6


def test_a_camera_of_the_rational_model_is_taken(ros_node, processes):
    """cam1's distortion as 8 coefficients (the rational model uav_vs_calibrate writes;
    k4-k6 zero, the same lens): the node starts and the pose is the true one."""
    d8 = '[-0.118, 0.082, 0.0004, -0.0003, -0.018, 0.0, 0.0, 0.0]'
    cfg, _, poses, _, pubs = _trinocular(ros_node, processes, '-p', f'cameras.cam1.D:={d8}')
    truth_pos, truth_yaw = np.array([0.4, -0.3, 1.2]), 2.5
    for pub, px in zip(pubs, _project_layout(cfg, truth_pos, truth_yaw)):
        pts = np.column_stack([px, np.ones(len(px))])
        pub.publish(points_to_polygon(pts, Header(stamp=ns_to_stamp(1_000_000_000))))
    assert wait_for(lambda: len(poses) == 1, 10)
    assert np.linalg.norm(msg_to_pose(poses[0])[0] - truth_pos) < 1e-6


def test_a_silent_camera_warns_and_all_silent_is_an_error(ros_node, processes):
    """Landmarks from every camera: OK. cam3 stops: WARN naming it, poses go on from two
    cameras. All stop: ERROR. They come back: OK again."""
    cfg, proc, poses, diags, pubs = _trinocular(
        ros_node, processes, '-p', 'trinocular.diagnostics_period:=0.1',
        '-p', 'trinocular.input_warn_after:=0.3', '-p', 'trinocular.input_error_after:=1.0',
        '-p', 'trinocular.max_wait:=0.05')
    pixels = _project_layout(cfg, np.array([0.4, -0.3, 1.2]), 2.5)
    sending = set(range(3))
    stamp = [1_000_000_000]
    stop = threading.Event()

    def send() -> None:
        while not stop.is_set():
            stamp[0] += 50_000_000
            for k in sorted(sending):
                pts = np.column_stack([pixels[k], np.ones(len(pixels[k]))])
                pubs[k].publish(points_to_polygon(pts, Header(stamp=ns_to_stamp(stamp[0]))))
            time.sleep(0.05)
    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    name = '/trinocular_pose_node'
    status = lambda: diags.get(name, DiagnosticStatus())
    try:
        assert wait_for(lambda: status().level == OK and status().message == 'pose ok', 10), \
            status()
        sending.discard(2)
        assert wait_for(lambda: status().level == WARN, 10), status()
        assert status().message.startswith('no landmarks from cam3 '), status()
        before = len(poses)
        assert wait_for(lambda: len(poses) > before + 5, 5)
        sending.clear()
        assert wait_for(lambda: status().level == ERROR, 10), status()
        assert all(c in status().message for c in CAMERAS), status()
        sending.update(range(3))
        assert wait_for(lambda: status().level == OK, 10), status()
    finally:
        stop.set()
        thread.join()
    assert proc.poll() is None
    assert ('/cam1/landmarks, /cam2/landmarks, /cam3/landmarks -> /ground/pose'
            in processes.log('trinocular_pose_node'))
