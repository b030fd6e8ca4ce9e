"""foxglove_node, seen by a real Foxglove protocol client: the official @foxglove/ws-protocol
client on Node.js (tools/foxglove_probe) connects to the running node as the Foxglove app
does, takes the channels it advertises, subscribes and calls a service. What it receives
is decoded with rosbags from the schema the node advertised, and compared with what this
test published; a call reaches the ROS service only when `foxglove.allow_services` is on."""
import base64
import json
import os
import re
import shutil
import socket
import subprocess
import threading
import time

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TransformStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from std_srvs.srv import SetBool
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import ImageMarker

from conftest import REPO, refused_at_start, wait_for
from ros2msg import cdr_decoder
from uav_vs.ros.convert import bgr_to_image, ns_to_stamp, outlines_to_marker, rect_corners
from uav_vs.vision.ground_config import read_params_file

PROBE = REPO / 'tools' / 'foxglove_probe'
HOW_TO_GET_NODE = ('Node.js and npm not found: the Foxglove protocol client of this test '
                   'runs on them (Debian: apt install nodejs npm)')


@pytest.fixture(scope='module')
def probe(tmp_path_factory):
    """probe(spec) runs tools/foxglove_probe/probe.mjs with `spec`: what it received."""
    node, npm = shutil.which('node'), shutil.which('npm')
    if node is None or npm is None:
        if os.environ.get('CI'):
            pytest.fail(HOW_TO_GET_NODE)
        pytest.skip(HOW_TO_GET_NODE)
    folder = tmp_path_factory.mktemp('foxglove_probe')
    for name in ('package.json', 'package-lock.json', 'probe.mjs'):
        shutil.copy(PROBE / name, folder / name)
    subprocess.run([npm, 'ci', '--no-audit', '--no-fund', '--loglevel=error'], cwd=folder,
                   check=True, timeout=300, stdin=subprocess.DEVNULL)

    def run(spec: dict) -> dict:
        done = subprocess.run([node, str(folder / 'probe.mjs'), json.dumps(spec)],
                              capture_output=True, text=True, stdin=subprocess.DEVNULL,
                              timeout=spec['timeout_s'] + 30)
        assert done.returncode == 0 and done.stdout, done.stderr
        return json.loads(done.stdout)
    return run


def start_node(processes, label: str, params: list[str]) -> str:
    """foxglove_node on a free port: its ws:// address."""
    processes('foxglove_node', ['--params-file', str(REPO / 'config' / 'foxglove.yaml'),
                                '-p', 'foxglove.port:=0', '-p', 'foxglove.discovery_period:=0.2',
                                *params], label=label)
    serving = re.compile(r'serving (ws://\S+)')
    assert wait_for(lambda: serving.search(processes.log(label)), 30), processes.log(label)
    return serving.search(processes.log(label))[1]


def decoder(channel: dict):
    """The CDR decoder of a channel or service message, built from the ros2msg schema the
    node advertised (as the app builds it), with rosbags."""
    decode = cdr_decoder(channel['schemaName'], channel['schema'])
    return lambda data_b64: decode(base64.b64decode(data_b64))


class Talker:
    """What the graph would publish: poses at 20 Hz, camera frames at 10 Hz (sensor-data
    QoS, as a camera driver offers them) each with its annotation (an ImageMarker
    outlining a window that moves), one latched static transform; an `arm` service that
    counts its calls; poses on /late/pose too from `late_at` (monotonic clock). Every
    pose, frame and outline sent is kept, by stamp."""

    late_at = float('inf')
    malformed_every: int | None = None      # every so many frames, one with too little data

    def __init__(self, node) -> None:
        self.node, self.poses, self.frames, self.outlines, self.calls = node, {}, {}, {}, []
        static = node.create_publisher(TFMessage, '/tf_static', QoSProfile(
            depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        t = TransformStamped(child_frame_id='cam1')
        t.header.frame_id = 'world'
        t.transform.translation.x, t.transform.rotation.w = 1.25, 1.0
        static.publish(TFMessage(transforms=[t]))
        self.pose_pub = node.create_publisher(PoseStamped, '/ground/pose', 10)
        self.image_pub = node.create_publisher(Image, '/cam1/image_raw', qos_profile_sensor_data)
        self.marker_pub = node.create_publisher(ImageMarker, '/cam1/landmark_windows', 10)
        node.create_service(SetBool, '/arm', self.on_arm)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def on_arm(self, request, response):
        self.calls.append(request.data)
        response.success, response.message = True, f'armed: {request.data}'
        return response

    def run(self) -> None:
        rng, k, late = np.random.default_rng(3), 0, None
        while not self.stop.is_set():
            if late is None and time.monotonic() > self.late_at:
                late = self.node.create_publisher(PoseStamped, '/late/pose', 10)
            if late is not None:
                late.publish(PoseStamped())
            stamp = time.time_ns()
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = ns_to_stamp(stamp), 'world'
            pose.pose.position.x, pose.pose.orientation.w = 0.01 * k, 1.0
            self.poses[stamp] = pose.pose.position.x
            self.pose_pub.publish(pose)
            if k % 2 == 0:
                header = Header(stamp=ns_to_stamp(stamp), frame_id='cam1')
                # Smooth (JPEG keeps it), and different in every frame.
                frame = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), np.uint8), (0, 0), 4)
                image = bgr_to_image(frame, header)
                if self.malformed_every and (k // 2) % self.malformed_every == 0:
                    image.data = image.data[:100]
                else:
                    self.frames[stamp] = frame
                self.image_pub.publish(image)
                self.outlines[stamp] = rect_corners(k % 40, 3.0, 12.5, 10.0)
                self.marker_pub.publish(outlines_to_marker([self.outlines[stamp]], header,
                                                           (1.0, 1.0, 0.0, 1.0)))
            k += 1
            time.sleep(0.05)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()


@pytest.fixture
def talker(ros_node):
    t = Talker(ros_node)
    yield t
    t.close()


def test_the_app_sees_the_graphs_topics_as_published_and_cannot_call_a_service(
        probe, processes, talker):
    url = start_node(processes, 'fox', [])
    talker.late_at = time.monotonic() + 1.0
    got = probe({'url': url, 'timeout_s': 30, 'settle_s': 1.0,
                 'subscribe': {'/ground/pose': 20, '/cam1/image_raw': 10, '/tf_static': 1,
                               '/late/pose': 1},
                 'call': {'service_id': 1, 'data_b64': 'AAEAAAE='}})
    assert not got['timedOut'], ({t: len(m) for t, m in got['messages'].items()},
                                 got['statuses'], processes.log('fox'))
    assert got['serverInfo']['capabilities'] == []
    channels = {c['topic']: c for c in got['channels']}
    for topic, schema in (('/ground/pose', 'geometry_msgs/msg/PoseStamped'),
                          ('/cam1/image_raw', 'sensor_msgs/msg/Image'),
                          ('/tf_static', 'tf2_msgs/msg/TFMessage'),
                          ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray')):
        assert (channels[topic]['schemaName'], channels[topic]['encoding'],
                channels[topic]['schemaEncoding']) == (schema, 'cdr', 'ros2msg'), topic
    # A topic that appeared once the node was running was advertised, and forwarded.
    assert '/late/pose' in channels and got['messages']['/late/pose']

    # Every pose and frame received is one this test published, unchanged, in order,
    # stamped with a receive time no earlier than its own stamp.
    pose = decoder(channels['/ground/pose'])
    xs, stamps = [], []
    for m in got['messages']['/ground/pose']:
        msg = pose(m['data_b64'])
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert talker.poses[stamp] == msg.pose.position.x
        assert int(m['timestamp']) >= stamp
        xs.append(msg.pose.position.x)
        stamps.append(stamp)
    assert xs == sorted(xs) and len(set(xs)) == len(xs)
    image = decoder(channels['/cam1/image_raw'])
    for m in got['messages']['/cam1/image_raw']:
        msg = image(m['data_b64'])
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert (msg.width, msg.height, msg.encoding) == (64, 48, 'bgr8')
        assert msg.data.tobytes() == talker.frames[stamp].tobytes()
    # The static transform, latched before the node started, came to a late subscriber.
    [static] = got['messages']['/tf_static']
    [t] = decoder(channels['/tf_static'])(static['data_b64']).transforms
    assert (t.header.frame_id, t.child_frame_id, t.transform.translation.x) == \
        ('world', 'cam1', 1.25)

    # Services are not offered: a call is refused by the server, the vehicle is not armed.
    assert got['services'] == []
    assert [f['message'] for f in got['serviceFailures']] == ['Server does not support services']
    assert talker.calls == []


def test_with_allow_services_the_app_calls_the_graphs_service(probe, processes, talker):
    url = start_node(processes, 'fox_services', ['-p', 'foxglove.allow_services:=true',
                                                 '-p', "foxglove.services:=['/arm']"])
    # A request that is no SetBool in CDR fails in the app, reaches nothing, stops nothing.
    garbage = probe({'url': url, 'timeout_s': 30, 'settle_s': 1.0,
                     'call': {'service': '/arm', 'data_b64': base64.b64encode(b'\x07').decode()}})
    assert len(garbage['serviceFailures']) == 1 and talker.calls == [], garbage
    request = base64.b64encode(serialize_message(SetBool.Request(data=True))).decode()
    got = probe({'url': url, 'timeout_s': 30, 'settle_s': 1.0,
                 'call': {'service': '/arm', 'data_b64': request}})
    assert not got['timedOut'] and got['serviceFailures'] == [], got
    assert got['serverInfo']['capabilities'] == ['services']
    [service] = got['services']
    assert (service['name'], service['type']) == ('/arm', 'std_srvs/srv/SetBool')
    [response] = got['serviceResponses']
    answer = decoder({'schemaName': service['response']['schemaName'],
                      'schema': service['response']['schema']})(response['data_b64'])
    assert (answer.success, answer.message) == (True, 'armed: True')
    assert talker.calls == [True]
    log = processes.log('fox_services')
    assert 'service /arm called from the app' in log
    assert 'malformed call of /arm from the app' in log


def test_for_a_slow_link_a_rate_limit_and_jpeg_frames(probe, processes, talker, ros_node):
    """The pose limited to 5 Hz (the talker sends 20), the raw frames also as JPEG; a
    frame that cannot be encoded is counted and skipped."""
    talker.malformed_every = 4
    diagnostics: list[dict] = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diagnostics.extend(
        {kv.key: kv.value for kv in s.values} for s in m.status
        if s.name == '/foxglove_node'), 10)
    url = start_node(processes, 'fox_slow', [
        '-p', "foxglove.max_rates:=['/ground/pose=5']",
        '-p', "foxglove.jpeg_topics:=['/cam[0-9]/image_raw']",
        '-p', 'foxglove.diagnostics_period:=0.2'])
    got = probe({'url': url, 'timeout_s': 30, 'settle_s': 1.0,
                 'subscribe': {'/ground/pose': 8, '/cam1/image_raw/jpeg': 8}})
    assert not got['timedOut'], {t: len(m) for t, m in got['messages'].items()}
    channels = {c['topic']: c for c in got['channels']}
    jpeg = channels['/cam1/image_raw/jpeg']
    assert (jpeg['schemaName'], jpeg['encoding']) == ('sensor_msgs/msg/CompressedImage', 'cdr')

    received = [int(m['timestamp']) for m in got['messages']['/ground/pose']]
    assert min(np.diff(received)) >= 200_000_000, np.diff(received)    # the node's clock
    decode = decoder(jpeg)
    for m in got['messages']['/cam1/image_raw/jpeg']:
        msg = decode(m['data_b64'])
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        image = cv2.imdecode(msg.data, cv2.IMREAD_COLOR)
        assert msg.format == 'jpeg' and msg.header.frame_id == 'cam1'
        error = np.abs(image.astype(int) - talker.frames[stamp]).mean()
        assert error < 3.0, error        # JPEG at quality 80 of a smooth frame
    assert wait_for(lambda: diagnostics and int(diagnostics[-1]['unconverted']) > 0
                    and int(diagnostics[-1]['throttled']) > 0, 10), diagnostics[-1:]
    assert 'image data too short' in processes.log('fox_slow')


def test_for_a_slow_link_smaller_frames_with_their_annotations(probe, processes, talker):
    """foxglove.jpeg_scale 0.5: the JPEG frames half the size, close to the frame shrunk
    by area; the annotation served beside them with its pixel coordinates halved."""
    url = start_node(processes, 'fox_small', [
        '-p', "foxglove.jpeg_topics:=['/cam1/image_raw']", '-p', 'foxglove.jpeg_scale:=0.5',
        '-p', "foxglove.jpeg_markers:=['/cam[0-9]/landmark_windows']"])
    got = probe({'url': url, 'timeout_s': 30, 'settle_s': 1.0,
                 'subscribe': {'/cam1/image_raw/jpeg': 6, '/cam1/landmark_windows/jpeg': 6}})
    assert not got['timedOut'], {t: len(m) for t, m in got['messages'].items()}
    channels = {c['topic']: c for c in got['channels']}
    assert channels['/cam1/landmark_windows/jpeg']['schemaName'] == \
        'visualization_msgs/msg/ImageMarker'
    image = decoder(channels['/cam1/image_raw/jpeg'])
    for m in got['messages']['/cam1/image_raw/jpeg']:
        msg = image(m['data_b64'])
        frame = talker.frames[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
        small = cv2.resize(frame, (32, 24), interpolation=cv2.INTER_AREA)
        decoded = cv2.imdecode(msg.data, cv2.IMREAD_COLOR)
        assert decoded.shape == (24, 32, 3)
        assert np.abs(decoded.astype(int) - small).mean() < 3.0
    marker = decoder(channels['/cam1/landmark_windows/jpeg'])
    for m in got['messages']['/cam1/landmark_windows/jpeg']:
        msg = marker(m['data_b64'])
        outline = talker.outlines[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
        points = np.array([(p.x, p.y) for p in msg.points])
        assert len(points) == 8 and np.allclose(points[::2], 0.5 * outline)


@pytest.mark.parametrize('param, value', [('foxglove.topics', "['(']"),
                                          ('foxglove.port', '70000'),
                                          ('foxglove.max_rates', "['/cam1/image_raw']")])
def test_a_bad_parameter_stops_the_node_with_one_line(tmp_path, param, value):
    fatal = refused_at_start('foxglove_node', ['-p', f'{param}:={value}'], tmp_path)
    assert param in fatal, fatal


def test_a_port_in_use_stops_the_node_with_one_line(tmp_path):
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen()
        port = taken.getsockname()[1]
        fatal = refused_at_start('foxglove_node', ['-p', f'foxglove.port:={port}'], tmp_path)
    assert f'cannot serve on 127.0.0.1:{port}' in fatal and 'foxglove.port' in fatal, fatal


def test_every_parameter_is_in_the_yaml_with_its_default():
    from uav_vs.nodes.foxglove_node import PARAMS

    yaml = read_params_file(REPO / 'config' / 'foxglove.yaml')
    assert yaml == {spec.name: spec.default for spec in PARAMS}


@pytest.mark.parametrize('args', [['--hosts', '2'], ['--vehicles', '2'],
                                  ['--autopilot', 'ardupilot-sitl'], ['--bag', 'bags/onboard']])
def test_the_demo_refuses_a_view_it_cannot_serve(args, capsys, tmp_path):
    from uav_vs.demo import main
    with pytest.raises(SystemExit) as stop:
        main(['--view', *args, '--out', str(tmp_path)])
    assert stop.value.code == 2 and '--view watches a closed-loop flight' in capsys.readouterr().err
