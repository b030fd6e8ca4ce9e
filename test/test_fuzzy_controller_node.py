"""fuzzy_controller_node as a process (console script + config/fuzzy_controller.yaml).

Truth: the frame geometry worked out by hand (a vehicle facing north with its setpoint
to the east must be commanded to its right in FLU; a target left of the image centre
must turn the vehicle left), and the node's documented fail-safe rules (zero command
from the first cycle after the measurement is older than the timeout, when disabled or
fed non-finite poses, or poses whose stamps the node's clock cannot believe).
"""
import math
import subprocess
import threading
import time

import numpy as np
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point32, Polygon, PolygonStamped, PoseStamped, TwistStamped
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header
from std_srvs.srv import SetBool

from conftest import REPO, wait_for
from uav_vs.graph import executable
from uav_vs.ros.convert import msg_to_twist, ns_to_stamp, pose_to_msg, stamp_to_ns

CONFIG = REPO / 'config' / 'fuzzy_controller.yaml'
PID_CONFIG = REPO / 'config' / 'fuzzy_controller_pid.yaml'
NODE = '/fuzzy_controller_node'
NORTH = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]     # yaw 90 deg, xyzw
TIMEOUT, PERIOD = 0.3, 1 / 50.0     # controller.timeout and 1 / controller.rate in `start`
# The first zero command must leave the node within one cycle of the timeout expiring
# (the 50 Hz floor timer is what notices it). SLACK covers what lies between the probe's
# last publish and the node's check: the pose's way to the node (~1 ms over shared
# memory) and the wake-up of the node's timer and executor on a loaded 2-core machine
# (a few scheduler slices of ~10 ms, at worst). 0.06 s = 3 cycles: a node that lagged
# several cycles, or timed the timeout from anything but the last pose, fails.
SLACK = 0.06


class Probe:
    def __init__(self, node):
        self.node = node
        self.cmds: list[tuple[float, TwistStamped]] = []
        self.diag: dict[str, str] = {}
        node.create_subscription(TwistStamped, '/cmd_vel',
                                 lambda m: self.cmds.append((time.monotonic(), m)), 50)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)
        self.pose = node.create_publisher(PoseStamped, '/ground/pose', 10)
        self.setpoint = node.create_publisher(PoseStamped, '/setpoint', 10)
        self.target = node.create_publisher(PolygonStamped, '/onboard/target', 10)
        self.enable = node.create_client(SetBool, '/controller/enable')
        self.stop = threading.Event()
        self.last_sent = math.nan           # wall time (the node's clock) of the last measurement sent
        self.sent_stamps: set[int] = set()  # stamps (ns) of every measurement sent

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == NODE:
                self.diag = {'message': s.message, **{kv.key: kv.value for kv in s.values}}

    def publish_poses(self, position, quaternion, rate=20.0, frame='world', stamp=time.time_ns):
        return self._publish_until_stopped(
            self.pose, lambda header: pose_to_msg(position, quaternion, header), rate, frame, stamp)

    def publish_targets(self, centre_x, rate=20.0, half=40.0, y=240.0):
        """target_tracker_node's message: four corners, then the centre as the last point."""
        def target(header):
            corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
            points = [Point32(x=centre_x() + dx, y=y + dy, z=0.0) for dx, dy in corners]
            return PolygonStamped(header=header, polygon=Polygon(
                points=[*points, Point32(x=centre_x(), y=y, z=0.0)]))
        return self._publish_until_stopped(self.target, target, rate, 'onboard_camera_optical')

    def _publish_until_stopped(self, publisher, make, rate, frame, stamp=time.time_ns):
        """Publish make(header) at `rate`, stamped stamp() (ns; now by default), until `stop`
        is set."""
        def loop():
            while not self.stop.is_set():
                ns = stamp()
                msg = make(Header(stamp=ns_to_stamp(ns), frame_id=frame))
                self.sent_stamps.add(ns)
                self.last_sent = time.time()
                publisher.publish(msg)
                time.sleep(1.0 / rate)
        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        return thread

    def stop_publishing(self, thread) -> tuple[float, int]:
        """Stop the measurement stream: (wall time of its last message, commands so far)."""
        self.stop.set()
        thread.join()
        self.stop.clear()
        return self.last_sent, len(self.cmds)

    def last_cmd(self):
        return msg_to_twist(self.cmds[-1][1]) if self.cmds else None

    def commanding(self, check) -> bool:
        """Wait until the last command satisfies check(linear, angular). The diagnostics
        and the commands are separate topics: either may arrive first."""
        return wait_for(lambda: self.cmds and check(*self.last_cmd()), 5)


def is_zero(msg: TwistStamped) -> bool:
    return not any(v for part in msg_to_twist(msg) for v in part)


def start(processes, *overrides, params_files=(CONFIG,)):
    args = [a for f in params_files for a in ('--params-file', str(f))]
    args += ['-p', f'controller.rate:={1 / PERIOD}', '-p', f'controller.timeout:={TIMEOUT}',
             '-p', 'controller.diagnostics_period:=0.1']
    for kv in overrides:
        args += ['-p', kv]
    return processes('fuzzy_controller_node', args, label='fuzzy')


def assert_zero_from_one_cycle_after_timeout(probe, last_sent, mark):
    """The first zero command after probe.cmds[mark:] began went out within one cycle
    (plus SLACK) of the timeout expiring after the last measurement was sent, not
    before the timeout; every command after it is zero."""
    assert wait_for(lambda: any(is_zero(m) for _, m in probe.cmds[mark:]), 5)
    cmds = probe.cmds[mark:]
    first = next(k for k, (_, m) in enumerate(cmds) if is_zero(m))
    # A zero command is stamped with the node's clock when it is sent (the wall clock,
    # as the probe's last_sent); the stop is measured from the probe's last publish, so
    # the measured delay is the true one (from the node receiving it) plus the transport.
    delay = stamp_to_ns(cmds[first][1].header.stamp) * 1e-9 - last_sent
    assert TIMEOUT - 1e-3 <= delay <= TIMEOUT + PERIOD + SLACK, delay
    seen = cmds[first][0]
    assert wait_for(lambda: probe.cmds[-1][0] > seen + 0.5, 5)    # 25 more cycles at 50 Hz
    after = probe.cmds[mark + first:]
    assert len(after) >= 10 and all(is_zero(m) for _, m in after), [msg_to_twist(m) for _, m in after]


def test_body_commands_then_zero_when_stale_and_when_disabled(ros_node, processes):
    probe = Probe(ros_node)
    proc = start(processes, 'controller.command_frame:=body', 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    assert wait_for(lambda: probe.diag.get('message') == 'no setpoint: zero command', 10), probe.diag
    probe.setpoint.publish(pose_to_msg([1.5, 0.0, 1.0], [0, 0, 0, 1.0],
                                       Header(frame_id='world')))
    poses = probe.publish_poses([0.0, 0.0, 1.0], NORTH)
    # Setpoint 1.5 m east of a vehicle facing north: to its right (-y FLU), turn right.
    assert wait_for(lambda: probe.diag.get('message') == 'commanding', 10), probe.diag
    assert probe.commanding(lambda linear, _: linear[1] < -0.3), probe.last_cmd()
    linear, angular = probe.last_cmd()
    assert abs(linear[0]) < 1e-6 and abs(linear[2]) < 1e-6 and angular[2] < 0
    assert math.hypot(linear[0], linear[1]) <= 1.0 + 1e-9 and abs(angular[2]) <= 0.8 + 1e-9
    assert probe.cmds[-1][1].header.frame_id == 'base_link'
    # A command computed from a pose carries that pose's stamp.
    assert stamp_to_ns(probe.cmds[-1][1].header.stamp) in probe.sent_stamps

    last_sent, mark = probe.stop_publishing(poses)
    assert_zero_from_one_cycle_after_timeout(probe, last_sent, mark)
    assert wait_for(lambda: probe.diag.get('message', '').startswith('measurement stale'), 5)

    poses = probe.publish_poses([0.0, 0.0, 1.0], NORTH)
    assert wait_for(lambda: probe.diag.get('message') == 'commanding', 5), probe.diag
    assert probe.enable.wait_for_service(10)
    future = probe.enable.call_async(SetBool.Request(data=False))
    assert wait_for(future.done, 10) and future.result().success
    assert wait_for(lambda: probe.diag.get('message') == 'disabled: zero command', 5)
    mark = time.monotonic() + 0.1
    assert wait_for(lambda: any(t > mark for t, _ in probe.cmds), 5)
    assert all(not any(msg_to_twist(m)[0]) and msg_to_twist(m)[1][2] == 0.0
               for t, m in probe.cmds if t > mark)
    probe.stop.set()
    assert proc.poll() is None


def test_tracking_mode_turns_towards_the_target_then_zero_when_stale(ros_node, processes):
    # Image centre column 319.5; a target left of it (smaller column) must turn the
    # vehicle left (positive yaw rate, FLU), one right of it right; never any linear
    # velocity. The error is 150 px, about half the controller's range.
    probe = Probe(ros_node)
    proc = start(processes, 'controller.mode:=tracking', 'controller.enabled:=true',
                 'controller.command_frame:=body')
    assert wait_for(lambda: probe.target.get_subscription_count() > 0, 30)
    column = [319.5 - 150.0]
    targets = probe.publish_targets(lambda: column[0])
    assert wait_for(lambda: probe.diag.get('message') == 'commanding', 10), probe.diag
    assert wait_for(lambda: probe.cmds and msg_to_twist(probe.cmds[-1][1])[1][2] > 0.1, 5)
    mark = len(probe.cmds)
    column[0] = 319.5 + 150.0
    assert wait_for(lambda: msg_to_twist(probe.cmds[-1][1])[1][2] < -0.1, 5)
    for _, m in probe.cmds[mark - 5:]:
        linear, angular = msg_to_twist(m)
        assert linear.tolist() == [0.0, 0.0, 0.0] and angular[:2].tolist() == [0.0, 0.0]
        assert abs(angular[2]) <= 0.6 + 1e-9                   # fuzzy.tracking.limit
        assert m.header.frame_id == 'base_link'
    # Commands follow the targets, stamped with their stamps.
    assert stamp_to_ns(probe.cmds[-1][1].header.stamp) in probe.sent_stamps

    last_sent, mark = probe.stop_publishing(targets)
    assert_zero_from_one_cycle_after_timeout(probe, last_sent, mark)
    assert wait_for(lambda: probe.diag.get('message', '').startswith('measurement stale'), 5)
    assert proc.poll() is None


def test_pid_layer_gives_z_integral_action(ros_node, processes):
    # config/fuzzy_controller_pid.yaml over the main file: a constant 0.1 m z error gives
    # a climb rate that grows as the error integral builds (0.18 m/s at first, 0.34 m/s
    # after 2 s); the PD-like base gives a constant 0.17 m/s. x, y and yaw are on target.
    probe = Probe(ros_node)
    proc = start(processes, 'controller.enabled:=true', params_files=(CONFIG, PID_CONFIG))
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([0.0, 0.0, 1.1], [0, 0, 0, 1.0], Header(frame_id='world')))
    poses = probe.publish_poses([0.0, 0.0, 1.0], [0, 0, 0, 1.0])
    assert wait_for(lambda: probe.diag.get('message') == 'commanding', 10), probe.diag
    early = msg_to_twist(probe.cmds[-1][1])[0][2]
    assert wait_for(lambda: msg_to_twist(probe.cmds[-1][1])[0][2] > early + 0.1, 5), \
        (early, msg_to_twist(probe.cmds[-1][1]))
    linear, angular = msg_to_twist(probe.cmds[-1][1])
    assert 0 < linear[2] <= 0.5 and abs(linear[0]) < 1e-9 and abs(linear[1]) < 1e-9
    assert abs(angular[2]) < 1e-9
    probe.stop_publishing(poses)
    assert proc.poll() is None


def test_non_finite_and_wrong_frame_poses_are_counted_and_never_commanded(ros_node, processes):
    probe = Probe(ros_node)
    proc = start(processes, 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([1.0, 1.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    # The setpoint and the poses travel on separate topics: the bad poses go out only
    # once the node holds the setpoint, so it is they alone that keep it from commanding.
    assert wait_for(lambda: probe.diag.get('message') == 'no measurement yet: zero command', 10), \
        probe.diag
    assert wait_for(lambda: probe.pose.get_subscription_count() > 0, 10)
    probe.pose.publish(pose_to_msg([math.nan, 0.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    probe.pose.publish(pose_to_msg([0.0, math.inf, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    probe.pose.publish(pose_to_msg([0.0, 0.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='map')))
    assert wait_for(lambda: probe.diag.get('malformed') == '3', 10), probe.diag
    assert probe.diag['message'] == 'no measurement yet: zero command'
    assert all(math.isfinite(v) and v == 0.0 for _, m in probe.cmds
               for part in msg_to_twist(m) for v in part)
    assert proc.poll() is None
    assert 'expected \'world\'' in processes.log('fuzzy')


def about_z(yaw_deg: float) -> list[float]:
    half = math.radians(yaw_deg) / 2
    return [0.0, 0.0, math.sin(half), math.cos(half)]


def test_old_unstamped_and_future_poses_are_dropped_and_command_zero(ros_node, processes):
    # Streams of poses stamped 10 s behind the node's clock, stamped 0, and 5 s ahead of
    # it: each is counted and dropped, commands stay zero and the diagnostics say why;
    # fresh poses then command (the setpoint is 1 m east).
    probe = Probe(ros_node)
    proc = start(processes, 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([1.0, 0.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    assert wait_for(lambda: probe.diag.get('message') == 'no measurement yet: zero command', 10)
    for stamp, why, count in ((lambda: time.time_ns() - 10_000_000_000,
                               'pose stamp 10.0 s old (> 0.50 s)', 'old_stamps'),
                              (lambda: 0, 'pose unstamped (stamp 0)', 'old_stamps'),
                              (lambda: time.time_ns() + 5_000_000_000,
                               'future stamp (pose ', 'future_stamps')):
        before = int(probe.diag.get(count, 0))
        poses = probe.publish_poses([0.0, 0.0, 1.0], [0, 0, 0, 1.0], stamp=stamp)
        assert wait_for(lambda: probe.diag.get('message', '').startswith(why)
                        and int(probe.diag[count]) > before + 3, 5), probe.diag
        probe.stop_publishing(poses)
    assert probe.diag['message'].endswith('s ahead of the clock): zero command'), probe.diag
    assert probe.diag['malformed'] == '0' and probe.diag['measurements'] == '0'
    assert len(probe.cmds) > 10 and all(is_zero(m) for _, m in probe.cmds)
    assert 'dropped' in processes.log('fuzzy')
    poses = probe.publish_poses([0.0, 0.0, 1.0], [0, 0, 0, 1.0])
    assert wait_for(lambda: probe.diag.get('message') == 'commanding', 5), probe.diag
    assert probe.commanding(lambda linear, _: linear[0] > 0.1), probe.last_cmd()
    probe.stop_publishing(poses)
    assert proc.poll() is None


def test_a_scaled_quaternion_commands_as_the_unit_one_and_a_zero_one_is_malformed(
        ros_node, processes):
    # Pose yaw 30 deg, setpoint yaw 60 deg: turn left. The pose's quaternion at twice
    # unit length names the same rotation and gives the same command (read as a unit
    # one it would be yaw 77 deg: a right turn). A zero quaternion is no rotation.
    probe = Probe(ros_node)
    proc = start(processes, 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([0.5, 0.0, 1.0], about_z(60), Header(frame_id='world')))
    commands = []
    for scale in (1.0, 2.0):
        mark = len(probe.cmds)
        poses = probe.publish_poses([0.0, 0.0, 1.0], [scale * v for v in about_z(30)])
        assert wait_for(lambda: sum(not is_zero(m) for _, m in probe.cmds[mark:]) >= 5, 10), \
            probe.diag
        commands.append(probe.last_cmd())
        probe.stop_publishing(poses)
    (linear, angular), (linear2, angular2) = commands
    assert linear[0] > 0.1 and angular[2] > 0.1
    np.testing.assert_allclose(linear2, linear, atol=1e-9)
    np.testing.assert_allclose(angular2, angular, atol=1e-9)
    probe.pose.publish(pose_to_msg([0.0, 0.0, 1.0], [0, 0, 0, 0.0], Header(frame_id='world')))
    probe.setpoint.publish(pose_to_msg([0.0, 0.0, 1.0], [0, 0, 0, 0.0], Header(frame_id='world')))
    assert wait_for(lambda: probe.diag.get('malformed') == '2', 10), probe.diag
    assert 'setpoint: quaternion (0, 0, 0, 0) is no rotation' in processes.log('fuzzy')
    assert proc.poll() is None


def test_with_sim_time_a_stopped_clock_gives_zero_commands_that_keep_coming(ros_node, processes):
    # /clock at 100 Hz from 1000 s, poses stamped with it: commands. /clock stops while
    # the poses go on (stamped with the time it stopped at): zero commands, 'clock
    # stopped'. Then the poses stop too: zero commands go on at the node's rate, though
    # its ROS time stands still.
    probe = Probe(ros_node)
    clock = ros_node.create_publisher(Clock, '/clock', 10)
    sim_ns = [1_000_000_000_000]
    ticking = threading.Event()
    ticking.set()

    def tick():
        while ticking.is_set():
            sim_ns[0] += 10_000_000
            clock.publish(Clock(clock=ns_to_stamp(sim_ns[0])))
            time.sleep(0.01)
    ticker = threading.Thread(target=tick, daemon=True)
    ticker.start()
    try:
        proc = start(processes, 'controller.enabled:=true', 'use_sim_time:=true')
        assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
        probe.setpoint.publish(pose_to_msg([1.0, 0.0, 1.0], [0, 0, 0, 1.0],
                                           Header(frame_id='world')))
        poses = probe.publish_poses([0.0, 0.0, 1.0], [0, 0, 0, 1.0], stamp=lambda: sim_ns[0])
        assert wait_for(lambda: probe.diag.get('message') == 'commanding', 10), probe.diag
        assert probe.commanding(lambda linear, _: linear[0] > 0.1), probe.last_cmd()
        assert stamp_to_ns(probe.cmds[-1][1].header.stamp) in probe.sent_stamps
    finally:
        ticking.clear()
        ticker.join()
    stopped_at = time.monotonic()
    assert wait_for(lambda: probe.diag.get('message', '').startswith('clock stopped'), 5), \
        probe.diag
    zero_from = next(k for k, (t, m) in enumerate(probe.cmds) if t > stopped_at and is_zero(m))
    probe.stop_publishing(poses)
    mark = len(probe.cmds)
    assert wait_for(lambda: len(probe.cmds) > mark + 10, 5)         # 50 Hz: 0.2 s
    assert all(is_zero(m) for _, m in probe.cmds[zero_from:]), \
        [msg_to_twist(m) for _, m in probe.cmds[zero_from:]]
    assert proc.poll() is None


def _broken(tmp_path, edit) -> str:
    doc = yaml.safe_load(CONFIG.read_text())
    edit(doc['/**']['ros__parameters'])
    out = tmp_path / 'broken.yaml'
    out.write_text(yaml.safe_dump(doc))
    return str(out)


def _fatal(cfg: str) -> str:
    run = subprocess.run([executable('fuzzy_controller_node'), '--ros-args', '--params-file', cfg],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1, run.stderr
    return fatal[0]


def test_rule_naming_an_unknown_set_or_variable_stops_the_node(tmp_path):
    def unknown_set(p):
        p['fuzzy']['axes']['y']['rules'][3] = 'IF error IS NX AND rate IS PS THEN command IS NM'

    def unknown_variable(p):
        p['fuzzy']['axes']['z']['rules'][0] = 'IF speed IS NB AND rate IS NB THEN command IS NB'

    assert "unknown set 'NX'" in _fatal(_broken(tmp_path, unknown_set))
    assert "unknown input variable 'speed'" in _fatal(_broken(tmp_path, unknown_variable))


def test_bad_or_unknown_controller_parameter_stops_the_node(tmp_path):
    def bad_frame(p):
        p['controller']['command_frame'] = 'ned'

    def typo(p):
        p['controller']['timout'] = 0.2

    assert 'controller.command_frame: expected' in _fatal(_broken(tmp_path, bad_frame))
    assert 'controller.timout: unknown parameter' in _fatal(_broken(tmp_path, typo))
