"""Bag replay benchmark: bags/ground_trinocular played at rate 0 into a subscriber.

The bag_play console script (its own process, the project's Fast DDS profile) publishes
the sample bag's 560 messages (12.5 MB, 7.9 s of recording: JPEG images, camera info,
poses) to a subscriber in this process that takes every message raw (KEEP_ALL,
reliable). The replay time runs from the first message received to the last; the
figures are messages/s, MB/s and how many times faster than real time (`x_realtime`,
the bag's duration over the replay time). Target: >= 20x real time, nothing lost.
"""
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from bench.common import report
from uav_vs import graph
from uav_vs.bag.reader import Bag
from uav_vs.ros.replay import message_class

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'ground_trinocular'
RUNS = 3
QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)


def replay_once(topics: dict[str, str], expected: int, log: Path) -> tuple[float, int, int]:
    """One replay: (seconds from first to last message received, messages, bytes)."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('bag_bench', context=ctx)
    arrivals: list[tuple[float, int]] = []
    for topic, msgtype in topics.items():
        node.create_subscription(message_class(msgtype), topic,
                                 lambda raw: arrivals.append((time.perf_counter(), len(raw))),
                                 QOS, raw=True)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    with open(log, 'wb') as out:
        player = subprocess.Popen([graph.executable('bag_play'), str(BAG), '--rate', '0'],
                                  stdout=out, stderr=subprocess.STDOUT)
    try:
        player.wait(60)
        deadline = time.monotonic() + 10
        while len(arrivals) < expected and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        graph.stop([player])
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        spinner.join(5)
    times = [t for t, _ in arrivals]
    return max(times) - min(times), len(arrivals), sum(n for _, n in arrivals)


def replay_throughput() -> None:
    with Bag(BAG) as bag:
        topics = {t: info.msgtype for t, info in bag.topics.items()}
        expected, span_s = bag.message_count, (bag.end_ns - bag.start_ns) / 1e9
    with tempfile.TemporaryDirectory(prefix='uav_vs_bags_') as tmp:
        runs = [replay_once(topics, expected, Path(tmp) / f'play{k}.log') for k in range(RUNS)]
    seconds = np.array([s for s, _, _ in runs])
    med = float(np.median(seconds))
    received, nbytes = min(n for _, n, _ in runs), runs[0][2]
    report('bags', 'bags/replay_throughput', seconds * 1e3, msgs_per_s=round(expected / med),
           mb_per_s=round(nbytes / med / 1e6, 1), x_realtime=round(span_s / med, 1),
           received=received, expected=expected, target_x_realtime=20)


def main() -> None:
    replay_throughput()


if __name__ == '__main__':
    main()
