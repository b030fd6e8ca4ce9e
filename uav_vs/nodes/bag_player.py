"""bag_play: replay a bag with real rclpy publishers of the recorded types.

    bag_play <bag> [--rate R] [--start S] [--duration D] [--loop] [--topics T ...]
             [--remap OLD:=NEW ...] [--clock HZ] [--qos-reliable] [--wait-subscribers S]
             [--ros-args ...]

Every message is published as recorded (raw CDR; ROS 1 bags converted) on a publisher
of its recorded type, offering the recorded reliability and durability (KEEP_ALL
history, so the player itself never drops). Rate 0 publishes as fast as the
subscribers take it, reliably, nothing dropped. Before the first message the player
waits up to --wait-subscribers seconds for every topic to have a subscriber; before it
exits, for every message to be acknowledged. Topics whose type has no Python message
package installed are skipped with a warning. `--clock HZ` publishes the bag time on
/clock (rosgraph_msgs/Clock) for nodes running with use_sim_time.

The storage is the truth: where metadata.yaml promises another time window or other
counts, one warning says so and every stored message plays. A topic name that ROS 2
does not allow (ROS 1 bags may hold `/ORB-SLAM/pose`) is played under a legal one, each
character other than letters, digits, '_' and '/' replaced by '_' and '_' put before a
name token starting with a digit (`/ORB_SLAM/pose`, `/_3d/points`), logged once per
topic; a `--remap` of the topic takes precedence. Exit status: 0 when the replay ran (or
was interrupted), 1 when the bag cannot be played, 2 on bad arguments.
"""
import argparse
import sys
import time
from collections import Counter
from typing import TextIO

import rclpy
from rclpy.duration import Duration
from rclpy.exceptions import InvalidTopicNameException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.validate_topic_name import validate_topic_name
from rosgraph_msgs.msg import Clock

from uav_vs.bag.play import Plan, PlayOptions, parse_remaps, progress_line
from uav_vs.bag.reader import Bag, BagError
from uav_vs.ros.cli import split_ros_args
from uav_vs.ros.convert import ns_to_stamp
from uav_vs.ros.replay import lossless_qos, message_class

ACK_TIMEOUT_S = 30.0
PROGRESS_PERIOD_S = 0.1


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='bag_play', description=__doc__.split('\n')[0])
    p.add_argument('bag', help='rosbag2 folder, .mcap or .db3 file, or ROS 1 .bag file')
    p.add_argument('--rate', type=float, default=1.0,
                   help='speed factor (0: as fast as the subscribers take it)')
    p.add_argument('--start', type=float, default=0.0, help='skip this much bag time, s')
    p.add_argument('--duration', type=float, help='play this much bag time, s')
    p.add_argument('--loop', action='store_true', help='play again and again')
    p.add_argument('--topics', nargs='+', help='play only these topics')
    p.add_argument('--remap', nargs='+', default=[], metavar='OLD:=NEW',
                   help='publish topic OLD under the name NEW')
    p.add_argument('--clock', type=float, default=0.0, metavar='HZ',
                   help='publish the bag time on /clock at this rate')
    p.add_argument('--qos-reliable', action='store_true',
                   help='offer RELIABLE on every topic, whatever was recorded')
    p.add_argument('--wait-subscribers', type=float, default=5.0, metavar='S',
                   help='wait up to S s for every topic to have a subscriber (default 5)')
    return p.parse_args(argv)


class BagPlayer:
    """Publishes a Plan: one publisher per topic whose message type can be imported."""

    def __init__(self, node: Node, plan: Plan, clock_hz: float = 0.0,
                 force_reliable: bool = False) -> None:
        self.node, self.plan = node, plan
        log = node.get_logger()
        self.pubs: dict[str, Publisher] = {}
        for topic, info in list(plan.topics.items()):
            try:
                cls = message_class(info.msgtype)
            except (ImportError, AttributeError, ValueError):
                log.warn(f'skipping {topic}: no Python message type {info.msgtype} '
                         f'(install its package)')
                del plan.topics[topic]
                continue
            qos = lossless_qos(info.offer, force_reliable or plan.options.rate == 0)
            self.pubs[topic] = node.create_publisher(cls, plan.name(topic), qos)
        if not self.pubs:
            raise BagError(f'{plan.bag.path}: nothing to play')
        self.clock_period = 1.0 / clock_hz if clock_hz > 0 else None
        self.clock_pub = node.create_publisher(
            Clock, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        ) if self.clock_period else None
        self.published: Counter[str] = Counter()

    def wait_for_subscribers(self, timeout_s: float) -> list[str]:
        """Wait until every topic has a matched subscription; return those that have none."""
        deadline = time.monotonic() + timeout_s
        while True:
            alone = [t for t, p in self.pubs.items() if p.get_subscription_count() == 0]
            if not alone or time.monotonic() >= deadline or not rclpy.ok(context=self.node.context):
                return alone
            time.sleep(0.02)

    def play(self, progress: TextIO | None = None) -> bool:
        """Publish every message when due; False if interrupted (SIGINT, SIGTERM).

        `progress` gets a progress bar, redrawn every PROGRESS_PERIOD_S.
        """
        ctx = self.node.context
        rate, start_ns = self.plan.options.rate, self.plan.start_ns
        t0 = time.monotonic()
        next_clock = next_progress = 0.0
        bag_ns = start_ns
        try:
            for due, msg in self.plan.schedule():
                while True:
                    now = time.monotonic() - t0
                    if rate > 0:
                        bag_ns = self.plan.bag_time_ns(now)
                    if self.clock_pub and now >= next_clock:
                        self.clock_pub.publish(Clock(clock=ns_to_stamp(bag_ns)))
                        next_clock = now + self.clock_period
                    if progress and now >= next_progress:
                        progress.write('\r' + progress_line(bag_ns - start_ns, self.plan.span_ns,
                                                            self.published.total()))
                        progress.flush()
                        next_progress = now + PROGRESS_PERIOD_S
                    if not rclpy.ok(context=ctx):
                        return False
                    if now >= due:
                        break
                    wake = min(due, next_clock if self.clock_pub else due,
                               next_progress if progress else due)
                    time.sleep(min(max(wake - now, 0.0), 0.1))
                self.pubs[msg.topic].publish(msg.raw)
                self.published[msg.topic] += 1
                if rate == 0:
                    bag_ns = msg.t_ns
            bag_ns = start_ns + self.plan.span_ns
            return True
        finally:
            if progress:
                progress.write('\r' + progress_line(bag_ns - start_ns, self.plan.span_ns,
                                                    self.published.total()) + '\n')

    def wait_for_acks(self, timeout_s: float) -> bool:
        """Block until every subscriber acknowledged every message (reliable topics)."""
        deadline = time.monotonic() + timeout_s
        return all(p.wait_for_all_acked(Duration(seconds=max(deadline - time.monotonic(), 0.0)))
                   for p in self.pubs.values())


def check_topic_name(name: str, what: str) -> None:
    """Raise ValueError naming `what` when `name` is not a legal ROS 2 topic name."""
    try:
        validate_topic_name(name)
    except InvalidTopicNameException as err:
        reason = str(err).splitlines()[0].removeprefix('Invalid topic name: ').rstrip(':')
        raise ValueError(f'{what} {name!r} is not a ROS 2 topic name ({reason})') from None


def main(argv: list[str] | None = None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = parse_args(own)
    try:
        options = PlayOptions(args.rate, args.start, args.duration, args.loop,
                              tuple(args.topics) if args.topics else None, parse_remaps(args.remap))
        for new in options.remap.values():
            check_topic_name(new, '--remap target')
    except ValueError as err:
        print(f'bag_play: error: {err}', file=sys.stderr)
        return 2
    try:
        bag = Bag(args.bag)
    except BagError as err:
        print(f'bag_play: error: {err}', file=sys.stderr)
        return 1
    rclpy.init(args=['bag_play', *ros_args])
    node = player = None
    done, t0 = False, time.monotonic()
    try:
        # Without its own /rosout publisher, a replayed /rosout carries the bag's messages only.
        node = rclpy.create_node('bag_player', enable_rosout=False)
        log = node.get_logger()
        if bag.metadata_mismatch:
            log.warn(bag.metadata_mismatch)
        player = BagPlayer(node, Plan(bag, options), args.clock, args.qos_reliable)
        for topic, name in player.plan.renamed.items():
            if topic in player.pubs:
                log.info(f'topic {topic} played as {name}')
        alone = player.wait_for_subscribers(args.wait_subscribers)
        if alone:
            log.info(f'no subscriber yet on {", ".join(player.plan.name(t) for t in alone)}')
        window = f' from {options.start_s:g} s' + (f' for {options.duration_s:g} s'
                                                   if options.duration_s else '')
        log.info(f'playing {len(player.pubs)} topics at rate {options.rate:g}{window}'
                 f'{", in a loop" if options.loop else ""}')
        t0 = time.monotonic()
        done = player.play(sys.stdout if sys.stdout.isatty() else None)
        if done and not player.wait_for_acks(ACK_TIMEOUT_S):
            log.warn(f'not every message was acknowledged within {ACK_TIMEOUT_S} s')
    except BagError as err:
        print(f'bag_play: error: {err}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    except Exception:
        if rclpy.ok():
            raise               # otherwise a signal shut ROS down in the middle of a call
    finally:
        bag.close()
        if player:
            counts = ', '.join(f'{player.plan.name(t)}: {n}' for t, n in player.published.items())
            node.get_logger().info(
                f'{"published" if done else "interrupted after"} {player.published.total()} '
                f'messages in {time.monotonic() - t0:.2f} s ({counts})')
        if node:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
