"""Fuzz: every node's subscriptions take storms of generated messages (Hypothesis).

One long-lived process of the node under test, started from its console script with its
params file, and no other node (one node's outputs are another's inputs). Each Hypothesis
example is a storm of 20-80 messages, sent in windows the node has room for (no message
is lost, so every one can be accounted for); after each window the process must still
run. After a case's storms:
- the node's refusal counters (`malformed`, and the stamp refusals some nodes count
  apart) cover at least every message that must be refused, and no more than those
  that may be;
- the node's answer on a fixed valid input, stamped now, equals a fresh node's answer
  on the same input (computed when the process started);
- what it published meanwhile stays within its documented limits (controller), and
  what reached the simulated vehicle is finite and within the relay's limits.

KNOWN_DEFECTS names the (node, case) pairs that fail on the current code; they are
xfail(strict=True), so each must be removed from the set when its fix lands.
One summary line per case is printed into pytest's output.
"""
import math
import os
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PolygonStamped, PoseStamped, TwistStamped
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

import fuzz_messages as fm
from conftest import REPO, wait_for
from uav_vs import graph
from uav_vs.ros.convert import (bgr_to_compressed, bgr_to_image, msg_to_twist, ns_to_stamp,
                                points_to_polygon, polygon_to_array, pose_to_msg, stamp_to_ns,
                                twist_to_msg)

KNOWN_DEFECTS: set[tuple[str, str]] = set()

RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
STORM = dict(min_size=20, max_size=80)
ONBOARD = REPO / 'config' / 'onboard.yaml'
GROUND = REPO / 'config' / 'ground_trinocular.yaml'


def now_ns() -> int:
    return time.time_ns()


# ------------------------------------------------------------------ probe

class Probe:
    """The test side: a node spinning in a thread, and the diagnostics it hears."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('fuzz_probe', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.diags: dict[str, list[tuple[int, dict]]] = defaultdict(list)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            entry = (stamp_to_ns(msg.header.stamp), {kv.key: kv.value for kv in status.values})
            history = self.diags[status.name]
            history.append(entry)
            del history[:-20]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.ctx)
        self.thread.join(timeout=5)


# ------------------------------------------------------------------ rigs

@dataclass
class Tally:
    """One case's account: messages sent, and how many must (may) be refused."""

    sent: int = 0
    must: int = 0
    may: int = 0
    crashes: list[str] = field(default_factory=list)


class Rig:
    """One node process under fuzz: its inputs, counters and valid answer."""

    executable = ''
    status = ''                    # its /diagnostics status name
    topics: dict[str, tuple[type, int, tuple[str, ...]]] = {}   # type, window, counters
    refusals = ('malformed', 'future', 'old_stamps', 'future_stamps')
    # case -> the counter of every message the node took in it, where it has one: a message
    # of a best-effort input lost on the way is then told from one taken and not refused.
    received: dict[str, str] = {}
    # A node whose answer depends on the frames it has taken (a tracker's keyframe) starts
    # afresh for each case: one case's storm may move it, several add up.
    fresh_each_case = False

    def __init__(self, probe: Probe, log_dir: Path) -> None:
        self.probe, self.node, self.log_dir = probe, probe.node, log_dir
        self.proc = None
        self.starts = 0
        self.last_stamp = 0
        self.pubs = {t: self.node.create_publisher(kind, t, RELIABLE)
                     for t, (kind, _, _) in self.topics.items()}
        self.reference = None

    def args(self) -> list[str]:
        raise NotImplementedError

    def start(self) -> None:
        if self.proc is not None:
            graph.stop([self.proc])
        self.starts += 1
        self.probe.diags.pop(self.status, None)      # the last process's
        # Only the storm may feed the node: any other publisher's messages (another rig's
        # node still running) would be counted as taken in place of storm messages lost.
        assert wait_for(lambda: all(self.node.count_publishers(t) == 1 for t in self.pubs), 10), \
            {t: self.node.count_publishers(t) for t in self.pubs}
        self.proc = graph.start(self.executable, self.args(), self.log_dir,
                                f'{self.executable}-{self.starts}')
        assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values())
                        or self.proc.poll() is not None, 30), self.log()
        assert wait_for(lambda: self.values() or self.proc.poll() is not None, 30), self.log()
        self.ready()
        answer = self.answer()
        assert answer is not None, f'a fresh {self.executable} gave no answer\n{self.log()}'
        if self.reference is None:
            self.reference = answer
        else:                      # every fresh process answers alike
            assert self.same(answer, self.reference), (answer, self.reference)

    def ready(self) -> None:
        """Anything the node needs before it answers (a link, a setpoint)."""

    def stop(self) -> None:
        if self.proc is not None:
            graph.stop([self.proc])
            self.proc = None

    def close(self) -> None:
        """Stop the node and withdraw the storm's publishers."""
        self.stop()
        for pub in self.pubs.values():
            self.node.destroy_publisher(pub)

    def log(self) -> str:
        path = self.log_dir / f'{self.executable}-{self.starts}.log'
        return path.read_text(errors='replace')[-3000:] if path.exists() else ''

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    # ---------------------------------------------------------- counters
    def values(self) -> dict:
        history = self.probe.diags.get(self.status)
        return history[-1][1] if history else {}

    def count(self, keys) -> int:
        values = self.values()
        return sum(int(values.get(k, 0)) for k in keys)

    def settle(self, since_ns: int, target: int | None, keys) -> None:
        """Wait until the node has accounted for what was sent: its counters reach
        `target`, or, for messages no counter accounts for (`target` None), two
        diagnostics stamped after `since_ns` came (its executor has cycled since)."""
        def done() -> bool:
            if not self.alive():
                return True
            if target is not None:
                return self.count(keys) >= target
            later = [s for s, _ in self.probe.diags.get(self.status, []) if s > since_ns]
            return len(later) >= 2
        wait_for(done, 10)

    # ---------------------------------------------------------- sending
    def stamp(self, spec: fm.Stamp) -> Time:
        if spec.fixed is not None:
            return Time(sec=spec.fixed[0], nanosec=spec.fixed[1])
        if spec.offset:
            return ns_to_stamp(now_ns() + int(spec.offset * 1e9))
        self.last_stamp = max(now_ns(), self.last_stamp + 1)
        return ns_to_stamp(self.last_stamp)

    def stamp_verdict(self, topic: str, stamp: Time) -> bool | None:
        """Must a message on `topic` be refused for its stamp alone? (vision nodes: no)"""
        return False

    def send(self, item: fm.Fuzzed) -> bool | None:
        verdict = item.bad
        if item.stamp is not None:
            item.payload.header.stamp = self.stamp(item.stamp)
            verdict = fm.either(verdict, self.stamp_verdict(item.topic, item.payload.header.stamp))
        self.pubs[item.topic].publish(item.payload)
        return verdict

    def storm(self, items: list[fm.Fuzzed], tally: Tally) -> None:
        """Send the storm in windows; after each one the node must be running."""
        k = 0
        while k < len(items) and self.alive():
            window = min(self.topics[item.topic][1] for item in items[k:k + 8])
            chunk = items[k:k + window]
            keys = sorted({key for item in chunk for key in self.topics[item.topic][2]})
            accountable = all(self.topics[item.topic][2] for item in chunk)
            before = self.count(keys)
            for item in chunk:
                verdict = self.send(item)
                tally.sent += 1
                tally.must += verdict is True
                tally.may += verdict is not False
            self.settle(now_ns(), before + len(chunk) if accountable else None, keys)
            if not self.alive():
                tally.crashes.append(describe(chunk))
            k += window

    # ---------------------------------------------------------- answer
    def answer(self):
        raise NotImplementedError

    def same(self, a, b) -> bool:
        return a is not None and b is not None and np.allclose(a, b, atol=1e-6, equal_nan=True)

    def checks(self) -> list[str]:
        """What else went wrong during the case ([] when nothing did)."""
        return []


def describe(chunk: list[fm.Fuzzed]) -> str:
    """The window that killed a node, short enough to read."""
    lines = []
    for item in chunk:
        p = item.payload
        if isinstance(p, bytes):
            lines.append(f'{item.topic}: {len(p)} serialized bytes {p[:24]!r}...')
        elif isinstance(p, Image):
            lines.append(f'{item.topic}: Image {p.width}x{p.height} {p.encoding[:16]!r} step '
                         f'{p.step}, {len(p.data)} bytes, stamp {item.stamp}')
        elif isinstance(p, CompressedImage):
            lines.append(f'{item.topic}: CompressedImage {p.format[:16]!r}, {len(p.data)} '
                         f'bytes {bytes(p.data[:12])!r}, stamp {item.stamp}')
        else:
            lines.append(f'{item.topic}: {str(p)[:300]}, stamp {item.stamp}')
    return '\n'.join(lines)


class Outputs:
    """Messages of one output topic by stamp."""

    def __init__(self, node, kind, topic: str, qos=RELIABLE) -> None:
        self.by_stamp: dict[int, object] = {}
        self.all: list = []
        node.create_subscription(kind, topic, self._on, qos)

    def _on(self, msg) -> None:
        self.by_stamp[stamp_to_ns(msg.header.stamp)] = msg
        self.all.append(msg)
        del self.all[:-5000]


class VisionRig(Rig):
    """An image node: `image_raw` (taken serialized) and `image_raw/compressed`."""

    prefix = ''
    size: tuple[int, int] | None = (640, 480)
    repeats = 3
    output: tuple[type, str] = (PolygonStamped, '')

    def __init__(self, probe, log_dir) -> None:
        counters = ('frames', 'malformed', 'stale', 'future')
        self.topics = {f'{self.prefix}image_raw': (Image, 8, counters),
                       f'{self.prefix}image_raw/compressed': (CompressedImage, 8, counters)}
        super().__init__(probe, log_dir)
        self.out = Outputs(self.node, *self.output)

    def frame(self) -> np.ndarray:
        """The fixed valid input (BGR, of the node's size)."""
        raise NotImplementedError

    def fuzz_frame(self) -> np.ndarray:
        return self.frame()

    def valid(self) -> list[tuple[str, object]]:
        img = self.fuzz_frame()
        raw, comp = f'{self.prefix}image_raw', f'{self.prefix}image_raw/compressed'
        return [(raw, bgr_to_image(img, Header(frame_id='camera_optical'))),
                (comp, bgr_to_compressed(img, Header(frame_id='camera_optical')))]

    def cases(self) -> dict[str, st.SearchStrategy]:
        raw, comp = f'{self.prefix}image_raw', f'{self.prefix}image_raw/compressed'
        img = self.fuzz_frame()
        return {
            'serialized': fm.serialized_images(self.valid()[0][1], raw),
            'image_fields': fm.raw_images(self.size, img, raw),
            'compressed': fm.compressed_images(self.size, img, comp),
            'stamps': fm.stamped_frames(self.valid()),
        }

    def answer(self):
        """The output for the fixed frame, sent `repeats` times stamped now."""
        raw = f'{self.prefix}image_raw'
        stamps = []
        for _ in range(self.repeats):
            msg = bgr_to_image(self.frame(), Header(stamp=self.stamp(fm.NOW),
                                                    frame_id='camera_optical'))
            stamps.append(stamp_to_ns(msg.header.stamp))
            self.pubs[raw].publish(msg)
            wait_for(lambda: stamps[-1] in self.out.by_stamp or not self.alive(), 5)
        last = self.out.by_stamp.get(stamps[-1])
        return None if last is None else self.read(last)

    def read(self, msg) -> np.ndarray:
        return polygon_to_array(msg)


class CamshiftRig(VisionRig):
    executable, status, prefix = 'camshift_node', '/cam1/camshift_node', '/cam1/'
    output = (PolygonStamped, '/cam1/landmarks')
    repeats = 8                    # the colour histogram is smoothed over frames

    def args(self):
        return ['--params-file', str(GROUND), '-r', '__ns:=/cam1', '-p', 'camera:=cam1',
                '-p', 'camshift.image_qos:=reliable', '-p', 'camshift.diagnostics_period:=0.05']

    def frame(self):
        if not hasattr(self, '_frame'):
            from uav_vs.sim.ground_scene import GroundScene, figure_eight
            from uav_vs.vision.ground_config import load_ground_config, read_params_file
            scene = GroundScene(load_ground_config(read_params_file(GROUND)), seed=1)
            self._frame = scene.render(figure_eight(3.0))[0][0]
        return self._frame

    def same(self, a, b):
        return (a is not None and b is not None and a.shape == b.shape
                and np.allclose(a[:, :2], b[:, :2], atol=0.5, equal_nan=True)
                and np.allclose(a[:, 2], b[:, 2], atol=0.05, equal_nan=True))


class HomographyRig(VisionRig):
    executable, status, prefix = 'homography_pose_node', '/homography_pose_node', '/onboard/'
    output = (PoseStamped, '/onboard/pose')
    fresh_each_case = True

    def args(self):
        return ['--params-file', str(ONBOARD), '-p', 'homography_pose.image_qos:=reliable',
                '-p', 'homography_pose.diagnostics_period:=0.05']

    def frame(self):
        if not hasattr(self, '_frame'):
            from uav_vs.sim.onboard_scene import OnboardScene
            from uav_vs.vision.ground_config import read_params_file
            from uav_vs.vision.onboard_config import load_onboard_config
            cfg = load_onboard_config(read_params_file(ONBOARD))
            scene = OnboardScene(cfg.camera, cfg.camera_to_body, seed=1)
            self._frame = scene.render(np.eye(3), np.array([0.0, 0.0, 1.0]))   # init.* pose
        return self._frame

    def same(self, a, b) -> bool:
        """Within 2 cm (2 % of the 1 m height) and ~1 deg of each other: a storm's frames that
        decode (a re-encoded or corrupted JPEG of the scene) may become the keyframe, whose
        error the poses after it carry; a wrong answer is metres or tens of degrees off."""
        return (a is not None and b is not None and np.allclose(a[:3], b[:3], atol=0.02)
                and np.allclose(a[3:], b[3:], atol=0.01))

    def read(self, msg):
        p, o = msg.pose.position, msg.pose.orientation
        return np.array([p.x, p.y, p.z, abs(o.w), o.x * np.sign(o.w), o.y * np.sign(o.w),
                         o.z * np.sign(o.w)])


class TargetRig(VisionRig):
    executable, status, prefix = 'target_tracker_node', '/target_tracker_node', '/onboard/'
    output = (PolygonStamped, '/onboard/target')
    size = None                    # any size
    repeats = 1

    def args(self):
        return ['--params-file', str(ONBOARD),
                '-p', f"target.template:={REPO / 'uav_vs' / 'sim' / 'assets' / 'box.png'}",
                '-p', 'target.image_qos:=reliable', '-p', 'target.diagnostics_period:=0.05']

    def frame(self):
        if not hasattr(self, '_frame'):
            from test_onboard_nodes import pasted_box
            self._frame = pasted_box()[0]
        return self._frame

    def fuzz_frame(self):          # small: SIFT on a full frame takes ~0.2 s
        return self.frame()[200:272, 280:376]


class TrinocularRig(Rig):
    executable, status = 'trinocular_pose_node', '/trinocular_pose_node'
    cameras = ['cam1', 'cam2', 'cam3']

    def __init__(self, probe, log_dir):
        self.topics = {f'/{c}/landmarks': (PolygonStamped, 8, ()) for c in self.cameras}
        super().__init__(probe, log_dir)
        from uav_vs.vision.ground_config import load_ground_config, read_params_file
        cfg = load_ground_config(read_params_file(GROUND))
        self.n_points = len(cfg.landmark_names)
        yaw, position = 2.5, np.array([0.4, -0.3, 1.2])
        c, s = math.cos(yaw), math.sin(yaw)
        world = cfg.layout @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + position
        self.pixels = [np.column_stack([cam.project(world), np.ones(self.n_points)])
                       for cam in cfg.cameras]
        self.out = Outputs(self.node, PoseStamped, '/ground/pose')

    def args(self):
        return ['--params-file', str(GROUND), '-p', 'trinocular.diagnostics_period:=0.05']

    def landmarks(self, k: int) -> PolygonStamped:
        return points_to_polygon(self.pixels[k], Header(frame_id=f'{self.cameras[k]}_optical'))

    def cases(self):
        valid = [(f'/{c}/landmarks', self.landmarks(k)) for k, c in enumerate(self.cameras)]
        return {'landmark_fields': fm.polygons(list(self.topics), self.n_points),
                'stamps': fm.stamped_frames(valid)}

    def answer(self):
        time.sleep(0.05)           # past the storm's stamps by more than the sync tolerance
        stamp = self.stamp(fm.NOW)
        for k, c in enumerate(self.cameras):
            msg = self.landmarks(k)
            msg.header.stamp = stamp
            self.pubs[f'/{c}/landmarks'].publish(msg)
        key = stamp_to_ns(stamp)
        wait_for(lambda: key in self.out.by_stamp or not self.alive(), 5)
        msg = self.out.by_stamp.get(key)
        return None if msg is None else HomographyRig.read(self, msg)


class ControllerRig(Rig):
    executable, status = 'fuzzy_controller_node', '/fuzzy_controller_node'
    topics = {'/ground/pose': (PoseStamped, 8, ('measurements', 'malformed', 'old_stamps',
                                                'future_stamps')),
              '/setpoint': (PoseStamped, 8, ())}
    limits = (1.0, 0.5, 0.8)       # config/fuzzy_controller.yaml controller.max_*

    def __init__(self, probe, log_dir):
        super().__init__(probe, log_dir)
        self.cmds = Outputs(self.node, TwistStamped, '/cmd_vel')
        self.checked = 0

    def args(self):
        return ['--params-file', str(REPO / 'config' / 'fuzzy_controller.yaml'),
                '-p', 'controller.enabled:=true', '-p', 'controller.diagnostics_period:=0.05']

    def cases(self):
        fresh = st.builds(lambda s: fm.Fuzzed('/ground/pose', pose_to_msg(
            [0.2, -0.1, 1.0], [0.0, 0.0, 0.0, 1.0], Header(frame_id='world')), None, s),
            fm.stamps())
        return {'pose_fields': fm.poses('/ground/pose', sane=True),
                'setpoint_fields': fm.poses('/setpoint'), 'stamps': fresh}

    def stamp_verdict(self, topic, stamp):
        """A pose stamped 0, 5 s behind the clock or 5 s ahead must not drive it; one
        stamped now must (the node's own tolerances lie between)."""
        if topic != '/ground/pose':
            return False
        ns, now = stamp_to_ns(stamp), now_ns()
        if ns <= 0 or abs(ns - now) > 5e9:
            return True
        return False if now - 5e7 <= ns <= now else None

    def answer(self):
        self.pubs['/setpoint'].publish(pose_to_msg([1.0, 0.5, 1.2], [0.0, 0.0, math.sin(0.15),
                                                                     math.cos(0.15)],
                                                   Header(frame_id='world')))
        time.sleep(0.1)
        for _ in range(40):        # 2 s: the error-rate filter forgets a jump of 1e6 m
            stamp = self.stamp(fm.NOW)
            self.pubs['/ground/pose'].publish(pose_to_msg([0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0],
                                                          Header(stamp=stamp, frame_id='world')))
            time.sleep(0.05)
        key = stamp_to_ns(stamp)
        wait_for(lambda: key in self.cmds.by_stamp or not self.alive(), 5)
        msg = self.cmds.by_stamp.get(key)
        return None if msg is None else np.concatenate(msg_to_twist(msg))

    def same(self, a, b) -> bool:    # to 1 mm/s: the D term's filter forgets slowly
        return a is not None and b is not None and np.allclose(a, b, atol=1e-3)

    def checks(self):
        """Every command sent meanwhile is finite and within controller.max_*."""
        bad = []
        for msg in self.cmds.all[self.checked:]:
            v, w = msg_to_twist(msg)
            h, z, yaw = self.limits
            if not (np.isfinite([*v, *w]).all() and math.hypot(v[0], v[1]) <= h + 1e-9
                    and abs(v[2]) <= z + 1e-9 and abs(w[2]) <= yaw + 1e-9):
                bad.append(f'cmd_vel {v.tolist()} {w.tolist()}')
        self.checked = len(self.cmds.all)
        return bad[:5]


class RelayRig(Rig):
    executable, status = 'mavlink_relay_node', '/mavlink_relay_node'
    topics = {'/cmd_vel': (TwistStamped, 8, ('cmd_vel',)),
              '/ground/pose': (PoseStamped, 1, ('vision', 'malformed'))}
    received = {'cmd_vel': 'cmd_vel'}
    # config/mavlink_relay.yaml limits.*: max_speed, max_climb, max_descent, max_yaw_rate
    limits = (2.0, 1.0, 0.7, 1.0)

    def __init__(self, probe, log_dir):
        super().__init__(probe, log_dir)
        self.vehicle = SpyVehicle()
        self.since = time.monotonic()

    def args(self):
        return ['--params-file', str(REPO / 'config' / 'mavlink_relay.yaml'),
                '-p', f'connection:=udpout:127.0.0.1:{self.vehicle.address[1]}',
                '-p', 'vision_pose_topic:=ground/pose', '-p', 'diagnostics_period:=0.05']

    def ready(self):
        assert wait_for(lambda: self.values().get('link') == 'connected', 20), self.values()

    def stop(self):
        super().stop()
        self.vehicle.stop()

    def cases(self):
        return {'cmd_vel': fm.twists('/cmd_vel'), 'vision_pose': fm.poses('/ground/pose')}

    def answer(self):
        # Each input is sent again until it shows at the vehicle: a restarted relay's
        # subscriptions may not have matched yet (the dead process's still count a while).
        command = twist_to_msg([0.3, 0.4, 0.2], [0.0, 0.0, 0.1], Header(frame_id='world'))
        t0 = time.monotonic()

        def ours():                # NED north 0.4, east 0.3, down -0.2 (not a hover's zero)
            return [t for t in self.vehicle.targets(since=t0)
                    if np.allclose(t.velocity, (0.4, 0.3, -0.2), atol=1e-6)]
        self._until(ours, self.pubs['/cmd_vel'], command)
        targets = ours()
        stamp = self.stamp(fm.NOW)
        usec = stamp_to_ns(stamp) // 1000     # the relay rounds it through a float
        pose = pose_to_msg([1.0, 2.0, 3.0], [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)],
                           Header(stamp=stamp, frame_id='world'))
        self._until(lambda: any(abs(m.usec - usec) <= 2 for m in self.vehicle.vision()),
                    self.pubs['/ground/pose'], pose)
        vision = [m for m in self.vehicle.vision() if abs(m.usec - usec) <= 2]
        if not targets or not vision:
            return None
        t, v = targets[-1], vision[-1]
        return np.array([*t.velocity, t.yaw_rate, t.frame, v.x, v.y, v.z, v.roll, v.pitch, v.yaw])

    def _until(self, seen, pub, msg, timeout: float = 5.0) -> None:
        end = time.monotonic() + timeout
        while not seen() and time.monotonic() < end and self.alive():
            pub.publish(msg)
            wait_for(seen, 0.1)

    def checks(self):
        """What reached the vehicle is finite and within the relay's limits."""
        speed, climb, descent, yaw_rate = self.limits
        bad = []
        for t in self.vehicle.targets(since=self.since):
            vn, ve, vd = t.velocity
            if not (all(map(math.isfinite, (*t.velocity, t.yaw_rate)))
                    and math.hypot(vn, ve) <= speed * (1 + 1e-6)
                    and -climb * (1 + 1e-6) <= vd <= descent * (1 + 1e-6)
                    and abs(t.yaw_rate) <= yaw_rate * (1 + 1e-6)):
                bad.append(f'velocity target {t.velocity}, yaw rate {t.yaw_rate}')
        for m in self.vehicle.vision(since=self.since):
            values = [m.x, m.y, m.z, m.roll, m.pitch, m.yaw, *m.covariance]
            if not all(map(math.isfinite, values)):
                bad.append(f'VISION_POSITION_ESTIMATE {values[:6]}')
        self.since = time.monotonic()
        return bad[:5]


class SpyVehicle:
    """The simulated copter on a free UDP port, keeping the vision estimates it receives."""

    def __init__(self) -> None:
        from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig
        received = self.received = []

        class Spy(MavlinkVehicle):
            def _handle(self, msg, now):
                if msg.get_type() == 'VISION_POSITION_ESTIMATE':
                    received.append((now, msg))
                super()._handle(msg, now)

        self.sim = Spy(VehicleConfig(connection='udpin:127.0.0.1:0', ready_delay=0.5)).start()
        self.address, self.targets = self.sim.address, self.sim.targets

    def vision(self, since: float = -math.inf) -> list:
        return [m for t, m in list(self.received) if t >= since]

    def stop(self) -> None:
        self.sim.stop()


RIGS = {r.executable: r for r in (CamshiftRig, TrinocularRig, HomographyRig, TargetRig,
                                   ControllerRig, RelayRig)}
CASES = {'camshift_node': ['serialized', 'image_fields', 'compressed', 'stamps'],
         'trinocular_pose_node': ['landmark_fields', 'stamps'],
         'homography_pose_node': ['serialized', 'image_fields', 'compressed', 'stamps'],
         'target_tracker_node': ['serialized', 'image_fields', 'compressed', 'stamps'],
         'fuzzy_controller_node': ['pose_fields', 'setpoint_fields', 'stamps'],
         'mavlink_relay_node': ['cmd_vel', 'vision_pose']}
# Examples per case (default 15: over a thousand messages per node); a storm of valid
# frames costs their processing, so the cases whose storms are mostly decodable images or
# full landmark sets run fewer (25-35 s each at 15 on 2 cores). UAV_VS_FUZZ_SCALE
# multiplies them all (`make fuzz`: ten times as many).
EXAMPLES = {'vision_pose': 8,     # one message at a time (the relay keeps only the newest)
            'stamps': 5, 'image_fields': 10, 'compressed': 8, 'landmark_fields': 8}
SCALE = float(os.environ.get('UAV_VS_FUZZ_SCALE', '1'))


# ------------------------------------------------------------------ fixtures and test

@pytest.fixture(scope='module')
def probe():
    p = Probe()
    yield p
    p.close()


@pytest.fixture(scope='module')
def rigs(probe, tmp_path_factory):
    """One process at a time, of the node under test: started on its first case, closed
    when the cases move to another node (whose inputs may be its outputs: the controller's
    cmd_vel is the relay's); restarted when a case left it dead or failed (so one defect
    does not spill into the next case), and for every case where the node keeps state
    from the frames it took."""
    running: dict[str, Rig] = {}
    log_dir = tmp_path_factory.mktemp('fuzz_logs')

    def get(name: str) -> Rig:
        for other in [n for n in running if n != name]:
            running.pop(other).close()
        rig = running.get(name)
        if rig is None:
            rig = running[name] = RIGS[name](probe, log_dir)
            rig.start()
        elif not rig.alive() or rig.tainted or rig.fresh_each_case:
            rig.start()
        rig.tainted = False
        return rig
    yield get
    for rig in running.values():
        rig.close()


def params():
    for node, cases in CASES.items():
        for case in cases:
            marks = ([pytest.mark.xfail(strict=True, reason='known defect, being fixed')]
                     if (node, case) in KNOWN_DEFECTS else [])
            yield pytest.param(node, case, marks=marks, id=f'{node}-{case}')


@pytest.mark.timeout(240 * max(1.0, SCALE))
@pytest.mark.parametrize('node, case', list(params()))
def test_node_survives_a_storm_and_still_answers(rigs, capsys, node, case):
    rig = rigs(node)
    rig.tainted = True
    tally = Tally()
    keys = rig.refusals
    rig.settle(now_ns(), None, ())      # the last answer's resends, still in flight, counted
    refused_before = rig.count(keys)
    counter = rig.received.get(case)
    received_before = rig.count((counter,)) if counter else 0
    rig.checks()

    @settings(max_examples=max(1, round(EXAMPLES.get(case, 15) * SCALE)), deadline=None,
              database=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(st.lists(rig.cases()[case], **STORM))
    def storm(items):
        rig.storm(items, tally)
        assert rig.alive(), (f'{node} died (exit {rig.proc.returncode}) on a window of:\n'
                             f'{tally.crashes[-1]}\n{rig.log()}')

    try:
        storm()
        rig.settle(now_ns(), None, ())
        refused = rig.count(keys) - refused_before
        # Messages sent that the node never took (best effort under load): they may be
        # ones it had to refuse, but no more than 2 % may go missing. (It may take more:
        # a resend of the answer before, still in flight.)
        taken = rig.count((counter,)) - received_before if counter else tally.sent
        lost = max(0, tally.sent - taken)
        answer = rig.answer()
        equal = rig.same(answer, rig.reference)
        problems = rig.checks()
    finally:
        with capsys.disabled():
            print(f"\nfuzz {node} {case}: {tally.sent} messages sent, {tally.must} must be "
                  f"refused ({tally.may} may), crashes {len(tally.crashes)}", end='')
    with capsys.disabled():
        print(f', taken {taken}, refused {refused}, lost {lost}, valid answer equal {equal}')
    assert lost <= 0.02 * tally.sent, (lost, tally, rig.values())
    assert tally.must - lost <= refused <= tally.may, (refused, lost, tally, rig.values())
    assert equal, (answer, rig.reference, rig.log())
    assert not problems, problems
    rig.tainted = False
