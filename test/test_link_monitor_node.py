"""link_monitor_node: the other host heard or not, on /diagnostics, judged by the node's
own account of the silence; a bad parameter stops it with one line."""
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry

from conftest import REPO, refused_at_start, wait_for
from uav_vs.vision.ground_config import read_params_file


def test_silence_is_an_outage_until_messages_come_again(ros_node, processes):
    processes('link_monitor_node', ['-p', 'link_monitor.timeout:=0.3',
                                    '-p', 'link_monitor.diagnostics_period:=0.05'],
              label='monitor')
    diag: list[dict] = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diag.extend(
        {'level': s.level[0], 'message': s.message, **{kv.key: kv.value for kv in s.values}}
        for s in m.status if s.name == '/link_monitor_node'), 10)
    pub = ros_node.create_publisher(Odometry, '/autopilot/odom', 10)
    assert wait_for(lambda: diag and diag[-1]['message'].startswith('never heard'), 30), diag[-1:]
    assert diag[-1]['level'] == 1

    def send_until(predicate) -> None:
        deadline = time.monotonic() + 30
        while not predicate() and time.monotonic() < deadline:
            pub.publish(Odometry())
            time.sleep(0.02)
        assert predicate(), diag[-1:]

    send_until(lambda: diag[-1]['message'] == 'heard on /autopilot/odom')
    assert diag[-1]['level'] == 0
    before = int(diag[-1]['outages'])      # a stall of this process may have made some
    # Silence: ERROR once the node itself has seen more than the timeout without one.
    assert wait_for(lambda: diag[-1]['level'] == 2, 10), diag[-1:]
    assert diag[-1]['message'].startswith('not heard on /autopilot/odom for')
    # (`silent` is given to 0.01 s: a silence just over the timeout may read 0.30)
    assert float(diag[-1]['silent']) >= 0.3 and int(diag[-1]['outages']) == before + 1
    send_until(lambda: diag[-1]['level'] == 0)
    assert float(diag[-1]['longest_silence']) >= 0.3, diag[-1]
    assert 'not heard' in processes.log('monitor')


def test_a_bad_parameter_stops_the_node_with_one_line(tmp_path: Path):
    fatal = refused_at_start('link_monitor_node', ['-p', 'link_monitor.timeout:=0.0'], tmp_path)
    assert 'link_monitor.timeout' in fatal, fatal


def test_every_parameter_is_in_the_yaml_with_its_default():
    from uav_vs.nodes.link_monitor_node import PARAMS

    yaml = read_params_file(REPO / 'config' / 'link_monitor.yaml')
    assert yaml == {spec.name: spec.default for spec in PARAMS}
