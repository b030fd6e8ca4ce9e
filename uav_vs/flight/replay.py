"""`make demo BAG=<bag>`: a recorded flight through the open-loop part of the graph, scored
as a closed-loop flight is (uav_vs.flight.report).

What runs depends on what the bag holds, each node a process started from its console
script with its params file, as `ros2 run` would:

    camK/image_raw[/compressed]      three camshift_node + trinocular_pose_node -> ground/pose
    onboard/image_raw[/compressed]   homography_pose_node -> onboard/pose
    setpoint                         fuzzy_controller_node on ground/pose (else onboard/pose),
                                     enabled -> cmd_vel

The bag's inputs (images, camera_info, truth/pose, setpoint, autopilot/odom) are published
raw at their recorded times; what the graph computes (OUTPUTS) is not replayed but made
anew and recorded by a FlightRecorder, as in flight. When the bag holds the flight's own
`onboard/pose` (a bag that uav_vs.flight.scenario recorded), homography_pose_node is initialised
at its first pose and fed from that frame on, as it was in flight; otherwise its params
file's `init.*` apply. Arrival times are mapped to the bag's clock, so the latencies are
those of the replayed graph (meaningful at rate 1).
"""
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped
from rclpy.serialization import deserialize_message
from scipy.spatial.transform import Rotation

from uav_vs import graph
from uav_vs.bag.reader import Bag, BagMessage, read_messages
from uav_vs.flight.ground_replay import ground_graph
from uav_vs.flight.onboard_replay import onboard_graph
from uav_vs.flight.recorder import FlightRecorder, MissionError
from uav_vs.flight.report import CommandTrack, FlightLog
from uav_vs.flight.scenario import Configs
from uav_vs.ros.convert import msg_to_pose, stamp_to_ns
from uav_vs.ros.replay import RawPublishers, message_class
from uav_vs.vision.ground_config import read_params_file

OUTPUTS = ('ground/pose', 'ground/landmarks', 'onboard/pose', 'onboard/target', 'cmd_vel',
           'diagnostics')
CONTROLLER = '/fuzzy_controller_node'


def replay_flight(bag: Path, log_dir: Path, configs: Configs = Configs(), rate: float = 1.0,
                  settle_s: float = 2.0, startup_timeout: float = 60.0) -> FlightLog:
    """Replay `bag` through the nodes its inputs call for; the FlightLog of what they did."""
    cameras = list(read_params_file(configs.ground)['cameras.names'])
    messages = [replace(m, topic=m.topic.lstrip('/')) for m in read_messages(bag)]
    outputs = {*OUTPUTS, *(f'{cam}/landmarks' for cam in cameras)}
    onboard_init = _first_pose(messages, 'onboard/pose')
    inputs = [m for m in messages if m.topic not in outputs
              and not _before(m, 'onboard/', onboard_init)]
    topics = {m.topic for m in inputs}
    if not topics:
        raise MissionError(f'{bag}: no message to replay')
    has = {name: any(t.startswith(f'{name}/image_raw') for t in topics)
           for name in (*cameras, 'onboard')}

    rec = FlightRecorder(cameras[0])
    procs: dict[str, object] = {}
    try:
        ground = any(has[cam] for cam in cameras)
        if ground:
            # A replay must lose no frame: the bag's images go reliably, as in any bag replay.
            procs.update(ground_graph(configs.ground, cameras, log_dir,
                                      ['-p', 'camshift.image_qos:=reliable']))
        if has['onboard']:
            [procs['homography_pose_node']] = onboard_graph(configs.onboard, log_dir,
                                                            _init_args(onboard_init))
        if 'setpoint' in topics:
            source = 'ground' if ground else 'onboard'
            procs['fuzzy_controller_node'] = graph.start('fuzzy_controller_node', [
                '--params-file', str(configs.controller),
                '-p', f'controller.pose_topic:={source}/pose', '-p', 'controller.enabled:=true',
                '-p', 'controller.command_frame:=world',
                '-p', 'controller.max_stamp_age:=0.0'], log_dir)   # the flight's stamps, not now
        pubs = RawPublishers(rec.node)
        images = [pubs.publisher(t, m.msgtype) for t, m in
                  {m.topic: m for m in inputs if '/image_raw' in m.topic}.items()]
        made = [f'/{name}/pose' for name, running in (('ground', ground),
                                                      ('onboard', has['onboard'])) if running]
        _wait(procs, lambda: all(p.get_subscription_count() for p in images)
              and all(rec.node.count_publishers(t) for t in made), startup_timeout)
        if 'fuzzy_controller_node' in procs:
            _wait(procs, lambda: CONTROLLER in rec.reporting, startup_timeout)
        t0 = pubs.play(inputs, rate)
        pubs.wait_for_all_acked(10.0)
        _wait(procs, lambda: False, settle_s, quiet=True)
    finally:
        codes = dict(zip(procs, graph.stop(list(procs.values()))))
        log = rec.log(f'replay of {bag}', setpoints=[], pad=None)
        rec.close()
    log.exit_codes = codes
    log.failed_logs = graph.failed_logs(procs)
    log.onboard_start_ns = onboard_init[0] if onboard_init else None
    scale, t0_bag = (rate if rate > 0 else 1.0), inputs[0].t_ns
    for track in (log.truth, log.ground, log.onboard, log.odom, log.commands):   # to bag time
        track.received = (t0_bag + (track.received - t0) * scale).astype(np.int64)
    return log


def _first_pose(messages: list[BagMessage], topic: str) -> tuple[int, PoseStamped] | None:
    """The stamp and message of the first `topic` pose in the bag, if any."""
    first = next((m for m in messages if m.topic == topic), None)
    if first is None:
        return None
    msg = deserialize_message(first.raw, PoseStamped)
    return stamp_to_ns(msg.header.stamp), msg


def _before(m: BagMessage, prefix: str, first: tuple[int, PoseStamped] | None) -> bool:
    """True for a `prefix` message stamped before the first pose (the node's start)."""
    if first is None or not m.topic.startswith(prefix):
        return False
    msg = deserialize_message(m.raw, message_class(m.msgtype))
    return stamp_to_ns(msg.header.stamp) < first[0]


def _init_args(first: tuple[int, PoseStamped] | None) -> list[str]:
    """homography_pose_node's init.* at the flight's first onboard pose (none: the YAML's)."""
    if first is None:
        return []
    position, q = msg_to_pose(first[1])
    rpy = Rotation.from_quat(q).as_euler('xyz')
    return ['-p', 'init.mode:=pose',
            '-p', 'init.position:=[{:.6f}, {:.6f}, {:.6f}]'.format(*position),
            '-p', 'init.rpy:=[{:.7f}, {:.7f}, {:.7f}]'.format(*rpy)]


def _wait(procs: dict, predicate, timeout: float, quiet: bool = False) -> None:
    """Until predicate() or the timeout (MissionError unless quiet); a node exiting early
    is a MissionError."""
    deadline = time.monotonic() + timeout
    while not predicate():
        dead = [label for label, p in procs.items() if p.poll() is not None]
        if dead:
            raise MissionError(f'{", ".join(dead)} exited early (see the logs)')
        if time.monotonic() > deadline:
            if quiet:
                return
            raise MissionError(f'the graph did not come up within {timeout:.0f} s')
        time.sleep(0.05)


def stamps_from_bag(bag: Path, topic: str, kind: type = PoseStamped) -> np.ndarray:
    """The header stamps (ns) of a bag's messages on `topic`, of type `kind`."""
    with Bag(bag) as b:
        return np.array([stamp_to_ns(deserialize_message(m.raw, kind).header.stamp)
                         for m in b.messages([topic])], np.int64)


def commands_from_bag(bag: Path, topic: str = '/cmd_vel') -> CommandTrack:
    """The cmd_vel of a bag as a CommandTrack, each received when the bag took it."""
    stamps, received, values = [], [], []
    with Bag(bag) as b:
        for m in b.messages([topic]):
            msg = deserialize_message(m.raw, TwistStamped)
            v, w = msg.twist.linear, msg.twist.angular
            stamps.append(stamp_to_ns(msg.header.stamp))
            received.append(m.t_ns)
            values.append((v.x, v.y, v.z, w.z))
    a = np.array(values, dtype=float).reshape(-1, 4)
    return CommandTrack(np.array(stamps, np.int64), np.array(received, np.int64), a[:, :3],
                        a[:, 3])
