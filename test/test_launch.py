"""`ros2 launch uav_vs <file>` with the real ROS 2 launch system.

The ROS 2 command line and launch wheels (../shared/wheels/ros2-jazzy-cli) are installed
once into a folder on PYTHONPATH; their PyPI dependencies are pinned in
requirements-dev.txt. Each launch file must bring up its nodes under the expected
names and namespaces (as the ROS graph reports them), apply its arguments, and stop
every node cleanly on one SIGINT to `ros2 launch`.
"""
import os
import signal
import subprocess
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python

from conftest import REPO, ROS2, wait_for
from uav_vs.flight.ground_replay import DEFAULT_LAYOUT
from uav_vs.flight.scenario import free_port

GROUND = {('/cam1', 'camshift_node'), ('/cam2', 'camshift_node'), ('/cam3', 'camshift_node'),
          ('/', 'trinocular_pose_node')}
GROUND_PROCESSES = {'one_process': 1, 'processes': len(GROUND)}


class Launch:
    """One `ros2 launch uav_vs FILE ARGS` process, its output in a file."""

    def __init__(self, env: dict[str, str], ros2, log: Path, file: str, *args: str) -> None:
        self.log, self.ros2 = log, ros2     # ros2: conftest's ros2_cli, for other commands
        with open(log, 'wb') as out:
            self.proc = subprocess.Popen([*ROS2, 'launch', 'uav_vs', file, *args], env=env,
                                         stdin=subprocess.DEVNULL, stdout=out,
                                         stderr=subprocess.STDOUT, start_new_session=True)

    def output(self) -> str:
        return self.log.read_text(errors='replace')

    def interrupt(self, terminal: bool, timeout: float = 30.0) -> int:
        """SIGINT to `ros2 launch` alone or, as Ctrl-C in a terminal, to it and every node
        (which then get a second one from launch); its exit status."""
        if terminal:
            os.killpg(self.proc.pid, signal.SIGINT)
        else:
            self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            raise AssertionError(f'ros2 launch did not stop on SIGINT:\n{self.output()[-3000:]}')


@pytest.fixture
def launch(ros2_env, ros2_cli, tmp_path):
    started: list[Launch] = []

    def start(file: str, *args: str) -> Launch:
        started.append(Launch(ros2_env, ros2_cli, tmp_path / f'{file}.log', file, *args))
        return started[-1]
    yield start
    for run in started:     # launch's nodes too, should launch itself have gone before them
        try:
            os.killpg(run.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        run.proc.wait()


class Graph:
    """The probe's view: nodes, their diagnostics, their parameters."""

    def __init__(self, node) -> None:
        self.node = node
        self.reporting: set[str] = set()
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        self.reporting.update(status.name for status in msg.status)

    def nodes(self) -> set[tuple[str, str]]:
        return {(ns, name) for name, ns in self.node.get_node_names_and_namespaces()}

    def wait_up(self, expected: set[tuple[str, str]], run: Launch, timeout: float = 60.0):
        """Every expected node in the graph and reporting on /diagnostics."""
        names = {f"{ns.rstrip('/')}/{name}" for ns, name in expected}
        ok = wait_for(lambda: expected <= self.nodes() and names <= self.reporting, timeout,
                      period=0.2)
        assert ok, (f'missing nodes {expected - self.nodes()}, silent {names - self.reporting}'
                    f'\n{run.output()[-3000:]}')

    def parameters(self, node: str, names: list[str]) -> list:
        client = self.node.create_client(GetParameters, f'{node}/get_parameters')
        assert client.wait_for_service(timeout_sec=20.0), f'no {node}/get_parameters'
        future = client.call_async(GetParameters.Request(names=names))
        assert wait_for(future.done, 20.0), f'{node}/get_parameters did not answer'
        return [parameter_value_to_python(v) for v in future.result().values]


def assert_stops_cleanly(graph: Graph, run: Launch, expected: set[tuple[str, str]],
                         terminal: bool = False, processes: int | None = None) -> None:
    """SIGINT: launch exits 0, every node process (one per node unless `processes`
    says) exits 0 and every node leaves the graph."""
    assert run.interrupt(terminal) == 0, run.output()[-3000:]
    out = run.output()
    count = len(expected) if processes is None else processes
    assert out.count('process has finished cleanly') == count, out[-3000:]
    assert 'process has died' not in out and 'Traceback' not in out, out[-3000:]
    # The graph as a newly started `ros2 node list` sees it, which must see the probe: the
    # probe's own graph cache was seen, under load, to keep nodes whose processes had exited
    # (a node gone without its DDS goodbye leaves when its lease runs out: 20 s in Fast DDS).
    names = {f"{ns.rstrip('/')}/{name}" for ns, name in expected}
    seen: set[str] = set()

    def gone() -> bool:
        seen.clear()
        seen.update(run.ros2('node', 'list', '--no-daemon', '--spin-time', '2').stdout.split())
        return f'/{graph.node.get_name()}' in seen and not names & seen
    assert wait_for(gone, 30.0, period=1.0), seen


@pytest.mark.parametrize('args, processes', [((), GROUND_PROCESSES[DEFAULT_LAYOUT]),
                                             (('layout:=processes', 'executor:=single'), 4),
                                             (('layout:=one_process', 'namespace:=uav1'), 1)])
def test_ground_launch_starts_the_station(launch, ros_node, args, processes):
    """Either layout, either executor: the same nodes (below the station's namespace)."""
    graph = Graph(ros_node)
    ns = '/uav1' if 'namespace:=uav1' in args else ''
    expected = {(f'{ns}{space}'.rstrip('/') or '/', name) for space, name in GROUND}
    run = launch('ground.launch.py', *args)
    graph.wait_up(expected, run)
    assert graph.parameters(f'{ns}/cam2/camshift_node', ['camera', 'use_sim_time']) == [
        'cam2', False]
    assert_stops_cleanly(graph, run, expected, terminal=True, processes=processes)


@pytest.mark.parametrize('follow', [False, True])
def test_onboard_launch_in_a_namespace(launch, ros_node, follow):
    graph = Graph(ros_node)
    expected = {('/uav1', 'homography_pose_node'), ('/uav1', 'target_tracker_node'),
                *([('/uav1', 'target_follower_node')] if follow else [])}
    run = launch('onboard.launch.py', 'namespace:=uav1', *(['follow:=true'] if follow else []))
    graph.wait_up(expected, run)
    assert not {name for _, name in expected} & {name for ns, name in graph.nodes()
                                                  if ns != '/uav1'}
    assert_stops_cleanly(graph, run, expected)


def test_control_launch_applies_its_arguments(launch, ros_node, tmp_path):
    """Namespace, connection, arming, pose topic, use_sim_time and a params file of one's own
    reach the nodes; an argument left empty keeps the params file's value."""
    relay_params = tmp_path / 'relay.yaml'
    relay_params.write_text((REPO / 'config' / 'mavlink_relay.yaml').read_text()
                            .replace('takeoff_height: 2.0', 'takeoff_height: 3.25'))
    graph = Graph(ros_node)
    expected = {('/uav2', 'fuzzy_controller_node'), ('/uav2', 'mavlink_relay_node')}
    run = launch('control.launch.py', 'namespace:=/uav2', 'use_sim_time:=true',
                 'connection:=udpin:127.0.0.1:14999', 'allow_arming:=true',
                 'pose_topic:=onboard/pose', f'relay_params:={relay_params}')
    # Under sim time without /clock the nodes' diagnostics timers never fire: the graph only.
    assert wait_for(lambda: expected <= graph.nodes(), 60.0, period=0.2), run.output()[-3000:]
    assert graph.parameters('/uav2/mavlink_relay_node', [
        'connection', 'allow_arming', 'takeoff_height', 'use_sim_time']) == [
        'udpin:127.0.0.1:14999', True, 3.25, True]
    assert graph.parameters('/uav2/fuzzy_controller_node', [
        'controller.pose_topic', 'controller.command_frame', 'use_sim_time']) == [
        'onboard/pose', 'world', True]
    assert_stops_cleanly(graph, run, expected)


def test_sim_launch_flies_nothing_but_sees_the_vehicle(launch, ros_node):
    """The whole graph: every node up and reporting, the relay connected to sim_world's
    vehicle, ground/pose from the rendered images at the vehicle's home (the origin)."""
    graph = Graph(ros_node)
    poses: list[PoseStamped] = []
    ros_node.create_subscription(PoseStamped, '/ground/pose', poses.append, 10)
    relay: dict[str, str] = {}

    def on_diag(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == '/mavlink_relay_node':
                relay.update({kv.key: kv.value for kv in status.values})
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
    expected = GROUND | {('/', name) for name in (
        'sim_world', 'homography_pose_node', 'target_tracker_node', 'fuzzy_controller_node',
        'mavlink_relay_node')}
    run = launch('sim.launch.py', f'port:={free_port()}')
    graph.wait_up(expected, run, timeout=90.0)
    assert wait_for(lambda: len(poses) >= 5 and relay.get('link') == 'connected', 30.0), (
        len(poses), relay, run.output()[-3000:])
    p = poses[-1].pose.position
    assert poses[-1].header.frame_id == 'world'
    assert abs(p.x) < 0.05 and abs(p.y) < 0.05 and abs(p.z) < 0.1, p
    assert relay['armed'] == 'False'
    assert_stops_cleanly(graph, run, expected,
                         processes=len(expected) - len(GROUND) + GROUND_PROCESSES[DEFAULT_LAYOUT])
