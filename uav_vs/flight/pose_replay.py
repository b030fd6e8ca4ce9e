"""Replay a bag through running node processes and score the poses they publish.

Shared by the ground (ground_replay) and onboard (onboard_replay) evaluations: every
message of the bag is published raw (recorded CDR, recorded stamps) with real rclpy
publishers at the recorded rate, once the nodes subscribe; the poses the nodes publish
are collected by header stamp and matched to the bag's `truth/pose` of the same stamp.
"""
import time
from dataclasses import dataclass, field
from pathlib import Path
from subprocess import Popen
from typing import Callable

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message
from scipy.spatial.transform import Rotation

from uav_vs import graph
from uav_vs.bag.reader import read_messages
from uav_vs.ros.convert import msg_to_pose, stamp_to_ns, yaw_of
from uav_vs.ros.replay import RawPublishers


@dataclass
class Replay:
    poses: dict[int, PoseStamped]        # received, by header stamp (ns)
    truth: dict[int, PoseStamped]        # the bag's truth (truth/pose), by stamp
    return_codes: list[int] = field(default_factory=list)


@dataclass
class PoseErrors:
    """Errors of the received poses that have a truth of the same stamp, in stamp order."""

    stamps: np.ndarray               # ns
    position_m: np.ndarray           # |p - p_true|
    yaw_deg: np.ndarray              # yaw - true yaw, wrapped to (-180, 180]
    attitude_deg: np.ndarray         # rotation angle of R_true^T R
    truth_positions: np.ndarray      # (n, 3)
    truth_quaternions: np.ndarray    # (n, 4) xyzw


def replay_bag(bag: Path, start_nodes: Callable[[], list[Popen]], pose_topic: str,
               rate: float = 1.0, settle_s: float = 2.0, start_timeout_s: float = 30.0,
               truth_topic: str = 'truth/pose') -> Replay:
    """Read `bag`, start the nodes, feed them the bag, collect `pose_topic`, stop them;
    the truth is the bag's `truth_topic`.

    Publishing starts when every image topic of the bag has a matched subscriber and
    `pose_topic` a matched publisher; rate 0 publishes as fast as possible. Raises
    RuntimeError if a process exits before the end.
    """
    messages = list(read_messages(bag))
    truth = {stamp_to_ns(m.header.stamp): m for m in
             (deserialize_message(b.raw, PoseStamped) for b in messages if b.topic == truth_topic)}
    procs = start_nodes()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('pose_replay', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    poses: dict[int, PoseStamped] = {}
    pose_sub = node.create_subscription(
        PoseStamped, pose_topic, lambda m: poses.setdefault(stamp_to_ns(m.header.stamp), m), 100)
    pubs = RawPublishers(node)
    image_topics = {b.topic: b.msgtype for b in messages if 'image_raw' in b.topic}
    image_pubs = [pubs.publisher(topic, msgtype) for topic, msgtype in image_topics.items()]
    try:
        _wait(executor, lambda: all(p.get_subscription_count() > 0 for p in image_pubs)
              and pose_sub.get_publisher_count() > 0, start_timeout_s, procs)
        pubs.play(messages, rate, lambda: executor.spin_once(timeout_sec=0))
        pubs.wait_for_all_acked(10.0)
        _wait(executor, lambda: len(poses) >= len(truth), settle_s, procs)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        codes = graph.stop(procs)
    return Replay(poses, truth, codes)


def _wait(executor, predicate, timeout: float, procs) -> None:
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        dead = [p.args[0] for p in procs if p.poll() is not None]
        if dead:
            raise RuntimeError(f'node process exited early: {dead}')
        executor.spin_once(timeout_sec=0.05)


def pose_errors(poses: dict[int, PoseStamped], truth: dict[int, PoseStamped]) -> PoseErrors:
    """Position, yaw and full attitude errors of every pose that has a truth."""
    stamps = sorted(s for s in poses if s in truth)
    p, q = _arrays([msg_to_pose(poses[s]) for s in stamps])
    tp, tq = _arrays([msg_to_pose(truth[s]) for s in stamps])
    yaw = np.array([yaw_of(a) - yaw_of(b) for a, b in zip(q, tq)])
    attitude = (Rotation.from_quat(tq).inv() * Rotation.from_quat(q)).magnitude() if stamps else yaw
    return PoseErrors(np.array(stamps, np.int64), np.linalg.norm(p - tp, axis=1),
                      np.degrees(np.arctan2(np.sin(yaw), np.cos(yaw))), np.degrees(attitude),
                      tp, tq)


def _arrays(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """[(position, quaternion), ...] -> positions (n, 3), quaternions (n, 4)."""
    return (np.array([p for p, _ in pairs]).reshape(-1, 3),
            np.array([q for _, q in pairs]).reshape(-1, 4))
