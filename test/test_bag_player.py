"""bag_play and bag_record: every bag replays to exactly its messages, a recording replays
to the bytes recorded, broken bags fail naming the file.

Truth is the bag itself as rosbags reads it, or the messages the test wrote or published.
Replays run as separate processes from their console scripts, several at once, into a
probe that subscribes raw (KEEP_ALL, reliable).
"""
import shutil
import signal
import subprocess
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String

from conftest import REPO, wait_for
from uav_vs import graph
from uav_vs.bag.play import Plan, PlayOptions, parse_remaps, progress_line
from uav_vs.bag.reader import Bag, BagError, QosOffer, record_request, replay_offer
from uav_vs.bag.writer import STORAGES, BagWriter
from uav_vs.nodes import bag_player, bag_recorder
from uav_vs.ros.convert import bgr_to_image
from uav_vs.ros.replay import message_class

SAMPLE_BAGS = [REPO / 'bags' / 'ground_trinocular', REPO / 'bags' / 'onboard']
SHARED_BAGS = ['talker_sqlite3', 'talker_mcap', 'cdr_test_sqlite3', 'cdr_test_mcap']
PROBE_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
ROS2 = get_typestore(Stores.ROS2_JAZZY)


# ---------------------------------------------------------------- bags made here

def string_bag(path: Path, n: int = 10, period_ns: int = 50_000_000, t0: int = 10**18,
               storage: StoragePlugin = StoragePlugin.MCAP, version: int = 9,
               compression: CompressionMode | None = None) -> list[bytes]:
    """/tick with 'k=0'..'k=n-1' every period_ns and /other beside it; returns /tick's CDR."""
    raws = [serialize_message(String(data=f'k={k}')) for k in range(n)]
    writer = Writer(path, version=version, storage_plugin=storage)
    if compression:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer as w:
        tick = w.add_connection('/tick', 'std_msgs/msg/String', typestore=ROS2)
        other = w.add_connection('/other', 'std_msgs/msg/String', typestore=ROS2)
        for k, raw in enumerate(raws):
            w.write(tick, t0 + k * period_ns, raw)
            w.write(other, t0 + k * period_ns + 1, serialize_message(String(data='other')))
    return raws


def split_bags(tmp_path: Path) -> tuple[Path, Path]:
    """The same 20 messages as a two-file sqlite3 bag with metadata.yaml, and without it."""
    parts = []
    for k in range(2):
        string_bag(tmp_path / f'part{k}', t0=10**18 + k * 10**9, storage=StoragePlugin.SQLITE3)
        parts.append(tmp_path / f'part{k}')
    with_meta, without = tmp_path / 'split', tmp_path / 'split_nometa'
    for out in (with_meta, without):
        out.mkdir()
        for k, part in enumerate(parts):
            shutil.copy(part / f'{part.name}.db3', out / f'split_{k}.db3')
    doc = yaml.safe_load((parts[0] / 'metadata.yaml').read_text())
    info = doc['rosbag2_bagfile_information']
    second = yaml.safe_load((parts[1] / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    info['relative_file_paths'] = ['split_0.db3', 'split_1.db3']
    info['files'] = [dict(f, path=f'split_{k}.db3')
                     for k, f in enumerate(info['files'] + second['files'])]
    info['message_count'] = 40
    info['duration']['nanoseconds'] += 10**9
    for topic in info['topics_with_message_count']:
        topic['message_count'] = 20
    (with_meta / 'metadata.yaml').write_text(yaml.safe_dump(doc))
    return with_meta, without


def ros1_bag(path: Path) -> dict[str, list]:
    """A ROS 1 bag: latched /ros1/status (String), /ros1/image (Image, header with seq)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    String1, Image1 = store.types['std_msgs/msg/String'], store.types['sensor_msgs/msg/Image']
    Header1, Time1 = store.types['std_msgs/msg/Header'], store.types['builtin_interfaces/msg/Time']
    truth: dict[str, list] = {'/ros1/status': [], '/ros1/image': []}
    with Rosbag1Writer(path) as w:
        status = w.add_connection('/ros1/status', 'std_msgs/msg/String', typestore=store,
                                  latching=1)
        image = w.add_connection('/ros1/image', 'sensor_msgs/msg/Image', typestore=store)
        for k in range(5):
            t = 10**18 + k * 10**8
            w.write(status, t, store.serialize_ros1(String1(data=f'status {k}'),
                                                    'std_msgs/msg/String'))
            pixels = np.full(4 * 3 * 3, k, np.uint8)
            msg = Image1(header=Header1(seq=k + 7, stamp=Time1(sec=k, nanosec=k * 1000),
                                        frame_id=f'frame{k}'),
                         height=4, width=3, encoding='rgb8', is_bigendian=0, step=9, data=pixels)
            w.write(image, t + 1, store.serialize_ros1(msg, 'sensor_msgs/msg/Image'))
            truth['/ros1/status'].append(f'status {k}')
            truth['/ros1/image'].append((k, k * 1000, f'frame{k}', pixels.tobytes()))
    return truth


def image_bag(path: Path, n: int = 120) -> None:
    """n raw 640x480 bgr8 images at 30 Hz (about 110 MB)."""
    rng = np.random.default_rng(0)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/camera/image_raw', 'sensor_msgs/msg/Image', typestore=ROS2)
        for k in range(n):
            img = rng.integers(0, 256, (480, 640, 3), np.uint8)
            msg = bgr_to_image(img, Header(frame_id='camera'))
            w.write(conn, 10**18 + k * 33_333_333, serialize_message(msg))


def promises_more(path: Path) -> Path:
    """A bag whose metadata promises 5 messages its storage does not hold."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection('/lost', 'std_msgs/msg/String', typestore=ROS2)
    meta = path / 'metadata.yaml'
    doc = yaml.safe_load(meta.read_text())
    info = doc['rosbag2_bagfile_information']
    info['message_count'] = 5
    info['topics_with_message_count'][0]['message_count'] = 5
    info['duration']['nanoseconds'] = 10**9
    info['starting_time']['nanoseconds_since_epoch'] = 10**18
    meta.write_text(yaml.safe_dump(doc))
    return path


def truncated(src: Path, out: Path, fraction: float) -> Path:
    """A copy of bag folder src whose storage file is cut to `fraction` of its size."""
    shutil.copytree(src, out)
    storage = next(f for f in out.iterdir() if f.suffix in ('.mcap', '.db3'))
    storage.chmod(0o644)
    data = storage.read_bytes()
    storage.write_bytes(data[:int(len(data) * fraction)])
    return storage


def same_cdr(received: list[bytes], sent: list[bytes]) -> bool:
    """Byte for byte, but for the zeros DDS may append to pad a payload to 4-byte length."""
    return len(received) == len(sent) and all(
        r == s or (r[:len(s)] == s and r[len(s):] == bytes(-len(s) % 4))
        for r, s in zip(received, sent))


def bag_messages(path: Path) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = defaultdict(list)
    with Bag(path) as bag:
        for m in bag.messages():
            out[m.topic].append(m.raw)
    return out


# ---------------------------------------------------------------- core, no ROS

def test_real_rosbag2_bags_are_read_whole_despite_rosbags_qos_mismatch(shared_data):
    """rosbags alone yields nothing from these folders (their QoS text differs between
    metadata.yaml and storage); the Bag reads the storage and gets all 20."""
    for name in ('talker_mcap', 'talker_sqlite3'):
        bag = shared_data / 'rosbag2' / name
        got = bag_messages(bag)
        assert {t: len(m) for t, m in got.items()} == {'/topic': 10, '/rosout': 10}
        assert [deserialize_message(r, String).data for r in got['/topic']] \
            == [f'Hello, world! {k}' for k in range(10)]
        with Bag(bag) as b:
            assert b.topics['/rosout'].offer == QosOffer(True, True)
            assert b.topics['/topic'].offer == QosOffer(True, False)


def test_every_layout_reads_every_message(tmp_path):
    """Metadata v8/v9, mcap/sqlite3, zstd per message and per file, split with and without
    metadata, a lone storage file: each yields exactly the messages its index promises."""
    tick = string_bag(tmp_path / 'v8', version=8, storage=StoragePlugin.SQLITE3)
    string_bag(tmp_path / 'zstd', compression=CompressionMode.MESSAGE)
    string_bag(tmp_path / 'zstd_file', compression=CompressionMode.FILE)
    for path in (tmp_path / 'v8', tmp_path / 'zstd', tmp_path / 'zstd_file',
                 tmp_path / 'zstd' / 'zstd.mcap', tmp_path / 'v8' / 'v8.db3'):
        assert bag_messages(path)['/tick'] == tick, path
    split, nometa = split_bags(tmp_path)
    for path in (split, nometa):
        with Bag(path) as bag:
            got = [(m.topic, m.t_ns) for m in bag.messages()]
            assert bag.topics['/tick'].count == 20 and len(got) == 40
            assert got == sorted(got, key=lambda x: x[1])


def test_ros1_bag_is_converted_to_ros2_cdr(tmp_path):
    truth = ros1_bag(tmp_path / 'old.bag')
    with Bag(tmp_path / 'old.bag') as bag:
        assert bag.topics['/ros1/status'].offer == QosOffer(True, True)
        assert bag.topics['/ros1/image'].offer == QosOffer(True, False)
        msgs = defaultdict(list)
        for m in bag.messages():
            msgs[m.topic].append(m.raw)
    assert [deserialize_message(r, String).data for r in msgs['/ros1/status']] \
        == truth['/ros1/status']
    images = [deserialize_message(r, Image) for r in msgs['/ros1/image']]
    assert [(i.header.stamp.sec, i.header.stamp.nanosec, i.header.frame_id, bytes(i.data))
            for i in images] == truth['/ros1/image']


def test_metadata_promising_more_than_the_storage_holds_is_said(tmp_path):
    bag = promises_more(tmp_path / 'bag')
    with Bag(bag) as b:
        assert list(b.messages()) == [] and b.topics['/lost'].count == 0
        assert '/lost: 5 in metadata, 0 in storage' in b.metadata_mismatch


@pytest.mark.parametrize('src, fraction', [(SAMPLE_BAGS[0], 0.5), (SAMPLE_BAGS[1], 0.999)])
def test_truncated_storage_is_an_error_naming_the_file(tmp_path, src, fraction):
    storage = truncated(src, tmp_path / 'bag', fraction)
    with pytest.raises(BagError, match=str(storage)):
        Bag(tmp_path / 'bag')


def test_plan_selects_remaps_windows_and_times(tmp_path):
    string_bag(tmp_path / 'b', n=20)
    with Bag(tmp_path / 'b') as bag:
        plan = Plan(bag, PlayOptions(rate=2.0, start_s=0.25, duration_s=0.5, loop=True,
                                     topics=('tick',), remap=parse_remaps(['/tick:=tock'])))
        assert list(plan.topics) == ['/tick'] and plan.name('/tick') == 'tock'
        sched = plan.schedule()
        first = [next(sched) for _ in range(25)]
        assert [deserialize_message(m.raw, String).data for _, m in first[:11]] \
            == [f'k={k}' for k in range(5, 15)] + ['k=5']
        assert np.allclose(np.diff([due for due, _ in first]), 0.025)
        assert plan.bag_time_ns(0.3) == plan.start_ns + 100_000_000    # 0.6 s mod 0.5 s
        with pytest.raises(BagError, match='no topic /nope'):
            Plan(bag, PlayOptions(topics=('/nope',)))
        with pytest.raises(BagError, match='no message'):
            list(Plan(bag, PlayOptions(start_s=5.0)).schedule())
    with pytest.raises(ValueError):
        parse_remaps(['a=b'])
    assert progress_line(5, 10, 3, width=10).startswith('[#####-----]  50.0 %')


def test_qos_follows_the_recorded_publishers_as_rosbag2_does():
    never = QosTime(0, 0)
    reliable = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
                   never, never, QosLiveliness.AUTOMATIC, never, False)
    best_effort = reliable._replace(reliability=QosReliability.BEST_EFFORT)
    latched = reliable._replace(durability=QosDurability.TRANSIENT_LOCAL)
    assert replay_offer([best_effort, best_effort]) == QosOffer(False, False)
    assert replay_offer([latched]) == QosOffer(True, True)
    assert replay_offer([best_effort, reliable]) == QosOffer()      # mixed: the default offer
    assert replay_offer([]) == QosOffer()
    assert record_request([best_effort, reliable]) == QosOffer(False, False)
    assert record_request([latched, latched]) == QosOffer(True, True)


# ---------------------------------------------------------------- through ROS

class Probe:
    """Raw KEEP_ALL subscriptions on the probe node; bytes received per topic name."""

    def __init__(self, node) -> None:
        self.node = node
        self.got: dict[str, list[bytes]] = defaultdict(list)

    def subscribe(self, name: str, msgtype: str) -> None:
        self.node.create_subscription(message_class(msgtype), name,
                                      lambda raw, n=name: self.got[n].append(raw), PROBE_QOS,
                                      raw=True)

    def count(self) -> int:
        return sum(len(v) for v in self.got.values())


def start(name: str, args: list[str], log_dir: Path, label: str) -> subprocess.Popen:
    """A console script with its own (argparse) arguments, output to log_dir/<label>.log."""
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / f'{label}.log', 'wb') as log:
        return subprocess.Popen([graph.executable(name), *args], stdout=log,
                                stderr=subprocess.STDOUT)


def replay_at_rate_0(bags: list[Path], ros_node, tmp_path: Path) -> None:
    """Play every bag at once (bag k's topics under /bk/) and check each topic received
    exactly the bag's messages, in order, byte for byte (but DDS's padding)."""
    probe, procs, expected = Probe(ros_node), [], {}
    for k, bag in enumerate(bags):
        with Bag(bag) as b:
            for topic, info in b.topics.items():
                probe.subscribe(f'/b{k}/{topic.lstrip("/")}', info.msgtype)
        expected.update({f'/b{k}/{t.lstrip("/")}': raws for t, raws in bag_messages(bag).items()})
    for k, bag in enumerate(bags):
        with Bag(bag) as b:
            remaps = [f'{t}:=/b{k}/{t.lstrip("/")}' for t in b.topics]
        # Each player waits for the probe's subscriptions, however long discovery takes on
        # a loaded machine (its 5 s default may pass first: what it publishes before a
        # subscriber matched is not delivered, volatile as the bags offer it).
        procs.append(start('bag_play', [str(bag), '--rate', '0', '--wait-subscribers', '50',
                                        '--remap', *remaps], tmp_path / 'logs', f'play{k}'))
    try:
        deadline = time.monotonic() + 120
        for p in procs:
            p.wait(max(deadline - time.monotonic(), 1))
        total = sum(len(v) for v in expected.values())
        wait_for(lambda: probe.count() >= total, 60)
    finally:
        graph.stop(procs)
    logs = {k: (tmp_path / 'logs' / f'play{k}.log').read_text() for k in range(len(bags))}
    assert [p.returncode for p in procs] == [0] * len(bags), logs
    for name, raws in expected.items():
        assert len(probe.got[name]) == len(raws), name
        assert same_cdr(probe.got[name], raws), name
    assert set(probe.got) <= set(expected)


def test_project_and_made_bags_replay_exactly_at_rate_0(ros_node, tmp_path):
    """Sample bags, a ROS 1 bag, split bags with and without metadata, a single storage
    file and 110 MB of raw images: nothing lost, nothing changed."""
    ros1_bag(tmp_path / 'old.bag')
    split, nometa = split_bags(tmp_path)
    image_bag(tmp_path / 'images')
    bags = [*SAMPLE_BAGS, tmp_path / 'old.bag', split, nometa / 'split_1.db3',
            tmp_path / 'images']
    replay_at_rate_0(bags, ros_node, tmp_path)


def test_real_rosbag2_bags_replay_exactly_at_rate_0(ros_node, tmp_path, shared_data):
    """Every message each storage file holds (counted by rosbags on the file alone)."""
    bags = [shared_data / 'rosbag2' / b for b in SHARED_BAGS]
    for bag in bags:
        held: Counter[str] = Counter()
        for file in bag.iterdir():
            if file.suffix in ('.mcap', '.db3'):
                with Reader(file) as reader:
                    held.update(conn.topic for conn, _, _ in reader.messages())
        assert Counter({t: len(m) for t, m in bag_messages(bag).items()}) == held, bag
    replay_at_rate_0(bags, ros_node, tmp_path)


def test_timing_window_loop_selection_remap_and_clock(ros_node, tmp_path):
    """At rate 2 the 50 ms spacing becomes 25 ms; only the window's messages of the chosen
    topic, under its new name, pass after pass; /clock runs inside the window; SIGINT ends
    the loop cleanly."""
    string_bag(tmp_path / 'b', n=20)
    probe = Probe(ros_node)
    probe.subscribe('/tock', 'std_msgs/msg/String')
    probe.subscribe('/other', 'std_msgs/msg/String')
    arrivals: list[float] = []
    clock: list[int] = []
    ros_node.create_subscription(String, '/tock', lambda m: arrivals.append(time.monotonic()),
                                 PROBE_QOS)
    ros_node.create_subscription(Clock, '/clock', lambda m: clock.append(
        m.clock.sec * 10**9 + m.clock.nanosec), 100)
    proc = start('bag_play', [str(tmp_path / 'b'), '--rate', '2', '--start', '0.25',
                              '--duration', '0.5', '--loop', '--topics', '/tick', '--remap',
                              '/tick:=/tock', '--clock', '100'], tmp_path / 'logs', 'play')
    try:
        assert wait_for(lambda: len(probe.got['/tock']) >= 40, 20)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(10) == 0
    finally:
        graph.stop([proc])
    data = [deserialize_message(r, String).data for r in probe.got['/tock']]
    assert data[:40] == [f'k={5 + k % 10}' for k in range(40)]
    assert probe.got['/other'] == []
    gaps_ms = np.diff(arrivals[:40]) * 1e3
    assert 20 <= np.median(gaps_ms) <= 30, gaps_ms
    start_ns = 10**18 + 250_000_000
    assert clock and all(start_ns <= t <= start_ns + 500_000_000 for t in clock)
    assert 'interrupted after' in (tmp_path / 'logs' / 'play.log').read_text()


def test_recording_replays_to_the_recorded_bytes(ros_node, tmp_path):
    """bag_record takes 640x480 images at 30 Hz and strings without loss; bag_play gives
    back the recorded bytes; metadata has the publishers' QoS and type hashes."""
    out = tmp_path / 'rec'
    rec = start('bag_record', ['-o', str(out), '/cam/image', 'chat'],
                tmp_path / 'logs', 'record')
    images = ros_node.create_publisher(Image, '/cam/image', QoSProfile(depth=100))
    chat = ros_node.create_publisher(String, '/chat', QoSProfile(depth=100))
    rng = np.random.default_rng(1)
    sent = {'/cam/image': [bgr_to_image(rng.integers(0, 256, (480, 640, 3), np.uint8),
                                        Header(frame_id='cam')) for _ in range(30)],
            '/chat': [String(data=f'hello {k}') for k in range(30)]}
    try:
        assert wait_for(lambda: images.get_subscription_count() and chat.get_subscription_count(),
                        20), (tmp_path / 'logs' / 'record.log').read_text()
        for img, text in zip(sent['/cam/image'], sent['/chat']):
            images.publish(img)
            chat.publish(text)
            time.sleep(1 / 30)
        images.wait_for_all_acked()
        chat.wait_for_all_acked()
        rec.send_signal(signal.SIGINT)
        assert rec.wait(10) == 0
    finally:
        graph.stop([rec])
    recorded = bag_messages(out)
    for topic, msgs in sent.items():
        assert [deserialize_message(r, type(msgs[0])) for r in recorded[topic]] == msgs, topic
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == 'mcap'
    for t in meta['topics_with_message_count']:
        info = ros_node.get_publishers_info_by_topic(t['topic_metadata']['name'])[0]
        assert t['topic_metadata']['type_description_hash'] == str(info.topic_type_hash)
        assert t['topic_metadata']['offered_qos_profiles'][0]['reliability'] == 'reliable'

    probe = Probe(ros_node)
    for topic in sent:
        probe.subscribe(f'/replay{topic}', ('sensor_msgs/msg/Image' if 'image' in topic
                                            else 'std_msgs/msg/String'))
    play = start('bag_play', [str(out), '--rate', '0', '--remap',
                              *[f'{t}:=/replay{t}' for t in sent]], tmp_path / 'logs', 'play')
    try:
        assert play.wait(30) == 0
        assert wait_for(lambda: probe.count() >= 60, 10)
    finally:
        graph.stop([play])
    for topic in sent:
        assert same_cdr(probe.got[f'/replay{topic}'], recorded[topic]), topic


def test_best_effort_recording_subscribes_best_effort_to_a_reliable_publisher(ros_node, tmp_path):
    """--best-effort: the recorder's subscription is best effort (as the graph shows it)
    though the publisher offers reliable, which the bag still records as offered."""
    out = tmp_path / 'rec'
    rec = start('bag_record', ['-o', str(out), '--best-effort', 'chat'], tmp_path / 'logs',
                'record')
    chat = ros_node.create_publisher(String, '/chat', QoSProfile(depth=100))
    sent = [String(data=f'hello {k}') for k in range(100)]
    try:
        assert wait_for(chat.get_subscription_count, 20), \
            (tmp_path / 'logs' / 'record.log').read_text()
        (sub,) = [i for i in ros_node.get_subscriptions_info_by_topic('/chat')
                  if i.node_name == 'bag_recorder']
        assert sub.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        for text in sent:
            chat.publish(text)
            time.sleep(0.01)
        time.sleep(0.5)
        rec.send_signal(signal.SIGINT)
        assert rec.wait(10) == 0
    finally:
        graph.stop([rec])
    # Best effort: what went out before the recorder's side had matched the publisher
    # (the publisher may see the subscription first) is lost, and on a busy machine a
    # message may be now and then; what is recorded came in the order sent, each once.
    got = [sent.index(deserialize_message(r, String)) for r in bag_messages(out)['/chat']]
    assert len(got) >= 10 and got == sorted(set(got)), got
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    offered = meta['topics_with_message_count'][0]['topic_metadata']['offered_qos_profiles']
    assert offered[0]['reliability'] == 'reliable'


def run_play(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([graph.executable('bag_play'), *args], capture_output=True, text=True,
                          timeout=30)


def test_broken_bags_and_bad_arguments_fail_clearly(tmp_path, capsys):
    storage = truncated(SAMPLE_BAGS[0], tmp_path / 'cut', 0.5)
    assert bag_player.main([str(tmp_path / 'cut')]) == 1
    assert str(storage) in capsys.readouterr().err
    assert bag_player.main([str(tmp_path / 'missing')]) == 1
    assert 'missing: no such file' in capsys.readouterr().err
    assert bag_player.main([str(SAMPLE_BAGS[0]), '--remap', 'a=b']) == 2
    assert 'old:=new' in capsys.readouterr().err
    r = run_play([str(promises_more(tmp_path / 'lost')), '--rate', '0',
                  '--wait-subscribers', '0'])
    assert r.returncode == 1 and 'no message of /lost' in r.stderr, r.stderr
    r = run_play([str(SAMPLE_BAGS[0]), '--topics', 'nope', '--wait-subscribers', '0'])
    assert r.returncode == 1 and 'no topic nope' in r.stderr, r.stderr
    assert bag_recorder.main(['-o', str(SAMPLE_BAGS[0]), 'topic']) == 1
    assert 'exists' in capsys.readouterr().err


def test_writer_stores_any_installed_type_in_either_storage(tmp_path):
    """Types outside rosbags' Jazzy store come from their .msg files."""
    from test_msgs.msg import Arrays, Nested
    msgs = [Arrays(string_values=['a', 'b', 'c']), Nested()]
    for storage in STORAGES:
        writer = BagWriter(tmp_path / storage, storage)
        conns = [writer.add_topic(f'/t{k}', f'test_msgs/msg/{type(m).__name__}')
                 for k, m in enumerate(msgs)]
        for k, (conn, msg) in enumerate(zip(conns, msgs)):
            writer.write(conn, 10**18 + k, serialize_message(msg))
        writer.close()
        got = bag_messages(tmp_path / storage)
        assert [deserialize_message(got[f'/t{k}'][0], type(m)) for k, m in enumerate(msgs)] == msgs
