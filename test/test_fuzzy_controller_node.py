"""fuzzy_controller_node as a process (console script + config/fuzzy_controller.yaml).

Truth: the frame geometry worked out by hand (a vehicle facing north with its setpoint
to the east must be commanded to its right in FLU), and the node's documented
fail-safe rules (zero command when stale, disabled or fed non-finite poses).
"""
import math
import subprocess
import threading
import time

import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped
from std_msgs.msg import Header
from std_srvs.srv import SetBool

from conftest import REPO, wait_for
from uav_vs.graph import executable
from uav_vs.ros.convert import msg_to_twist, ns_to_stamp, pose_to_msg

CONFIG = REPO / 'config' / 'fuzzy_controller.yaml'
NODE = '/fuzzy_controller_node'
NORTH = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]     # yaw 90 deg, xyzw


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
        self.enable = node.create_client(SetBool, NODE + '/enable')
        self.stop = threading.Event()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == NODE:
                self.diag = {'message': s.message, **{kv.key: kv.value for kv in s.values}}

    def publish_poses(self, position, quaternion, rate=20.0, frame='world'):
        def loop():
            k = 0
            while not self.stop.is_set():
                header = Header(stamp=ns_to_stamp(1_000_000_000 + int(k * 1e9 / rate)),
                                frame_id=frame)
                self.pose.publish(pose_to_msg(position, quaternion, header))
                k += 1
                time.sleep(1.0 / rate)
        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        return thread

    def last_cmd(self):
        return msg_to_twist(self.cmds[-1][1]) if self.cmds else None


def start(processes, *overrides):
    args = ['--params-file', str(CONFIG), '-p', 'controller.rate:=50.0',
            '-p', 'controller.timeout:=0.3', '-p', 'controller.diagnostics_period:=0.1']
    for kv in overrides:
        args += ['-p', kv]
    return processes('fuzzy_controller_node', args, label='fuzzy')


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
    assert wait_for(lambda: probe.last_cmd()[0][1] < -0.3, 5)
    linear, angular = probe.last_cmd()
    assert abs(linear[0]) < 1e-6 and abs(linear[2]) < 1e-6 and angular[2] < 0
    assert math.hypot(linear[0], linear[1]) <= 1.0 + 1e-9 and abs(angular[2]) <= 0.8 + 1e-9
    assert probe.cmds[-1][1].header.frame_id == 'base_link'

    probe.stop.set()
    poses.join()
    stopped = time.monotonic()
    assert wait_for(lambda: probe.diag.get('message', '').startswith('measurement stale'), 5)
    zero_from = next(t for t, m in probe.cmds if t > stopped and not any(msg_to_twist(m)[0]))
    # Timeout 0.3 s + one 20 ms cycle, with slack for the loaded test machine.
    assert zero_from - stopped < 0.3 + 0.02 + 0.5
    assert all(not any(msg_to_twist(m)[0]) for t, m in probe.cmds if t > zero_from)

    probe.stop.clear()
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


def test_non_finite_and_wrong_frame_poses_are_counted_and_never_commanded(ros_node, processes):
    probe = Probe(ros_node)
    proc = start(processes, 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([1.0, 1.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    time.sleep(0.3)
    probe.pose.publish(pose_to_msg([math.nan, 0.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    probe.pose.publish(pose_to_msg([0.0, math.inf, 1.0], [0, 0, 0, 1.0], Header(frame_id='world')))
    probe.pose.publish(pose_to_msg([0.0, 0.0, 1.0], [0, 0, 0, 1.0], Header(frame_id='map')))
    assert wait_for(lambda: probe.diag.get('malformed') == '3', 10), probe.diag
    assert probe.diag['message'] == 'no measurement yet: zero command'
    assert all(math.isfinite(v) and v == 0.0 for _, m in probe.cmds
               for part in msg_to_twist(m) for v in part)
    assert proc.poll() is None
    assert 'expected \'world\'' in processes.log('fuzzy')


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
