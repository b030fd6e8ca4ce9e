"""sim_world as a process, started from its console script with the three params files.

What it publishes is checked against the vehicle simulator's state at home (the world
origin, heading north) and the calibration files; bad parameters stop it at start-up.
"""
import math
import subprocess

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import SetBool

from conftest import REPO, wait_for
from uav_vs.graph import executable
from uav_vs.ros.convert import image_to_bgr, msg_to_pose, stamp_to_ns, yaw_of
from uav_vs.flight.scenario import free_port
from uav_vs.sim.ground_scene import rot_z
from uav_vs.vision.colour_model import models_from_params
from uav_vs.vision.ground_config import load_ground_config, read_params_file, read_params_files
from uav_vs.vision.landmarks import LandmarkDetector, centroids

GROUND = REPO / 'config' / 'ground_trinocular.yaml'
LANDMARKS_UAV2 = REPO / 'config' / 'landmarks_uav2.yaml'
FILES = ['--params-file', str(GROUND),
         '--params-file', str(REPO / 'config' / 'onboard.yaml'),
         '--params-file', str(REPO / 'config' / 'sim_world.yaml')]


def test_publishes_ground_images_and_truth_of_the_vehicle_at_home(ros_node, processes):
    proc = processes('sim_world', [*FILES, '-p',
                                   f'vehicle.connection:=tcpin:127.0.0.1:{free_port()}'])
    got: dict[str, list] = {'image': [], 'info': [], 'truth': [], 'onboard': []}
    ros_node.create_subscription(Image, '/cam2/image_raw', got['image'].append,
                                 qos_profile_sensor_data)
    ros_node.create_subscription(CameraInfo, '/cam2/camera_info', got['info'].append, 10)
    ros_node.create_subscription(PoseStamped, '/truth/pose', got['truth'].append, 50)
    ros_node.create_subscription(Image, '/onboard/image_raw', got['onboard'].append,
                                 qos_profile_sensor_data)
    assert wait_for(lambda: len(got['image']) >= 3 and len(got['info']) >= 3, 60), proc.poll()

    image, info = got['image'][-1], got['info'][-1]
    assert image_to_bgr(image, (640, 480)).shape == (480, 640, 3)
    assert image.header.frame_id == info.header.frame_id == 'cam2_optical'
    K = read_params_file(REPO / 'config' / 'ground_trinocular.yaml')['cameras.cam2.K']
    np.testing.assert_allclose(info.k, K)
    D = read_params_file(REPO / 'config' / 'ground_trinocular.yaml')['cameras.cam2.D']
    np.testing.assert_allclose(info.d, D)       # rendered through the calibrated lens
    # Every frame's truth carries the frame's stamp; at home it is the world origin,
    # heading north (the autopilot's yaw 0).
    truth = {stamp_to_ns(m.header.stamp): m for m in got['truth']}
    assert stamp_to_ns(image.header.stamp) in truth
    position, q = msg_to_pose(truth[stamp_to_ns(image.header.stamp)])
    assert truth[stamp_to_ns(image.header.stamp)].header.frame_id == 'world'
    np.testing.assert_allclose(position, 0.0, atol=1e-9)
    assert yaw_of(q) == pytest.approx(math.pi / 2)
    assert got['onboard'] == []            # on the ground, the onboard camera sees nothing

    # Covered (ground_cameras/enable false), the ground cameras deliver nothing sampled
    # after the answer while the truth goes on; uncovered, they deliver again.
    enable = ros_node.create_client(SetBool, '/ground_cameras/enable')
    assert enable.wait_for_service(timeout_sec=10)

    def cover(on: bool) -> int:
        future = enable.call_async(SetBool.Request(data=not on))
        assert wait_for(future.done, 10) and future.result().success
        return ros_node.get_clock().now().nanoseconds

    def after(key: str, ns: int) -> list:
        return [m for m in got[key] if stamp_to_ns(m.header.stamp) > ns]

    covered = cover(True)
    assert wait_for(lambda: len(after('truth', covered)) >= 20, 30)
    assert after('image', covered) == [] and after('info', covered) == []
    uncovered = cover(False)
    assert wait_for(lambda: after('image', uncovered) and after('info', uncovered), 30)


def test_the_ground_cameras_see_another_vehicle_where_its_truth_says(ros_node, processes):
    """A second vehicle, /uav2 (its own sim_world: home at `start` in world, no ground
    cameras, its truth served as SIM_STATE), in the view of the first one's ground cameras
    (fleet.names [uav2]): on cam2's image each vehicle's detector (its own colours) finds
    all four of its landmarks within 1.5 px of where its truth projects them."""
    truth_port, start = free_port(), [0.8, 1.0]
    processes('sim_world', [*FILES, '-r', '__ns:=/uav2', '-p', 'vehicle.system_id:=2',
                            '-p', f'vehicle.connection:=tcpin:127.0.0.1:{free_port()}',
                            '-p', f'vehicle.truth_connection:=tcpin:127.0.0.1:{truth_port}',
                            '-p', f'vehicle.start:={start}', '-p', 'ground.rate:=0.0'],
              label='uav2')
    truths: dict[str, list] = {'/truth/pose': [], '/uav2/truth/pose': []}
    for topic, got in truths.items():
        ros_node.create_subscription(PoseStamped, topic, got.append, 50)
    assert wait_for(lambda: truths['/uav2/truth/pose'], 60)
    images = []
    ros_node.create_subscription(Image, '/cam2/image_raw', images.append, qos_profile_sensor_data)
    processes('sim_world', [*FILES, '-p', f'vehicle.connection:=tcpin:127.0.0.1:{free_port()}',
                            '-p', 'fleet.names:=[uav2]', '-p', 'fleet.uav2.system_id:=2',
                            '-p', f'fleet.uav2.truth_connection:=tcp:127.0.0.1:{truth_port}',
                            '-p', f'fleet.uav2.start:={start}',
                            '-p', f'fleet.uav2.landmarks:={LANDMARKS_UAV2}'], label='cameras')
    assert wait_for(lambda: len(images) >= 3, 60)
    image = image_to_bgr(images[-1], (640, 480))
    for topic, files in (('/truth/pose', [GROUND]), ('/uav2/truth/pose', [GROUND, LANDMARKS_UAV2])):
        params = read_params_files(files)
        config = load_ground_config(params)
        position, q = msg_to_pose(truths[topic][-1])
        assert np.allclose(position, [*start, 0.0] if 'uav2' in topic else 0.0, atol=1e-6)
        landmarks = config.layout @ rot_z(yaw_of(q)).T + position
        found = centroids(LandmarkDetector(models_from_params(params)).detect(image))[0]
        error = np.linalg.norm(found - config.cameras[1].project(landmarks), axis=1)
        assert (error < 1.5).all(), (topic, error)


def test_switched_on_effects_change_what_is_published(ros_node, processes):
    """No lens distortion: camera_info has D = 0; calibration error: camera_info keeps
    the calibration the nodes are given; drops: about the stated fraction of frames is
    missing; latency: every frame arrives at least latency - jitter after its stamp."""
    latency, jitter, p_drop = 0.08, 0.02, 0.4
    proc = processes('sim_world', [*FILES, '-p', f'vehicle.connection:=tcpin:127.0.0.1:{free_port()}',
                                   '-p', 'onboard.rate:=0.0', '-p', 'distortion.enabled:=false',
                                   '-p', 'calibration.enabled:=true',
                                   '-p', 'drops.enabled:=true', '-p', f'drops.probability:={p_drop}',
                                   '-p', 'latency.enabled:=true', '-p', f'latency.mean:={latency}',
                                   '-p', f'latency.jitter:={jitter}'])
    got: dict[str, list] = {'image': [], 'info': [], 'truth': []}
    clock = ros_node.get_clock()
    ros_node.create_subscription(Image, '/cam2/image_raw',
                                 lambda m: got['image'].append((m, clock.now().nanoseconds)),
                                 qos_profile_sensor_data)
    ros_node.create_subscription(CameraInfo, '/cam2/camera_info', got['info'].append, 10)
    ros_node.create_subscription(PoseStamped, '/truth/pose', got['truth'].append, 50)
    assert wait_for(lambda: len(got['truth']) >= 120, 90), proc.poll()

    assert got['info'] and all(not any(m.d) for m in got['info'])
    K = read_params_file(REPO / 'config' / 'ground_trinocular.yaml')['cameras.cam2.K']
    np.testing.assert_allclose(got['info'][-1].k, K)
    truth = {stamp_to_ns(m.header.stamp) for m in got['truth']}
    # skip discovery at the start and the frames still in flight at the end
    first, last = min(truth) + 1_000_000_000, max(truth) - 500_000_000
    frames = [(m, t) for m, t in got['image'] if first <= stamp_to_ns(m.header.stamp) < last]
    assert {stamp_to_ns(m.header.stamp) for m, _ in frames} <= truth
    n = sum(first <= s < last for s in truth)     # frame sets rendered in that span
    missing = 1 - len(frames) / n
    assert abs(missing - p_drop) < 4 * math.sqrt(p_drop * (1 - p_drop) / n), (len(frames), n)
    delays = [(t - stamp_to_ns(m.header.stamp)) * 1e-9 for m, t in frames]
    assert min(delays) >= latency - jitter, min(delays)
    # each one as late as its own delay: none held up for seconds (delivery, not speed)
    assert max(delays) < latency + jitter + 0.5, max(delays)


def test_unsynchronised_cameras_stamp_their_own_capture(ros_node, processes):
    """Camera 1 captures at the instant of truth/pose; cameras 2 and 3 each a fixed lag
    (at most unsynchronised.lag) plus a per-frame jitter later, and stamp that."""
    lag, jitter = 0.02, 0.002
    proc = processes('sim_world', [*FILES, '-p', f'vehicle.connection:=tcpin:127.0.0.1:{free_port()}',
                                   '-p', 'onboard.rate:=0.0', '-p', 'unsynchronised.enabled:=true',
                                   '-p', f'unsynchronised.lag:={lag}',
                                   '-p', f'unsynchronised.jitter:={jitter}'])
    stamps: dict[str, list[int]] = {name: [] for name in ('cam1', 'cam2', 'cam3', 'truth')}
    for name in ('cam1', 'cam2', 'cam3'):
        ros_node.create_subscription(
            Image, f'/{name}/image_raw',
            lambda m, name=name: stamps[name].append(stamp_to_ns(m.header.stamp)),
            qos_profile_sensor_data)
    ros_node.create_subscription(PoseStamped, '/truth/pose',
                                 lambda m: stamps['truth'].append(stamp_to_ns(m.header.stamp)), 50)
    assert wait_for(lambda: all(len(stamps[n]) >= 30 for n in ('cam1', 'cam2', 'cam3')), 90), \
        proc.poll()
    # Only frames captured while truth/pose was received: either subscription may match
    # first.
    truth = np.array(sorted(stamps['truth']))
    assert len(truth) >= 10, proc.poll()
    assert {s for s in stamps['cam1'] if truth[0] <= s <= truth[-1]} <= set(truth.tolist())
    lags = {}
    for name in ('cam2', 'cam3'):
        got = np.array([s for s in stamps[name] if truth[0] <= s < truth[-1]])
        assert len(got) >= 10, (name, len(got))
        nominal = truth[np.searchsorted(truth, got, side='right') - 1]
        lags[name] = (got - nominal) * 1e-9
        assert lags[name].min() >= 0 and lags[name].max() <= lag + jitter + 1e-6, lags[name]
        # a fixed lag drawn once, plus the jitter
        assert np.ptp(lags[name]) <= jitter + 1e-6, lags[name]
    assert max(lags['cam2'].max(), lags['cam3'].max()) > 0.002
    assert proc.poll() is None


def test_occlusion_covers_every_landmark_it_is_told_to(ros_node, processes):
    """With occlusion.probability 1 every landmark in front of every ground camera is
    occluded in every frame set, and the diagnostics count them."""
    proc = processes('sim_world', [*FILES, '-p', f'vehicle.connection:=tcpin:127.0.0.1:{free_port()}',
                                   '-p', 'onboard.rate:=0.0', '-p', 'world.diagnostics_period:=0.2',
                                   '-p', 'occlusion.enabled:=true',
                                   '-p', 'occlusion.probability:=1.0'])
    counts: list[dict] = []

    def on_diagnostics(msg: DiagnosticArray) -> None:
        counts.extend({kv.key: kv.value for kv in s.values} for s in msg.status
                      if s.name == '/sim_world')
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
    assert wait_for(lambda: counts and int(counts[-1]['ground_frames']) >= 10, 60), proc.poll()
    last = counts[-1]
    assert int(last['occluded_landmarks']) == 3 * 4 * int(last['ground_frames']), last


@pytest.mark.parametrize('override, expected', [
    ('ground.background:=nope.jpg', 'ground.background: cannot read'),
    ('onboard.rate:=-1.0', 'onboard.rate: expected a number in [0, 60]'),
    ('vehicle.connection:=tcpin:10.255.255.1:5760', 'vehicle.connection: cannot serve'),
    ('vehicle.autopilot:=betaflight', 'vehicle.autopilot: expected a string (one of ardupilot, px4)'),
    ('latency.jitter:=0.05', 'latency.jitter: 0.05 s is more than latency.mean 0.03 s'),
    ('drops.probability:=1.5', 'drops.probability: expected a number in [0, 1]'),
    ('calibration.angle_sigma:=2.0', 'calibration.angle_sigma: expected a number in [0, 0.5]'),
    ('wind.gust_sigma:=-0.1', 'wind.gust_sigma: expected a number in [0, 5]'),
    ('unsynchronised.lag:=0.5', 'unsynchronised.lag: expected a number in [0, 0.1]'),
    ('occlusion.fraction:=1.5', 'occlusion.fraction: expected a number in [0, 1]'),
    ('fleet.names:=[uav2]', 'fleet.uav2.truth_connection: missing'),
    (('fleet.names:=[uav2]', 'fleet.uav2.truth_connection:=tcp:127.0.0.1:5760',
      'fleet.uav2.landmarks:=/nonexistent/landmarks_uav2.yaml'),
     'fleet.uav2.landmarks: /nonexistent/landmarks_uav2.yaml: [Errno 2] No such file'),
    (('fleet.names:=[uav2]', 'fleet.uav2.truth_connection:=tcp:127.0.0.1:5760',
      f'fleet.uav2.landmarks:={REPO / "config" / "link_monitor.yaml"}'),
     'link_monitor.yaml: landmarks.names: expected a list of at least 2 distinct names'),
])
def test_bad_parameter_stops_it_with_one_line(override, expected):
    overrides = [override] if isinstance(override, str) else override
    run = subprocess.run([executable('sim_world'), '--ros-args', *FILES,
                          *(a for o in overrides for a in ('-p', o))],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and expected in fatal[0], run.stderr


def test_sitl_without_a_sitl_stops_it_with_one_line():
    port = free_port()
    run = subprocess.run([executable('sim_world'), '--ros-args', *FILES, '-p', 'vehicle.model:=sitl',
                          '-p', f'vehicle.sitl_connection:=tcp:127.0.0.1:{port}'],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and f'vehicle.sitl_connection: tcp:127.0.0.1:{port}: ' in fatal[0], \
        run.stderr
