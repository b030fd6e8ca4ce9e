"""Faults injected in flight, and what the vehicle does: the control chain as processes
(fuzzy_controller_node -> mavlink_relay_node) flying the simulated copter of this process;
and a ground camera dropped from the trinocular station.

The pose source is the test: it publishes `ground/pose` from the simulator's truth
(NED -> ENU worked out by hand: east, north, up = y, x, -z; heading = pi/2 - yaw), as a
perfect ground station would. Each fault is injected while the vehicle flies towards a
setpoint at the controller's speed limit, and the vehicle's true motion afterwards is
checked: where it stops, and that it flies on once the fault is gone.
"""
import math
import threading
import time

import numpy as np
import pytest
from geometry_msgs.msg import PolygonStamped, PoseStamped
from std_msgs.msg import Header

from conftest import REPO, wait_for
from test_mavlink_relay_node import Probe, settle, start_relay, take_off, vehicle_and_connection
from uav_vs.ros.convert import (msg_to_pose, ns_to_stamp, points_to_polygon, pose_to_msg,
                                stamp_to_ns, yaw_of)
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig
from uav_vs.vision.ground_config import load_ground_config, read_params_file

CONTROLLER = REPO / 'config' / 'fuzzy_controller.yaml'
GROUND = REPO / 'config' / 'ground_trinocular.yaml'
SPEED = 1.0              # controller.max_horizontal_speed, m/s
COMMAND_TIMEOUT = 0.4    # the relay's watchdog, s
POSE_TIMEOUT = 0.3       # the controller's, s
TAU = 0.35               # the simulated copter's velocity lag (VehicleConfig.tau), s


def enu(vehicle: MavlinkVehicle) -> tuple[np.ndarray, float]:
    """The vehicle's true position (east, north, up) and heading (0 east, counter-clockwise)."""
    t = vehicle.truth()
    return np.array([t.position[1], t.position[0], -t.position[2]]), math.pi / 2 - t.yaw


class PoseSource:
    """ground/pose from the simulator's truth at 30 Hz, stamped now (`running` cleared:
    none), and the current setpoint, facing north (the heading after takeoff), at 3 Hz."""

    def __init__(self, node, vehicle: MavlinkVehicle):
        self.node, self.vehicle = node, vehicle
        self.pub = node.create_publisher(PoseStamped, '/ground/pose', 10)
        self.setpoint_pub = node.create_publisher(PoseStamped, '/setpoint', 10)
        self.running, self.done = threading.Event(), threading.Event()
        self.running.set()
        self.goal: np.ndarray | None = None
        self.clock_offset_ns = 0        # added to the stamps: a camera clock that jumps
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        north = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
        k = 0
        while not self.done.is_set():
            if self.goal is not None and k % 10 == 0:
                self.setpoint_pub.publish(pose_to_msg(self.goal, north, Header(frame_id='world')))
            k += 1
            if self.running.is_set():
                position, heading = enu(self.vehicle)
                q = [0.0, 0.0, math.sin(heading / 2), math.cos(heading / 2)]
                now = self.node.get_clock().now().nanoseconds + self.clock_offset_ns
                header = Header(stamp=ns_to_stamp(now), frame_id='world')
                self.pub.publish(pose_to_msg(position, q, header))
            time.sleep(1 / 30)

    def close(self) -> None:
        self.done.set()
        self.thread.join()


def start_controller(processes):
    return processes('fuzzy_controller_node', [
        '--params-file', str(CONTROLLER), '-p', 'controller.enabled:=true',
        '-p', f'controller.timeout:={POSE_TIMEOUT}', '-p', 'controller.rate:=20.0',
        '-p', f'controller.max_horizontal_speed:={SPEED}'], label='controller')


def fly_until_cruising(vehicle: MavlinkVehicle) -> None:
    assert wait_for(lambda: np.linalg.norm(vehicle.truth().velocity) > 0.8 * SPEED, 15), \
        'the vehicle never reached cruise speed'


def arrives(vehicle: MavlinkVehicle, goal, tolerance: float = 0.15, timeout: float = 25.0) -> bool:
    return wait_for(lambda: np.linalg.norm(enu(vehicle)[0] - goal) < tolerance
                    and np.linalg.norm(vehicle.truth().velocity) < 0.1, timeout)


@pytest.fixture
def flight(ros_node, processes):
    """A copter hovering at 1 m, the relay and the controller running, the pose streaming."""
    vehicle, connection = vehicle_and_connection('udp')
    start_relay(processes, connection, 'allow_arming:=true',
                f'command_timeout:={COMMAND_TIMEOUT}', 'link_timeout:=2.0')
    probe = Probe(ros_node)
    assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
    take_off(probe, vehicle)
    source = PoseSource(ros_node, vehicle)
    controller = start_controller(processes)
    assert wait_for(lambda: source.setpoint_pub.get_subscription_count() > 0, 20)
    state = dict(vehicle=vehicle, probe=probe, source=source, controller=controller,
                 connection=connection)
    yield state
    source.close()
    state['vehicle'].stop()


def test_controller_killed_in_flight_the_relay_stops_the_vehicle_and_a_restart_flies_on(
        flight, processes):
    vehicle, source = flight['vehicle'], flight['source']
    goal = np.array([4.0, 0.0, 1.0])
    source.goal = goal
    fly_until_cruising(vehicle)
    flight['controller'].kill()                      # SIGKILL: no last zero command
    killed, killed_at = time.monotonic(), enu(vehicle)[0]
    flight['probe'].wait_diag(command='hover')
    settle(vehicle)
    # The relay's watchdog sends zero command_timeout after the last command (plus its
    # tick and, on a loaded machine, the scheduler's delay), then the velocity lag stops
    # the vehicle within SPEED * TAU; ArduPilot alone (GUID_TIMEOUT 3 s) would fly on 3 m.
    hover = next(t.time for t in vehicle.targets(killed) if not any(t.velocity))
    assert hover - killed < COMMAND_TIMEOUT + 0.35, hover - killed
    coasted = np.linalg.norm(enu(vehicle)[0] - killed_at)
    assert coasted < SPEED * (hover - killed + TAU) + 0.25, (coasted, hover - killed)
    assert enu(vehicle)[0][0] < goal[0] - 0.5
    start_controller(processes)
    assert arrives(vehicle, goal), enu(vehicle)


def test_pose_lost_in_flight_the_controller_stops_the_vehicle_and_it_flies_on_when_back(
        flight):
    vehicle, source = flight['vehicle'], flight['source']
    goal = np.array([0.0, 4.0, 1.0])
    source.goal = goal
    fly_until_cruising(vehicle)
    source.running.clear()                           # every camera blind
    lost_at = enu(vehicle)[0]
    settle(vehicle)
    coasted = np.linalg.norm(enu(vehicle)[0] - lost_at)
    assert coasted < SPEED * (POSE_TIMEOUT + TAU) + 0.25, coasted
    assert flight['probe'].diag()['command'] == 'active'   # zero commands, not silence
    source.running.set()
    assert arrives(vehicle, goal), enu(vehicle)


def test_pose_clock_jumps_in_flight_the_controller_stops_the_vehicle_until_it_is_right(flight):
    """The ground station's clock jumps 10 s back (the poses keep coming, stamped 10 s old)
    and later 5 s ahead: the controller takes neither, the vehicle stops each time."""
    vehicle, source = flight['vehicle'], flight['source']
    for jump_s, goal in ((-10.0, np.array([-4.0, 0.0, 1.0])), (5.0, np.array([4.0, 0.0, 1.0]))):
        source.goal = goal
        fly_until_cruising(vehicle)
        source.clock_offset_ns = int(jump_s * 1e9)
        jumped_at = enu(vehicle)[0]
        settle(vehicle)
        coasted = np.linalg.norm(enu(vehicle)[0] - jumped_at)
        assert coasted < SPEED * (POSE_TIMEOUT + TAU) + 0.25, (jump_s, coasted)
        assert np.linalg.norm(enu(vehicle)[0] - goal) > 0.5
        source.clock_offset_ns = 0              # the clock is right again: on to the goal
    assert arrives(vehicle, goal), enu(vehicle)


def test_vehicle_restarted_in_flight_the_relay_reconnects_and_the_new_vehicle_stays_put(flight):
    vehicle, probe = flight['vehicle'], flight['probe']
    flight['source'].goal = np.array([4.0, 4.0, 1.0])
    fly_until_cruising(vehicle)
    port = vehicle.address[1]
    vehicle.stop()                                   # the autopilot reboots
    probe.wait_diag(link='lost')
    reboot = MavlinkVehicle(VehicleConfig(connection=f'udpin:127.0.0.1:{port}',
                                          ready_delay=0.5)).start()
    flight['vehicle'] = reboot
    flight['source'].vehicle = reboot
    probe.wait_diag(link='connected', reconnects='1')
    time.sleep(2.0)                                  # commands flow again, to a vehicle on the ground
    truth = reboot.truth()
    assert not truth.armed and not truth.flying
    assert np.linalg.norm(truth.position) < 1e-6 and np.linalg.norm(truth.velocity) < 1e-6


def test_a_ground_camera_dropped_the_pose_goes_on_from_the_other_two(ros_node, processes):
    """The trinocular node fed landmarks projected through the calibration (truth: the
    layout at a known pose) at 30 Hz by three cameras; cam3 goes silent for good. Each set
    is then released with the two cameras left once `max_wait` (0.2 s) of newer stamps
    have come: the poses go on, at the true pose."""
    cfg = load_ground_config(read_params_file(GROUND))
    processes('trinocular_pose_node', ['--params-file', str(GROUND)])
    poses: list[PoseStamped] = []
    sub = ros_node.create_subscription(PoseStamped, '/ground/pose', poses.append, 50)
    pubs = [ros_node.create_publisher(PolygonStamped, f'/{c.name}/landmarks', 10)
            for c in cfg.cameras]
    # Both ways matched: the node hears the cameras and its poses reach the probe.
    assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                    and sub.get_publisher_count() > 0, 30)
    truth, yaw = np.array([0.4, -0.3, 1.2]), 2.5
    c, s = math.cos(yaw), math.sin(yaw)
    world = cfg.layout @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + truth
    polygons = [np.column_stack([cam.project(world), np.ones(len(world))]) for cam in cfg.cameras]

    def stream(cameras: int, frames: int) -> list[int]:
        stamps = []
        for _ in range(frames):
            stamp = ros_node.get_clock().now().to_msg()
            for pub, points in list(zip(pubs, polygons))[:cameras]:
                pub.publish(points_to_polygon(points, Header(stamp=stamp)))
            stamps.append(stamp_to_ns(stamp))
            time.sleep(1 / 30)
        return stamps

    # Each end of a topic matches the other in its own time: stream until poses come back.
    deadline = time.monotonic() + 20.0
    while len(poses) < 10 and time.monotonic() < deadline:
        stream(3, 3)
    assert len(poses) >= 10, len(poses)
    two = stream(2, 30)                               # cam3 dropped
    time.sleep(0.5)
    after = [p for p in poses if stamp_to_ns(p.header.stamp) in set(two)]
    # A set short of cam3 goes once frames 0.2 s newer have come (the sync is by stamp):
    # from the tenth frame on, every frame but the last 0.2 s gives its pose.
    assert set(two[10:-8]) <= {stamp_to_ns(p.header.stamp) for p in after}, len(after)
    for p in after:
        position, q = msg_to_pose(p)
        assert np.linalg.norm(position - truth) < 1e-6 and abs(yaw_of(q) - yaw) < 1e-6
