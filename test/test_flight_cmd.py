"""uav_vs_cmd against mavlink_relay_node and the simulated copter (in this process), and
against fuzzy_controller_node and a setpoint subscriber.

The truth is the simulator's state (mode, armed, NED height) and what the subscriber
receives; the exit status and the printed reason are the command's.
"""
import math
import subprocess

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped

from conftest import REPO, wait_for
from test_mavlink_relay_node import Probe, start_relay, vehicle_and_connection
from uav_vs.graph import executable
from uav_vs.ros.convert import msg_to_pose, yaw_of

CONTROLLER = REPO / 'config' / 'fuzzy_controller.yaml'


def cmd(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([executable('uav_vs_cmd'), *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture
def vehicle():
    sim, connection = vehicle_and_connection('tcp')
    yield sim, connection
    sim.stop()


def test_takeoff_sequence_flies_the_vehicle_to_the_height_and_lands(vehicle, processes, ros_node):
    sim, connection = vehicle
    start_relay(processes, connection, 'allow_arming:=true', ns='/uav3')
    Probe(ros_node, '/uav3').wait_diag(link='connected', prearm_ok='True')
    for command in ('set_guided', 'arm', 'takeoff'):
        done = cmd('--ns', 'uav3', command)
        assert done.returncode == 0, (command, done.stdout, done.stderr)
        assert done.stdout.startswith(f'{command}: done'), done.stdout
    truth = sim.truth()
    assert truth.armed and truth.mode == 'GUIDED'
    assert -truth.position[2] == pytest.approx(1.0, abs=0.05)   # the relay's takeoff_height
    assert cmd('--ns', '/uav3', 'land').returncode == 0
    assert wait_for(lambda: sim.truth().mode == 'LAND', 5.0), sim.truth().mode


def test_refused_arm_exits_1_with_the_relays_reason(vehicle, processes, ros_node):
    sim, connection = vehicle
    start_relay(processes, connection)                       # allow_arming false
    Probe(ros_node).wait_diag(link='connected', prearm_ok='True')
    refused = cmd('arm')
    assert refused.returncode == 1
    assert 'arming is disabled' in refused.stderr, refused.stderr
    assert not sim.truth().armed


def test_no_service_exits_1_naming_it():
    missing = cmd('--ns', 'nobody', '--timeout', '0.5', 'takeoff')
    assert missing.returncode == 1
    assert '/nobody/takeoff: service not available' in missing.stderr, missing.stderr


def test_enable_and_disable_answer_from_the_controller(processes):
    processes('fuzzy_controller_node', ['--params-file', str(CONTROLLER), '-r', '__ns:=/uav4'])
    for command, answer in (('enable', 'enabled'), ('disable', 'disabled')):
        done = cmd('--ns', 'uav4', command)
        assert (done.returncode, done.stdout.strip()) == (0, answer), done.stderr


def test_setpoint_reaches_a_subscriber_in_world_with_its_yaw(ros_node):
    got: list[PoseStamped] = []
    ros_node.create_subscription(PoseStamped, '/uav5/setpoint', got.append, 10)
    sent = cmd('--ns', 'uav5', 'setpoint', '1.5', '-0.5', '2', '-30')
    assert sent.returncode == 0, sent.stderr
    assert wait_for(lambda: got, 5.0)
    position, q = msg_to_pose(got[-1])
    assert got[-1].header.frame_id == 'world'
    np.testing.assert_allclose(position, [1.5, -0.5, 2.0])
    assert yaw_of(q) == pytest.approx(math.radians(-30))
    default = cmd('--ns', 'uav5', 'setpoint', '0', '0', '1')
    assert default.returncode == 0, default.stderr
    assert yaw_of(msg_to_pose(got[-1])[1]) == pytest.approx(math.pi / 2)     # north


def test_setpoint_without_subscriber_exits_1():
    alone = cmd('--ns', 'nobody', '--timeout', '0.5', 'setpoint', '0', '0', '1')
    assert alone.returncode == 1
    assert '/nobody/setpoint: no subscriber' in alone.stderr, alone.stderr


def test_bad_arguments_exit_2():
    assert cmd('setpoint', '0', 'nan', '1').returncode == 2
    assert cmd('hover').returncode == 2
    bad_ns = cmd('--ns', 'uav 1', 'land')
    assert bad_ns.returncode == 2 and '--ns' in bad_ns.stderr, bad_ns.stderr
