"""bag_record: record topics to a rosbag2 folder without deserializing them.

    bag_record -o <dir> [--storage mcap|sqlite3] [--best-effort] topic [topic ...]
               [--ros-args ...]

Each topic is subscribed once a publisher of it appears (raw CDR, KEEP_ALL, reliable
and transient local when every publisher offers them, so nothing is lost at image
rates; best effort with --best-effort, as a node on the far end of a lossy link
subscribes: what arrives is recorded when it arrives, nothing is sent again) and
recorded under its fully qualified name with the receive time of the node's clock, its
message definition, the type hash computed from that definition (a warning
if the publishers announce another) and the QoS its publishers offered. SIGINT or
SIGTERM stops the recording and writes metadata.yaml (rosbag2 version 9, as Jazzy's
`ros2 bag` reads it). A topic name that ROS 2 does not allow stops it with one FATAL
line before anything is written. Exit status: 0 after a recording, 1 when the bag
cannot be written, 2 on bad arguments.
"""
import argparse
import sys
from functools import partial

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy
from rosbags.interfaces import Connection

from uav_vs.bag.reader import BagError, record_request
from uav_vs.bag.writer import STORAGES, BagWriter
from uav_vs.nodes.bag_player import check_topic_name
from uav_vs.ros.cli import split_ros_args
from uav_vs.ros.replay import bag_qos, lossless_qos, message_class

DISCOVERY_PERIOD_S = 0.1


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='bag_record', description=__doc__.split('\n')[0])
    p.add_argument('-o', '--output', required=True, help='bag folder to create (must not exist)')
    p.add_argument('--storage', choices=sorted(STORAGES), default='mcap', help='storage format')
    p.add_argument('--best-effort', action='store_true',
                   help='subscribe best effort, whatever the publishers offer')
    p.add_argument('topics', nargs='+', help='topics to record')
    return p.parse_args(argv)


class BagRecorder(Node):
    """Subscribes each topic as soon as it has a publisher and writes what arrives."""

    def __init__(self, writer: BagWriter, topics: list[str], best_effort: bool = False) -> None:
        super().__init__('bag_recorder')
        self._writer, self._best_effort = writer, best_effort
        self._pending = {self.resolve_topic_name(t) for t in topics}
        self._timer = self.create_timer(DISCOVERY_PERIOD_S, self._discover)
        self._discover()

    def _discover(self) -> None:
        for topic in sorted(self._pending):
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            msgtype = publishers[0].topic_type
            self._pending.discard(topic)
            try:
                cls = message_class(msgtype)
                offered = [bag_qos(p.qos_profile) for p in publishers]
                conn = self._writer.add_topic(topic, msgtype, offered)
            except (ImportError, AttributeError, BagError) as err:
                self.get_logger().error(f'not recording {topic}: {err}')
                continue
            announced = str(publishers[0].topic_type_hash)
            if announced.startswith('RIHS01_') and conn.digest != announced:
                self.get_logger().warn(f'{topic}: its publishers announce type hash {announced}, '
                                       f'the definition stored hashes to {conn.digest}')
            qos = lossless_qos(record_request(offered))
            if self._best_effort:
                qos.reliability = ReliabilityPolicy.BEST_EFFORT
            self.create_subscription(cls, topic, partial(self._write, conn), qos, raw=True)
            self.get_logger().info(f'recording {topic} ({msgtype})')
        if not self._pending:
            self._timer.cancel()

    def _write(self, conn: Connection, raw: bytes) -> None:
        self._writer.write(conn, self.get_clock().now().nanoseconds, raw)


def main(argv: list[str] | None = None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = parse_args(own)
    try:
        for topic in args.topics:
            check_topic_name(topic, 'topic')
    except ValueError as err:
        rclpy.logging.get_logger('bag_recorder').fatal(str(err))
        return 2
    try:
        writer = BagWriter(args.output, args.storage)
    except BagError as err:
        print(f'bag_record: error: {err}', file=sys.stderr)
        return 1
    rclpy.init(args=['bag_record', *ros_args])
    node = None
    try:
        node = BagRecorder(writer, args.topics, args.best_effort)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise               # otherwise a signal shut ROS down while the node was starting
    finally:
        writer.close()
        counts = ', '.join(f'{t}: {n}' for t, n in sorted(writer.counts.items()))
        print(f'bag_record: recorded {writer.counts.total()} messages to {writer.path} '
              f'({counts or "nothing"})', file=sys.stderr)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
