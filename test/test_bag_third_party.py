"""bag_play and bag_record on bags made elsewhere: split bags whose metadata disagrees
with their storage, ROS 1 topic names that ROS 2 does not allow, message types outside
the stock type store.

Truth is what the test wrote (or published), rclpy's own name validation and type
hashes, and rosbags' AnyReader reading a recording with nothing but the bag itself.
"""
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.validate_topic_name import validate_topic_name
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String
from test_msgs.msg import Arrays, BasicTypes

from conftest import wait_for
from test_bag_player import Probe, start
from uav_vs import graph
from uav_vs.bag.play import Plan, PlayOptions, ros2_name
from uav_vs.bag.reader import Bag, BagError

ROS2 = get_typestore(Stores.ROS2_JAZZY)
TOPICS = ['AAA', 'BBB', 'CCC']          # relative names, as in rosbag2's own test bags
PARTS = 3
PER_PART = 40                           # messages per topic and file


# ---------------------------------------------------------------- bags made here

def disagreeing_split_bag(path: Path, storage: StoragePlugin) -> dict[str, list[str]]:
    """A three-file bag like rosbag2's `wbag`: the storage holds messages from 1000 ns to
    1000 + 3 * 120 * 3 ns, metadata.yaml promises a window near the end and fewer AAA.

    Returns each topic's strings in time order.
    """
    truth: dict[str, list[str]] = {t: [] for t in TOPICS}
    parts, t = [], 1000
    for k in range(PARTS):
        part = path.parent / f'{path.name}_part{k}'
        with Writer(part, version=9, storage_plugin=storage) as w:
            conns = {topic: w.add_connection(topic, 'std_msgs/msg/String', typestore=ROS2)
                     for topic in TOPICS}
            for n in range(PER_PART):
                for topic in TOPICS:
                    text = f'{topic} {k}.{n}'
                    w.write(conns[topic], t, serialize_message(String(data=text)))
                    truth[topic].append(text)
                    t += 3
        parts.append(part)
    path.mkdir()
    doc = yaml.safe_load((parts[0] / 'metadata.yaml').read_text())
    info = doc['rosbag2_bagfile_information']
    suffix = '.mcap' if storage == StoragePlugin.MCAP else '.db3'
    names = [f'{path.name}_{k}{suffix}' for k in range(PARTS)]
    for part, name in zip(parts, names):
        shutil.copy(part / f'{part.name}{suffix}', path / name)
        shutil.rmtree(part)
    info['relative_file_paths'] = names
    info['files'] = [dict(info['files'][0], path=name) for name in names]
    info['starting_time']['nanoseconds_since_epoch'] = t - 300     # as wbag: late and short
    info['duration']['nanoseconds'] = 411
    info['message_count'] = PARTS * PER_PART * len(TOPICS) - 7
    for topic in info['topics_with_message_count']:
        topic['message_count'] = PARTS * PER_PART - 7 * (topic['topic_metadata']['name'] == 'AAA')
    (path / 'metadata.yaml').write_text(yaml.safe_dump(doc))
    return truth


def ros1_slam_bag(path: Path, n: int = 6) -> dict[str, list[tuple]]:
    """A ROS 1 bag with names ROS 2 refuses: /ORB-SLAM/pose, /S-PTAM/odom, /3d/status."""
    store = get_typestore(Stores.ROS1_NOETIC)
    ros1 = {name.split('/')[-1]: store.types[name] for name in (
        'std_msgs/msg/Header', 'std_msgs/msg/String', 'builtin_interfaces/msg/Time',
        'nav_msgs/msg/Odometry', *(f'geometry_msgs/msg/{n}' for n in (
            'Point', 'Quaternion', 'Pose', 'PoseStamped', 'PoseWithCovariance', 'Vector3',
            'Twist', 'TwistWithCovariance')))}
    truth: dict[str, list[tuple]] = {'/ORB-SLAM/pose': [], '/S-PTAM/odom': [], '/3d/status': []}
    with Rosbag1Writer(path) as w:
        pose_c = w.add_connection('/ORB-SLAM/pose', 'geometry_msgs/msg/PoseStamped',
                                  typestore=store)
        odom_c = w.add_connection('/S-PTAM/odom', 'nav_msgs/msg/Odometry', typestore=store)
        status_c = w.add_connection('/3d/status', 'std_msgs/msg/String', typestore=store)
        for k in range(n):
            t = 10**18 + k * 10**8
            header = ros1['Header'](seq=k, stamp=ros1['Time'](sec=k, nanosec=7), frame_id='map')
            pose = ros1['Pose'](position=ros1['Point'](x=k, y=2.0 * k, z=0.5),
                                orientation=ros1['Quaternion'](x=0, y=0, z=0, w=1))
            w.write(pose_c, t, store.serialize_ros1(ros1['PoseStamped'](header=header, pose=pose),
                                                    'geometry_msgs/msg/PoseStamped'))
            twist = ros1['Twist'](linear=ros1['Vector3'](x=0.1 * k, y=0, z=0),
                                  angular=ros1['Vector3'](x=0, y=0, z=-0.2 * k))
            odom = ros1['Odometry'](
                header=header, child_frame_id='base_link',
                pose=ros1['PoseWithCovariance'](pose=pose, covariance=np.arange(36.0) * k),
                twist=ros1['TwistWithCovariance'](twist=twist, covariance=np.zeros(36)))
            w.write(odom_c, t + 1, store.serialize_ros1(odom, 'nav_msgs/msg/Odometry'))
            w.write(status_c, t + 2, store.serialize_ros1(ros1['String'](data=f'ok {k}'),
                                                          'std_msgs/msg/String'))
            truth['/ORB-SLAM/pose'].append((k, float(k), 2.0 * k))
            truth['/S-PTAM/odom'].append((k, 'base_link', 35.0 * k, -0.2 * k))
            truth['/3d/status'].append((f'ok {k}',))
    return truth


def run_play(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([graph.executable('bag_play'), *args], capture_output=True, text=True,
                          timeout=60)


# ---------------------------------------------------------------- storage is the truth

@pytest.mark.parametrize('storage', [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_split_bag_whose_metadata_disagrees_plays_its_storage(tmp_path, storage):
    """Every stored message, in time order across the files; the mismatch said once,
    naming the window and the count that disagree."""
    truth = disagreeing_split_bag(tmp_path / 'wbag', storage)
    with Bag(tmp_path / 'wbag') as bag:
        assert {t: i.count for t, i in bag.topics.items()} == {t: PARTS * PER_PART for t in TOPICS}
        assert (bag.start_ns, bag.end_ns) == (1000, 1000 + 3 * PARTS * PER_PART * len(TOPICS) - 2)
        played = [m for _, m in Plan(bag, PlayOptions(rate=0)).schedule()]
        mismatch = bag.metadata_mismatch
    assert [m.t_ns for m in played] == sorted(m.t_ns for m in played)
    for topic, texts in truth.items():
        assert [deserialize_message(m.raw, String).data for m in played if m.topic == topic] \
            == texts, topic
    assert 'time window' in mismatch and 'AAA: 113 in metadata, 120 in storage' in mismatch
    assert 'BBB' not in mismatch


def test_bag_play_plays_all_of_a_disagreeing_split_bag(ros_node, tmp_path):
    truth = disagreeing_split_bag(tmp_path / 'wbag', StoragePlugin.MCAP)
    probe = Probe(ros_node)
    for topic in TOPICS:
        probe.subscribe(f'/{topic}', 'std_msgs/msg/String')
    total = sum(map(len, truth.values()))
    r = run_play([str(tmp_path / 'wbag'), '--rate', '0'])
    assert r.returncode == 0, r.stderr + r.stdout
    assert wait_for(lambda: probe.count() >= total, 10)
    for topic, texts in truth.items():
        assert [deserialize_message(raw, String).data for raw in probe.got[f'/{topic}']] == texts
    log = r.stdout + r.stderr
    assert log.count('metadata.yaml disagrees with the storage') == 1, log


def test_bag_play_of_a_bag_whose_storage_is_empty_says_why(tmp_path):
    with Writer(tmp_path / 'b', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection('/lost', 'std_msgs/msg/String', typestore=ROS2)
    meta = tmp_path / 'b' / 'metadata.yaml'
    doc = yaml.safe_load(meta.read_text())
    doc['rosbag2_bagfile_information']['topics_with_message_count'][0]['message_count'] = 5
    meta.write_text(yaml.safe_dump(doc))
    r = run_play([str(tmp_path / 'b'), '--wait-subscribers', '0'])
    assert r.returncode == 1
    assert '/lost: 5 in metadata, 0 in storage' in r.stdout + r.stderr
    assert 'no message of /lost' in r.stderr


# ---------------------------------------------------------------- ROS 1 names

@pytest.mark.parametrize('name', ['/ORB-SLAM/pose', '/S-PTAM/odom', '/3d/points', '/a.b//c-',
                                  'cam 1/image', '/x/9', '/-'])
def test_every_mapped_name_is_a_legal_ros2_name(name):
    validate_topic_name(ros2_name(name))                    # rclpy raises on a bad name


@pytest.mark.parametrize('name', ['/camera/image_raw', 'AAA', '/a1/b_2', '/rosout'])
def test_legal_names_are_kept(name):
    assert ros2_name(name) == name


def test_names_mapped_onto_one_are_refused_naming_both(tmp_path):
    with Writer(tmp_path / 'b', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for topic in ('/a-b', '/a_b'):
            w.write(w.add_connection(topic, 'std_msgs/msg/String', typestore=ROS2), 10**18,
                    serialize_message(String()))
    with Bag(tmp_path / 'b') as bag:
        with pytest.raises(BagError, match='/a-b and /a_b would both be played as /a_b'):
            Plan(bag, PlayOptions())
        plan = Plan(bag, PlayOptions(remap={'/a-b': '/ab'}))
        assert (plan.name('/a-b'), plan.name('/a_b'), plan.renamed) == ('/ab', '/a_b', {})


def test_ros1_bag_with_ros1_only_names_plays_under_mapped_names(ros_node, tmp_path):
    """/ORB-SLAM/pose as /ORB_SLAM/pose, /3d/status as /_3d/status, each said once; the
    explicit remap of /S-PTAM/odom wins over the rule; every message and value arrives."""
    truth = ros1_slam_bag(tmp_path / 'slam.bag')
    probe = Probe(ros_node)
    probe.subscribe('/ORB_SLAM/pose', 'geometry_msgs/msg/PoseStamped')
    probe.subscribe('/sptam/odom', 'nav_msgs/msg/Odometry')
    probe.subscribe('/_3d/status', 'std_msgs/msg/String')
    r = run_play([str(tmp_path / 'slam.bag'), '--rate', '0',
                  '--remap', '/S-PTAM/odom:=/sptam/odom'])
    log = r.stdout + r.stderr
    assert r.returncode == 0, log
    assert wait_for(lambda: probe.count() >= 18, 10)
    poses = [deserialize_message(raw, PoseStamped) for raw in probe.got['/ORB_SLAM/pose']]
    assert [(p.header.stamp.sec, p.pose.position.x, p.pose.position.y) for p in poses] \
        == truth['/ORB-SLAM/pose']
    odoms = [deserialize_message(raw, Odometry) for raw in probe.got['/sptam/odom']]
    assert [(o.header.stamp.sec, o.child_frame_id, o.pose.covariance[35], o.twist.twist.angular.z)
            for o in odoms] == truth['/S-PTAM/odom']
    assert [(deserialize_message(raw, String).data,) for raw in probe.got['/_3d/status']] \
        == truth['/3d/status']
    assert log.count('topic /ORB-SLAM/pose played as /ORB_SLAM/pose') == 1, log
    assert log.count('topic /3d/status played as /_3d/status') == 1, log
    assert 'S-PTAM/odom played as' not in log and 'Traceback' not in log


def test_bad_remap_target_is_refused_in_one_line(tmp_path):
    ros1_slam_bag(tmp_path / 'slam.bag', n=1)
    r = run_play([str(tmp_path / 'slam.bag'), '--remap', '/S-PTAM/odom:=/s-ptam'])
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "bag_play: error: --remap target '/s-ptam' is not a ROS 2 topic name (topic name must "
        "not contain characters other than alphanumerics, '_', '~', '{', or '}')"]


def test_bag_record_refuses_a_ros1_only_name_before_writing(tmp_path):
    out = tmp_path / 'rec'
    r = subprocess.run([graph.executable('bag_record'), '-o', str(out), '/chat', '/ORB-SLAM/pose'],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    lines = (r.stdout + r.stderr).strip().splitlines()
    assert len(lines) == 1 and 'FATAL' in lines[0] and "'/ORB-SLAM/pose'" in lines[0], lines
    assert not out.exists()


# ---------------------------------------------------------------- types outside the store

def basic(k: int) -> BasicTypes:
    return BasicTypes(bool_value=k % 2 == 1, byte_value=bytes([k + 1]), char_value=65 + k,
                      float32_value=0.5 * k, float64_value=-1.25 * k, int8_value=-k,
                      uint8_value=200 + k, int16_value=-300 * k, uint16_value=600 * k,
                      int32_value=-70000 * k, uint32_value=70000 * k, int64_value=-(2**40) * k,
                      uint64_value=2**40 * k)


def arrays(k: int) -> Arrays:
    msg = Arrays()
    msg.char_values = [65 + k, 66, 67]
    msg.int32_values = [k, -k, 2 * k]
    msg.float64_values = [0.5 * k, 1.5, -2.0]
    msg.string_values = [f's{k}', 'b', '']
    msg.basic_types_values = [basic(k), basic(k + 1), basic(0)]
    return msg


def plain(value, like) -> object:
    """`value` (rclpy's or rosbags' message) as nested dicts, lists and floats, with the
    fields of the rclpy message `like`. A byte is compared as the byte it is: rclpy gives
    one bytes object, rosbags a signed integer."""
    if hasattr(like, 'get_fields_and_field_types'):
        return {name: plain(getattr(value, name), getattr(like, name))
                for name in like.get_fields_and_field_types()}
    if isinstance(like, bytes):
        return (value[0] if isinstance(value, bytes) else int(value)) % 256
    if isinstance(like, str):
        return value
    if hasattr(like, '__len__'):
        return [plain(v, w) for v, w in zip(value, like, strict=True)]
    return float(value)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_recording_of_non_stock_types_reads_back_with_anyreader(ros_node, tmp_path, storage):
    """test_msgs types, recorded by bag_record, open in rosbags' AnyReader from the bag's
    own definitions (the stored hash must be that of the stored definition), with the
    very hash rclpy announces, and every value comes back."""
    out = tmp_path / 'rec'
    rec = start('bag_record', ['-o', str(out), '--storage', storage, '/basic', '/arrays'],
                tmp_path / 'logs', 'record')
    pubs = {'/basic': ros_node.create_publisher(BasicTypes, '/basic', QoSProfile(depth=100)),
            '/arrays': ros_node.create_publisher(Arrays, '/arrays', QoSProfile(depth=100))}
    sent = {'/basic': [basic(k) for k in range(8)], '/arrays': [arrays(k) for k in range(8)]}
    try:
        assert wait_for(lambda: all(p.get_subscription_count() for p in pubs.values()), 20), \
            (tmp_path / 'logs' / 'record.log').read_text()
        for topic, msgs in sent.items():
            for msg in msgs:
                pubs[topic].publish(msg)
            pubs[topic].wait_for_all_acked()
        rec.send_signal(signal.SIGINT)
        assert rec.wait(10) == 0
    finally:
        graph.stop([rec])
    log = (tmp_path / 'logs' / 'record.log').read_text()
    assert 'announce type hash' not in log, log
    got: dict[str, list] = {t: [] for t in sent}
    with AnyReader([out]) as reader:
        digests = {c.topic: c.digest for c in reader.connections}
        for conn, _, raw in reader.messages():
            got[conn.topic].append(reader.deserialize(raw, conn.msgtype))
    for topic in sent:
        announced = ros_node.get_publishers_info_by_topic(topic)[0].topic_type_hash
        assert digests[topic] == str(announced), topic
    for topic, msgs in sent.items():
        assert len(got[topic]) == len(msgs), topic
        assert [plain(a, b) for a, b in zip(got[topic], msgs)] == [plain(b, b) for b in msgs]


# ---------------------------------------------------------------- TF

def test_tf_bag_plays_every_transform(ros_node, tmp_path):
    """/tf and /tf_static (tf2_msgs, built into the venv by the install) play in full;
    the values are the ones written by rosbags' own Jazzy serializer."""
    from tf2_msgs.msg import TFMessage

    types = ROS2.types
    truth = {'/tf': [], '/tf_static': []}
    with Writer(tmp_path / 'tf', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, 'tf2_msgs/msg/TFMessage', typestore=ROS2) for t in truth}
        for k in range(20):
            topic = '/tf_static' if k % 10 == 0 else '/tf'
            stamp = types['builtin_interfaces/msg/Time'](sec=k, nanosec=5)
            tf = types['geometry_msgs/msg/TransformStamped'](
                header=types['std_msgs/msg/Header'](stamp=stamp, frame_id='world'),
                child_frame_id=f'base_link_{k}',
                transform=types['geometry_msgs/msg/Transform'](
                    translation=types['geometry_msgs/msg/Vector3'](x=0.1 * k, y=-1.0, z=2.0),
                    rotation=types['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))
            msg = types['tf2_msgs/msg/TFMessage'](transforms=[tf])
            w.write(conns[topic], 10**9 + k * 10**6,
                    ROS2.serialize_cdr(msg, 'tf2_msgs/msg/TFMessage'))
            truth[topic].append((f'base_link_{k}', 0.1 * k))
    probe = Probe(ros_node)
    for topic in truth:
        probe.subscribe(topic, 'tf2_msgs/msg/TFMessage')
    r = run_play([str(tmp_path / 'tf'), '--rate', '0'])
    assert r.returncode == 0, r.stderr + r.stdout
    assert wait_for(lambda: probe.count() >= 20, 10), r.stdout + r.stderr
    for topic, expected in truth.items():
        got = [deserialize_message(raw, TFMessage).transforms[0] for raw in probe.got[topic]]
        assert [(t.child_frame_id, t.transform.translation.x) for t in got] == expected
