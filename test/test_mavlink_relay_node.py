"""mavlink_relay_node as a process (console script + config/mavlink_relay.yaml + -p overrides)
against the simulated ArduCopter running in this process, over loopback UDP and TCP.

Ground truth is the simulator's NED state. Expected motions are worked out here by hand
from the commanded ENU/FLU velocity (never through uav_vs.autopilot.frames): ENU
(east, north, up) is NED (north, east, down) = (y, x, -z); FLU (forward, left, up) at
NED heading psi moves the vehicle along forward = (cos psi, sin psi) and
right = (-sin psi, cos psi). For the simulator's first-order velocity lag, the distance
flown by a velocity held for T seconds, once stopped, is exactly v * T.
"""
import logging
import math
import re
import shlex
import subprocess
import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Twist, TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Log
from rclpy.logging import LoggingSeverity
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import SetBool, Trigger

from conftest import REPO, wait_for
from uav_vs import graph
from uav_vs.autopilot.link import load_signing_key, mavlink, open_connection
from uav_vs.autopilot.session import SEND_BURST
from uav_vs.graph import executable
from uav_vs.ros import log_bridge
from uav_vs.ros.convert import (msg_to_odometry, ns_to_stamp, odometry_to_msg, pose_to_msg,
                                twist_to_msg)
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

CONFIG = REPO / 'config' / 'mavlink_relay.yaml'
NODE = '/mavlink_relay_node'


def vehicle_and_connection(transport: str, **cfg) -> tuple[MavlinkVehicle, str]:
    """A simulated copter on a free loopback port and the relay's connection string for it."""
    server = {'tcp': 'tcpin:127.0.0.1:0', 'udp': 'udpin:127.0.0.1:0'}[transport]
    config = VehicleConfig(connection=server, **{'ready_delay': 0.5, **cfg})
    vehicle = MavlinkVehicle(config).start()
    port = vehicle.address[1]
    return vehicle, {'tcp': f'tcp:127.0.0.1:{port}', 'udp': f'udpout:127.0.0.1:{port}'}[transport]


def start_relay(processes, connection: str, *overrides: str, ns: str = '', label: str = 'relay'):
    args = ['--params-file', str(CONFIG), '-p', f'connection:={connection}',
            '-p', 'diagnostics_period:=0.2', '-p', 'takeoff_height:=1.0']
    for kv in overrides:
        args += ['-p', kv]
    if ns:
        args += ['-r', f'__ns:={ns}']
    return processes('mavlink_relay_node', args, label=label)


class Probe:
    """The test side of one relay: cmd_vel, odometry, diagnostics, services."""

    def __init__(self, node, ns: str = ''):
        self.node, self.name = node, f'{ns}{NODE}'
        self.diags: dict[str, dict] = {}
        self.diag_messages: dict[str, str] = {}
        self.odom: list[Odometry] = []
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)
        node.create_subscription(Odometry, f'{ns}/autopilot/odom', self.odom.append, 10)
        self.cmd = node.create_publisher(TwistStamped, f'{ns}/cmd_vel', 10)
        self.clients = {name: node.create_client(kind, f'{ns}/{name}') for name, kind in (
            ('arm', SetBool), ('takeoff', Trigger), ('land', Trigger), ('set_guided', Trigger),
            ('install_signing_key', Trigger))}

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.diag_messages[status.name] = status.message   # before the values waited on
            self.diags[status.name] = {kv.key: kv.value for kv in status.values}

    def diag(self) -> dict:
        return self.diags.get(self.name, {})

    def wait_diag(self, timeout: float = 20.0, **expected: str) -> dict:
        ok = wait_for(lambda: all(self.diag().get(k) == v for k, v in expected.items()), timeout)
        assert ok, f'diagnostics never showed {expected}: {self.diag()}'
        return self.diag()

    def call(self, name: str, data: bool | None = None, timeout: float = 20.0):
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=20.0), f'no {name} service'
        request = client.srv_type.Request() if data is None else SetBool.Request(data=data)
        future = client.call_async(request)
        assert wait_for(future.done, timeout), f'{name} service did not answer'
        return future.result()

    def send(self, frame: str, linear, yaw_rate: float = 0.0) -> None:
        self.cmd.publish(twist_to_msg(linear, [0.0, 0.0, yaw_rate], Header(frame_id=frame)))

    def fly(self, frame: str, linear, yaw_rate: float = 0.0, duration: float = 1.2,
            rate: float = 20.0) -> None:
        """Hold one command for `duration`, then command zero."""
        end = time.monotonic() + duration
        while time.monotonic() < end:
            self.send(frame, linear, yaw_rate)
            time.sleep(1.0 / rate)
        self.send(frame, [0.0, 0.0, 0.0])


def settle(vehicle: MavlinkVehicle, timeout: float = 6.0) -> None:
    assert wait_for(lambda: np.linalg.norm(vehicle.truth().velocity) < 0.02
                    and abs(vehicle.truth().yaw_rate) < 0.01, timeout), 'the vehicle never stopped'


def take_off(probe: Probe, vehicle: MavlinkVehicle) -> None:
    probe.wait_diag(link='connected')
    for name, data in (('set_guided', None), ('arm', True), ('takeoff', None)):
        response = probe.call(name, data)
        assert response.success, response.message
    truth = vehicle.truth()
    assert truth.armed and truth.mode == 'GUIDED' and 0.95 < -truth.position[2] < 1.05
    settle(vehicle)


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_flight_in_world_and_body_frames_odometry_and_landing(ros_node, processes, transport):
    vehicle, connection = vehicle_and_connection(transport, land_speed=1.0)
    try:
        # a long command timeout: only the relay's zero setpoint on shutdown stops it early
        relay = start_relay(processes, connection, 'allow_arming:=true', 'command_timeout:=2.5')
        probe = Probe(ros_node)
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        take_off(probe, vehicle)

        # world ENU (0.6 east, 0.8 south, 0.3 up) m/s held T s (the vehicle's own record
        # of the command, however late a loaded machine ended it): NED (-0.8, 0.6, -0.3) T m
        p0, t0 = vehicle.truth().position, time.monotonic()
        probe.fly('world', [0.6, -0.8, 0.3])
        settle(vehicle)
        held = vehicle.moving_time(since=t0)
        assert held > 0.6   # the pulse reached the vehicle (either end of it may come late)
        assert np.allclose(vehicle.truth().position - p0, np.array([-0.8, 0.6, -0.3]) * held,
                           atol=0.05)

        # the autopilot's estimate, as odometry: ENU position = (NED y, NED x, -NED z),
        # ENU yaw = pi/2 - NED yaw
        n_odom = len(probe.odom)
        assert wait_for(lambda: len(probe.odom) > n_odom + 2, 5)
        p, q, v, w = msg_to_odometry(probe.odom[-1])
        truth = vehicle.truth()
        n, e, d = truth.position
        assert np.allclose(p, [e, n, -d], atol=0.03)
        last = probe.odom[-1]
        assert (last.header.frame_id, last.child_frame_id) == ('world', 'base_link')
        yaw_enu = math.atan2(2 * (q[3] * q[2] + q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))
        assert abs(math.remainder(yaw_enu - (math.pi / 2 - truth.yaw), 2 * math.pi)) < 0.01
        assert np.linalg.norm(v) < 0.05 and np.linalg.norm(w) < 0.05

        # +0.6 rad/s about z-up held T s, in base_link: a left turn, NED yaw falls by 0.6 T rad
        yaw0, t0 = vehicle.truth().yaw, time.monotonic()
        probe.fly('base_link', [0.0, 0.0, 0.0], yaw_rate=0.6)
        settle(vehicle)
        psi = vehicle.truth().yaw
        assert math.isclose(math.remainder(psi - yaw0, 2 * math.pi),
                            -0.6 * vehicle.moving_time(since=t0), abs_tol=0.03)

        # base_link FLU (0.8 forward, 0.6 left) m/s held T s at NED heading psi
        forward = np.array([math.cos(psi), math.sin(psi)])
        right = np.array([-math.sin(psi), math.cos(psi)])
        p0, t0 = vehicle.truth().position, time.monotonic()
        probe.fly('base_link', [0.8, 0.6, 0.0], duration=1.5)
        # the odometry's twist is in base_link (REP-105): compare it with the true velocity
        # near the end of the command, projected by hand on the body axes
        cruising = msg_to_odometry(probe.odom[-1])[2]
        vn, ve, _ = vehicle.truth().velocity
        flu = [vn * forward[0] + ve * forward[1], -(vn * right[0] + ve * right[1])]
        assert np.allclose(cruising[:2], flu, atol=0.08), (cruising, flu)
        assert np.allclose(cruising[:2], [0.8, 0.6], atol=0.15)
        settle(vehicle)
        moved = vehicle.truth().position - p0
        assert np.allclose(moved[:2], vehicle.moving_time(since=t0)
                           * (0.8 * forward - 0.6 * right), atol=0.05)
        assert abs(moved[2]) < 0.03
        assert abs(math.remainder(vehicle.truth().yaw - psi, 2 * math.pi)) < 0.02  # no nose swing

        # the relay stopped mid-command (0.5 m/s north): it exits cleanly after one zero
        # setpoint (its command watchdog, 2.5 s here, has not run out); without it the
        # copter would fly on for GUID_TIMEOUT (3 s)
        for _ in range(10):
            last = time.monotonic()
            probe.send('world', [0.0, 0.5, 0.0])
            time.sleep(0.05)
        assert graph.stop([relay]) == [0]
        settle(vehicle)
        final = vehicle.targets(since=last)[-1]
        assert final.velocity == (0.0, 0.0, 0.0) and final.time - last < 2.5

        # a new relay process picks the flying copter up and lands it
        start_relay(processes, connection, label='relay2')
        probe.wait_diag(link='connected', reconnects='0', cmd_vel='0')
        xy = vehicle.truth().position[:2]
        response = probe.call('land')
        assert response.success, response.message
        assert wait_for(lambda: not vehicle.truth().armed, 15), 'no touchdown'
        truth = vehicle.truth()
        assert truth.mode == 'LAND' and not truth.flying and truth.position[2] == 0.0
        assert np.allclose(truth.position[:2], xy, atol=0.05)
        assert probe.wait_diag(armed='False')['malformed'] == '0'
    finally:
        vehicle.stop()


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_stale_input_hovers_and_link_loss_reconnects_without_replay(ros_node, processes, transport):
    vehicle, connection = vehicle_and_connection(transport)
    try:
        start_relay(processes, connection, 'allow_arming:=true', 'command_timeout:=0.3',
                    'link_timeout:=2.0')
        probe = Probe(ros_node)
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        take_off(probe, vehicle)

        # 1 m/s north for 0.5 s, then the input stops: the 0.3 s watchdog streams zero,
        # about 0.8 m flown; the copter's own GUID_TIMEOUT (3 s) would carry it 3.5 m
        p0 = vehicle.truth().position
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            probe.send('world', [0.0, 1.0, 0.0])
            time.sleep(0.05)
        probe.wait_diag(command='hover')
        settle(vehicle)
        north = (vehicle.truth().position - p0)[0]
        assert 0.6 < north < 1.3, north

        # link cut while commands flow: detected, commands refused, not queued
        def stream(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                probe.send('world', [0.5, 0.0, 0.0])   # east
                time.sleep(0.05)
        stream(0.5)
        vehicle.cut_link()
        refused_before = int(probe.diag()['refused'])
        stream(2.0)
        diag = probe.wait_diag(link='lost', command='idle')
        stream(0.5)
        assert int(probe.wait_diag(link='lost')['refused']) > refused_before
        settle(vehicle)                   # its own GUID_TIMEOUT stopped it
        restored = time.monotonic()
        vehicle.restore_link()
        diag = probe.wait_diag(link='connected', reconnects='1')
        assert diag['command'] == 'idle'
        time.sleep(1.0)
        assert vehicle.targets(since=restored) == []   # nothing from before the loss
        assert np.linalg.norm(vehicle.truth().velocity) < 0.01
        fresh = time.monotonic()
        probe.send('world', [0.0, 0.5, 0.0])   # north
        assert wait_for(lambda: vehicle.targets(since=fresh), 5)
        assert vehicle.targets(since=fresh)[0].velocity == (0.5, 0.0, 0.0)  # NED north
    finally:
        vehicle.stop()


def test_a_running_flight_service_holds_up_neither_cmd_vel_nor_the_next_service(ros_node,
                                                                                processes):
    vehicle, connection = vehicle_and_connection('udp', takeoff_speed=0.3)   # a slow climb
    try:
        start_relay(processes, connection, 'allow_arming:=true')
        probe = Probe(ros_node)
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        probe.wait_diag(link='connected', prearm_ok='True')
        assert probe.call('set_guided').success and probe.call('arm', True).success

        takeoff = probe.clients['takeoff'].call_async(Trigger.Request())
        land = probe.clients['land'].call_async(Trigger.Request())   # waits for the takeoff

        # while the takeoff waits for its height, cmd_vel is still taken (and refused)
        assert wait_for(lambda: probe.diag().get('command') == 'locked' or takeoff.done(), 20)

        def refused() -> bool:
            probe.send('world', [0.0, 0.5, 0.0])
            return int(probe.diag().get('refused', 0)) > 0
        assert wait_for(lambda: refused() or takeoff.done(), 20, period=0.05)
        assert not takeoff.done() and probe.diag()['command'] == 'locked'

        # one flight command at a time: the takeoff completes, then the landing
        assert wait_for(land.done, 30), 'land service did not answer'
        assert takeoff.done() and takeoff.result().success, takeoff.result().message
        assert land.result().success, land.result().message
        assert vehicle.truth().mode == 'LAND'
        assert int(probe.wait_diag(command='locked')['sent']) == 0
    finally:
        vehicle.stop()


def test_refused_arming_carries_the_reason_and_malformed_cmd_vel_is_skipped(ros_node, processes):
    not_ready, conn1 = vehicle_and_connection('udp', ready_delay=60.0)
    ready, conn2 = vehicle_and_connection('udp')
    try:
        start_relay(processes, conn1, 'allow_arming:=true', ns='/a', label='a')
        start_relay(processes, conn2, ns='/b', label='b')    # allow_arming false (the default)
        a, b = Probe(ros_node, '/a'), Probe(ros_node, '/b')
        # not ready, and the diagnostics say which checks fail (all three, on ArduPilot)
        assert wait_for(lambda: 'EKF_STATUS_REPORT flags' in a.diag().get('prearm_reasons', ''), 10)
        diag = a.wait_diag(link='connected', prearm_ok='False')
        assert diag['prearm_reasons'] == ('SYS_STATUS pre-arm check not passed; EKF_STATUS_REPORT '
                                          'flags 0xa5 lack EKF_POS_HORIZ_ABS, EKF_PRED_POS_HORIZ_ABS; '
                                          'GPS fix GPS_FIX_TYPE_NO_FIX, needs 3D')
        response = a.call('arm', True)
        assert not response.success
        assert 'PreArm: Need Position Estimate' in response.message      # the autopilot's reason
        assert 'MAV_RESULT_FAILED' in response.message
        response = a.call('set_guided')
        assert not response.success and 'GUIDED requires position' in response.message
        assert not not_ready.truth().armed

        b.wait_diag(link='connected', prearm_ok='True', prearm_reasons='')
        assert b.call('set_guided').success and ready.truth().mode == 'GUIDED'
        response = b.call('arm', True)
        assert not response.success and 'allow_arming' in response.message
        assert not ready.truth().armed

        # malformed cmd_vel: counted, skipped, the node goes on
        assert wait_for(lambda: b.cmd.get_subscription_count() > 0, 20)
        t0 = time.monotonic()
        for k, (frame, v) in enumerate((('world', [math.nan, 0.0, 0.0]), ('map', [1.0, 0.0, 0.0]),
                                        ('base_link', [0.0, math.inf, 0.0]))):
            b.send(frame, v)
            b.wait_diag(malformed=str(k + 1))
        assert ready.targets(since=t0) == []
        b.send('world', [0.0, 0.5, 0.0])   # a good one after them: north (ignored on the ground)
        assert wait_for(lambda: ready.targets(since=t0), 5)
        assert ready.targets(since=t0)[0].velocity == (0.5, 0.0, 0.0)
        log = processes.log('b')
        assert "frame_id 'map'" in log and 'not finite' in log
    finally:
        not_ready.stop()
        ready.stop()


class BareAutopilot:
    """A bare ArduPilot-like UDP endpoint: heartbeats, and a record of what it receives."""

    def __init__(self):
        self.conn = open_connection('udpin:127.0.0.1:0', source_system=1, source_component=1)
        self.port = self.conn.port.getsockname()[1]
        self.received: list = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        next_hb = 0.0
        while not self.stop.is_set():
            if time.monotonic() >= next_hb and self.conn.clients:
                next_hb = time.monotonic() + 0.2
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR,
                                             mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 4)
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is not None:
                self.received.append(msg)

    def close(self):
        self.stop.set()
        self.thread.join(timeout=2.0)
        self.conn.close()


def forward_vision(pub, autopilot: 'BareAutopilot', good: PoseStamped, bad: PoseStamped) -> list:
    """Publish `good` then `bad` alternately until the relay forwards one (the subscription
    has matched); the VISION_POSITION_ESTIMATEs that reached the autopilot (at least one)."""
    def vision():
        return [m for m in autopilot.received if m.get_type() == 'VISION_POSITION_ESTIMATE']
    end = time.monotonic() + 10
    while not vision() and time.monotonic() < end:
        pub.publish(good)
        time.sleep(0.05)   # the relay keeps only the newest message (depth 1)
        pub.publish(bad)
        time.sleep(0.05)
    time.sleep(0.3)
    forwarded = vision()
    assert forwarded, 'no vision pose was forwarded'
    return forwarded


@contextmanager
def relaying_vision(ros_node, processes, kind: type, topic: str, *params: str):
    """A relay forwarding `topic` (messages of `kind`) to a BareAutopilot, linked and
    subscribed: (the autopilot, a Probe, the test's publisher on `topic`)."""
    autopilot = BareAutopilot()
    try:
        start_relay(processes, f'udpout:127.0.0.1:{autopilot.port}',
                    f'vision_pose_topic:={topic}', *params)
        probe = Probe(ros_node)
        pub = ros_node.create_publisher(kind, f'/{topic}', 10)
        probe.wait_diag(link='connected')
        assert wait_for(lambda: pub.get_subscription_count() > 0, 20)
        yield autopilot, probe, pub
    finally:
        autopilot.close()


def test_vision_pose_is_forwarded_in_ned(ros_node, processes):
    with relaying_vision(ros_node, processes, PoseStamped, 'ground/pose',
                         'vision.position_std:=0.2') as (autopilot, probe, pub):
        s = math.sqrt(0.5)   # nose north: ENU yaw +90 deg, NED yaw 0
        good = pose_to_msg([1.0, 2.0, 3.0], [0.0, 0.0, s, s],
                           Header(stamp=ns_to_stamp(1_700_000_000_250_000_000), frame_id='world'))
        bad = pose_to_msg([1.0, 2.0, 3.0], [0.0, 0.0, s, s], Header(frame_id='map'))

        forwarded = forward_vision(pub, autopilot, good, bad)
        diag = probe.wait_diag(vision=str(len(forwarded)))
        assert int(diag['malformed']) >= 1 and int(diag['cmd_vel']) == 0
        for v in forwarded:   # ENU (east 1, north 2, up 3) is NED (north 2, east 1, down -3)
            assert (v.x, v.y, v.z, v.usec) == (2.0, 1.0, -3.0, 1_700_000_000_250_000)
            assert abs(v.yaw) < 1e-6 and abs(v.roll) < 1e-6 and abs(v.pitch) < 1e-6
            assert math.isclose(v.covariance[0], 0.04, rel_tol=1e-6)   # (0.2 m)^2
        assert "frame_id 'map'" in processes.log('relay')


def test_fused_odometry_is_forwarded_with_its_covariance(ros_node, processes):
    """pose_filter_node's fused/odom as external navigation: its position covariance in
    NED (x, y swapped, their correlation kept), roll and pitch (unknown to the filter:
    1e6) sent with the yaw's variance and uncorrelated; a covariance that is not one
    (negative eigenvalue) counted as malformed and not sent."""
    with relaying_vision(ros_node, processes, Odometry, 'fused/odom',
                         'vision_pose_type:=odometry') as (autopilot, probe, pub):
        cov = np.diag([0.04, 0.01, 0.09, 1e6, 1e6, 0.0025])
        cov[0, 1] = cov[1, 0] = 0.012           # east-north correlation 0.6
        cov[2, 5] = cov[5, 2] = 0.003           # up-yaw correlation 0.2
        s = math.sqrt(0.5)
        header = Header(stamp=ns_to_stamp(1_700_000_000_500_000_000), frame_id='world')
        good = odometry_to_msg([1.0, 2.0, 3.0], [0.0, 0.0, s, s], [0.3, 0.0, 0.0],
                               [0.0, 0.0, 0.1], header, 'base_link', pose_covariance=cov)
        not_psd = cov.copy()
        not_psd[0, 1] = not_psd[1, 0] = 0.03    # correlation 1.5
        bad = odometry_to_msg([1.0, 2.0, 3.0], [0.0, 0.0, s, s], [0.3, 0.0, 0.0],
                              [0.0, 0.0, 0.1], header, 'base_link', pose_covariance=not_psd)

        forwarded = forward_vision(pub, autopilot, good, bad)
        diag = probe.wait_diag(vision=str(len(forwarded)))
        assert int(diag['malformed']) >= 1
        upper = np.triu_indices(6)
        for v in forwarded:
            assert (v.x, v.y, v.z, v.usec) == (2.0, 1.0, -3.0, 1_700_000_000_500_000)
            sent = np.zeros((6, 6))
            sent[upper] = v.covariance
            yaw = 0.0025
            expected = np.diag([0.01, 0.04, 0.09, yaw, yaw, yaw])
            expected[0, 1] = 0.012                # north-east
            expected[2, 5] = 0.003                # down-yaw (NED): both signs flip
            assert np.allclose(sent, expected, rtol=1e-6, atol=1e-9), sent
        assert 'positive semi-definite' in processes.log('relay')


def _gcs_hears(transport: str, port: int, seconds: float) -> tuple[list, list]:
    """A GCS without the key sends DO_SET_MODE STABILIZE: (its ACKs, HEARTBEAT signed flags).

    The simulator serves one TCP client, the newest: over TCP, stop the relay first."""
    device = {'tcp': f'tcp:127.0.0.1:{port}', 'udp': f'udpout:127.0.0.1:{port}'}[transport]
    gcs = open_connection(device, source_system=254)
    gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0)
    end, acks, signed = time.monotonic() + seconds, [], []
    while time.monotonic() < end:
        msg = gcs.recv_match(blocking=True, timeout=0.1)
        if msg is None:
            continue
        if msg.get_type() == 'HEARTBEAT':
            signed.append(bool(msg.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED))
        elif msg.get_type() == 'COMMAND_ACK' and msg.target_system == 254:
            acks.append(msg)
    gcs.close()
    return acks, signed


@pytest.mark.parametrize('transport', ['udp', 'tcp'])
def test_signing_rejects_unsigned_traffic_both_ways_and_installs_the_key(ros_node, processes,
                                                                          tmp_path, transport):
    key_file = tmp_path / 'signing.key'
    key_file.write_text('correct horse battery staple\n')
    key = load_signing_key(key_file)
    signed, conn1 = vehicle_and_connection(transport, signing_key=key)
    unsigned, conn2 = vehicle_and_connection(transport)
    fresh, conn3 = vehicle_and_connection(transport)
    try:
        relay_a = start_relay(processes, conn1, f'signing_key_file:={key_file}', ns='/a', label='a')
        start_relay(processes, conn2, f'signing_key_file:={key_file}', ns='/b', label='b')
        relay_c = start_relay(processes, conn3, f'signing_key_file:={key_file}',
                              'signing_required:=false', ns='/c', label='c')
        a, b, c = Probe(ros_node, '/a'), Probe(ros_node, '/b'), Probe(ros_node, '/c')

        # both sides sign: commands and ACKs go through
        a.wait_diag(link='connected', vehicle_signs='True', signing='True')
        assert a.call('set_guided').success and signed.truth().mode == 'GUIDED'
        if transport == 'tcp':
            assert graph.stop([relay_a]) == [0]
        acks, flags = _gcs_hears(transport, signed.address[1], 1.5)
        assert acks == [] and signed.truth().mode == 'GUIDED'   # unsigned command dropped
        assert flags and all(flags)                              # and all it hears is signed

        # a vehicle that does not sign is never accepted by a relay that requires signing
        b.wait_diag(link='connecting')
        assert wait_for(lambda: int(b.diag().get('rejected_unsigned', 0)) > 0, 10), b.diag()
        assert b.diag()['link'] == 'connecting'

        # the install_signing_key service puts the key on the autopilot
        c.wait_diag(link='connected', vehicle_signs='False')
        assert not fresh.truth().signing
        response = c.call('install_signing_key')
        assert response.success, response.message
        assert fresh.truth().signing
        c.wait_diag(vehicle_signs='True')
        if transport == 'tcp':
            assert graph.stop([relay_c]) == [0]
        acks, _ = _gcs_hears(transport, fresh.address[1], 1.2)
        assert acks == [] and fresh.truth().mode == 'STABILIZE'
        for label in 'abc':   # the key never reaches a log
            log = processes.log(label)
            assert key.hex() not in log and 'correct horse' not in log
    finally:
        for v in (signed, unsigned, fresh):
            v.stop()


@pytest.mark.parametrize('override, expected', [
    ('limits.max_speed:=-1.0', 'limits.max_speed: expected a number in [0, 30], got -1.0'),
    (None, 'connection: missing'),
    ('geofence.min:=[0.0, 0.0]', 'geofence.min: expected 3 numbers'),
    ('signing_key_file:=/nonexistent/key', 'signing_key_file: cannot read /nonexistent/key'),
    ('max_send_rate:=5.0', 'max_send_rate: expected at least stream_rate (10.0 Hz), got 5.0'),
    ('connection:=tcp:nohost', "connection: expected tcp:HOST:PORT with a port in 0..65535, "
                               "got 'tcp:nohost'"),
    ('connection:=udpin:0.0.0.0:port', "connection: expected udpin:HOST:PORT with a port"),
    ('connection:=serial0', "connection: expected udp:, udpin:, udpout:, udpbcast:, tcp:, "
                            "tcpin: followed by HOST:PORT, or a serial device"),
    ('ekf_origin:=[-35.36, 149.17]', 'ekf_origin: expected [latitude, longitude, altitude] or []'),
    ('ekf_origin:=[-35.36, 149.17, 584.0]', 'ekf_origin: set without vision_pose_topic'),
    ('vision_pose_type:=twist', "vision_pose_type: expected a string (one of pose, pose_cov, "
                                "odometry), got 'twist'"),
])
def test_bad_parameter_stops_the_node_with_one_fatal_line(tmp_path, override, expected):
    doc = yaml.safe_load(CONFIG.read_text())
    params = doc['/**']['ros__parameters']
    if override is None:
        del params['connection']
    config = tmp_path / 'relay.yaml'
    config.write_text(yaml.safe_dump(doc))
    argv = [executable('mavlink_relay_node'), '--ros-args', '--params-file', str(config)]
    if override:
        argv += ['-p', override]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert len(fatal) == 1 and expected in fatal[0], run.stdout + run.stderr


def test_a_cmd_vel_burst_is_coalesced_to_max_send_rate_and_the_newest_is_sent(ros_node,
                                                                            processes):
    vehicle, connection = vehicle_and_connection('udp')
    try:
        start_relay(processes, connection, 'max_send_rate:=40.0', 'command_timeout:=2.5')
        probe = Probe(ros_node)
        probe.wait_diag(link='connected')
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        t0 = time.monotonic()
        n = 0
        while time.monotonic() < t0 + 1.0:   # ~1 kHz for 1 s (targets are recorded on the ground)
            probe.send('world', [min(n / 1000, 1.0), 0.0, 0.0])
            n += 1
            time.sleep(0.001)
        probe.send('world', [0.0, 0.5, 0.0])   # the newest: north 0.5
        assert wait_for(lambda: any(t.velocity == (0.5, 0.0, 0.0)
                                    for t in vehicle.targets(since=t0)), 2.0), 'newest never sent'
        end = time.monotonic()
        sent = vehicle.targets(since=t0)
        assert len(sent) <= 40.0 * (end - t0) + SEND_BURST, (n, len(sent), end - t0)
        assert sent[-1].velocity == (0.5, 0.0, 0.0)
        diag = probe.wait_diag()
        assert wait_for(lambda: int(probe.diag()['coalesced']) > 0, 5), probe.diag()
        assert int(diag['cmd_vel']) > 2 * len(sent)   # most of the burst did reach the relay
    finally:
        vehicle.stop()


def test_an_unknown_host_is_named_in_the_diagnostics_and_the_node_log(ros_node, processes):
    start_relay(processes, 'tcp:nohost.invalid:5760')
    probe = Probe(ros_node)
    reason = "cannot open tcp:nohost.invalid:5760: host 'nohost.invalid' does not resolve"
    assert wait_for(lambda: probe.diag().get('link_reason', '').startswith(reason), 20), probe.diag()
    assert probe.diag()['link'] == 'connecting'
    time.sleep(3.0)   # three more tries within the 10 s warning period
    lines = [line for line in processes.log('relay').splitlines() if reason in line]
    assert len(lines) == 1 and '[WARN]' in lines[0] and '[mavlink_relay_node]' in lines[0], lines


def test_a_cmd_vel_publisher_of_another_type_is_warned_about_once_and_shown(ros_node, processes):
    """A geometry_msgs/Twist publisher on cmd_vel is never heard by the relay (it takes
    TwistStamped): it is named in one warning and in the diagnostics while it lasts."""
    vehicle, connection = vehicle_and_connection('udp')
    ctx = None
    try:
        start_relay(processes, connection)
        probe = Probe(ros_node)                      # its cmd_vel publisher is TwistStamped
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        probe.wait_diag(link='connected', cmd_vel_wrong_type='')
        ctx = rclpy.Context()    # a participant of its own (one may not hold both types)
        rclpy.init(context=ctx)
        teleop = rclpy.create_node('teleop', context=ctx)
        twist = teleop.create_publisher(Twist, '/cmd_vel', 10)
        diag = probe.wait_diag(cmd_vel_wrong_type='/teleop (geometry_msgs/msg/Twist)')
        assert 'cmd_vel publishers of another type' in probe.diag_messages[NODE]
        t0 = time.monotonic()
        for _ in range(10):
            twist.publish(Twist())
            time.sleep(0.05)
        time.sleep(1.0)                              # five more diagnostics periods
        assert int(probe.diag()['cmd_vel']) == 0 and vehicle.targets(since=t0) == []
        lines = [line for line in processes.log('relay').splitlines() if 'geometry_msgs' in line]
        assert lines == [lines[0]] and '[WARN]' in lines[0], lines
        assert ('/cmd_vel: /teleop publishes geometry_msgs/msg/Twist, the relay subscribes '
                'geometry_msgs/msg/TwistStamped' in lines[0]), lines
        teleop.destroy_publisher(twist)
        probe.wait_diag(cmd_vel_wrong_type='')
        assert int(diag['cmd_vel']) == 0
    finally:
        if ctx is not None:
            teleop.destroy_node()
            rclpy.shutdown(context=ctx)
        vehicle.stop()


def test_the_relays_core_lines_reach_its_console_and_rosout_at_their_severity(ros_node,
                                                                             processes):
    """The session's lines (link, watchdog, the autopilot's STATUSTEXT) in a running relay:
    on /rosout under the node's name at their severity, and on its console the same way."""
    rosout = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)   # rcl's, with its history
    received = []
    ros_node.create_subscription(Log, '/rosout', received.append, rosout)
    vehicle, connection = vehicle_and_connection('udp', ready_delay=60.0)   # never ready
    try:
        start_relay(processes, connection, 'allow_arming:=true', 'command_timeout:=0.3')
        probe = Probe(ros_node)
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        probe.wait_diag(link='connected')
        probe.send('world', [0.0, 0.0, 0.0])        # taken, then stale: hovering
        probe.wait_diag(command='hover')
        assert not probe.call('arm', True).success   # refused with a CRITICAL STATUSTEXT
        vehicle.cut_link()
        probe.wait_diag(link='lost')
        expected = [(Log.INFO, f'opened {connection}'),
                    (Log.INFO, 'connected to ardupilot QUADROTOR (system 1)'),
                    (Log.INFO, 'command input stale for'),
                    (Log.ERROR, 'autopilot: PreArm: Need Position Estimate'),
                    (Log.WARN, 'link lost: no HEARTBEAT for')]
        core = lambda: [(m.level, m.msg) for m in received  # noqa: E731
                        if m.name == 'mavlink_relay_node' and m.file.endswith('log_bridge.py')]
        assert wait_for(lambda: len(core()) >= len(expected), 10), core()
        assert [(level, text) for (level, text), (_, start) in zip(core(), expected)
                if not text.startswith(start)] == [], core()
        assert [level for level, _ in core()[:len(expected)]] == [lv for lv, _ in expected]
        console = processes.log('relay').splitlines()
        for level, text in expected:
            name = {Log.INFO: 'INFO', Log.WARN: 'WARN', Log.ERROR: 'ERROR'}[level]
            assert any(line.startswith(f'[{name}]') and f'[mavlink_relay_node]: {text}' in line
                       for line in console), (text, console)
        assert all(line.startswith('[') for line in console), console   # nothing bypasses it
    finally:
        vehicle.stop()


def test_core_log_records_reach_rosout_at_their_severity(ros_node):
    received = []
    ros_node.create_subscription(Log, '/rosout', received.append, 50)
    handler = log_bridge.forward('uav_vs.bridge_test', ros_node.get_logger())
    try:
        core = logging.getLogger('uav_vs.bridge_test.session')
        time.sleep(0.5)   # the /rosout subscription matches
        core.debug('not shown at INFO')
        core.info('opened %s', 'tcp:127.0.0.1:5760')
        core.warning('link lost')
        core.error('refused')
        mine = lambda: [(m.level, m.msg) for m in received if m.name == 'test_probe']  # noqa: E731
        assert wait_for(lambda: len(mine()) >= 3, 5), received
        assert mine() == [(Log.INFO, 'opened tcp:127.0.0.1:5760'), (Log.WARN, 'link lost'),
                          (Log.ERROR, 'refused')]
        # the rclpy logger's level as it is now: set while running, the core follows it
        ros_node.get_logger().set_level(LoggingSeverity.DEBUG)
        core.debug('shown at DEBUG')
        assert wait_for(lambda: len(mine()) >= 4, 5), received
        assert mine()[3] == (Log.DEBUG, 'shown at DEBUG')
        ros_node.get_logger().set_level(LoggingSeverity.WARN)
        core.info('not shown at WARN')
        core.warning('shown at WARN')
        assert wait_for(lambda: len(mine()) >= 5, 5), received
        assert mine()[4:] == [(Log.WARN, 'shown at WARN')]
    finally:
        ros_node.get_logger().set_level(LoggingSeverity.INFO)
        log_bridge.stop_forwarding('uav_vs.bridge_test', handler)


def relay_command_lines() -> list[tuple[str, list[str]]]:
    """(page, argv) of every mavlink_relay_node command in the docs' sh blocks."""
    found = []
    for page in [REPO / 'README.md', *sorted((REPO / 'docs').glob('*.md'))]:
        for block in re.findall(r'^```sh\n(.*?)^```', page.read_text(), re.M | re.S):
            for line in block.replace('\\\n', ' ').splitlines():
                argv = shlex.split(line, comments=True)
                if argv[:1] == ['mavlink_relay_node']:
                    found.append((page.name, argv))
    return found


def test_every_relay_command_in_the_docs_sets_declared_parameters_and_can_arm():
    """The flight steps that follow each command arm the vehicle: allow_arming must be set."""
    from uav_vs.nodes.mavlink_relay_node import PARAMS
    declared = {p.name for p in PARAMS}
    commands = relay_command_lines()
    assert len(commands) >= 5, commands
    for page, argv in commands:
        rules = dict(arg.split(':=', 1) for prev, arg in zip(argv, argv[1:]) if prev == '-p')
        assert set(rules) <= declared, (page, argv)
        assert rules.get('allow_arming') == 'true', (page, ' '.join(argv))


def test_odometry_twist_is_expressed_in_the_child_frame():
    """convert.odometry_to_msg: world velocity rotated into base_link (REP-105)."""
    s = math.sqrt(0.5)
    header = Header(frame_id='world')
    # nose north (yaw +90 deg about z-up): moving north is moving forward
    msg = odometry_to_msg([1.0, 2.0, 3.0], [0.0, 0.0, s, s], [0.0, 2.0, 0.5], [0.0, 0.0, 0.3],
                          header, 'base_link')
    p, q, v, w = msg_to_odometry(msg)
    assert msg.child_frame_id == 'base_link' and msg.header.frame_id == 'world'
    assert np.array_equal(p, [1.0, 2.0, 3.0]) and np.allclose(q, [0.0, 0.0, s, s])
    assert np.allclose(v, [2.0, 0.0, 0.5]) and np.array_equal(w, [0.0, 0.0, 0.3])
    # rolled +90 deg about forward (x): base_link's left axis points up, so climbing is
    # moving to the body's left
    msg = odometry_to_msg([0.0, 0.0, 0.0], [s, 0.0, 0.0, s], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0],
                          header, 'base_link')
    assert np.allclose(msg_to_odometry(msg)[2], [0.0, 1.0, 0.0])


@pytest.mark.parametrize('autopilot', ['px4', 'ardupilot'])
def test_odometry_covariances_are_the_autopilots_in_ros_frames(ros_node, processes, autopilot):
    """PX4's ODOMETRY variances (NED position and velocity, FRD orientation) come out in
    ENU / FLU: east and north swap, the velocity's seen from the body at its heading.
    ArduPilot reports no covariance: zero (unknown)."""
    vehicle, connection = vehicle_and_connection('udp', autopilot=autopilot)
    try:
        start_relay(processes, connection)
        probe = Probe(ros_node)
        assert wait_for(lambda: probe.odom and any(probe.odom[-1].pose.covariance)
                        or autopilot == 'ardupilot' and len(probe.odom) > 20, 20)
        last = probe.odom[-1]
        pose, twist = (np.reshape(c, (6, 6)) for c in (last.pose.covariance,
                                                      last.twist.covariance))
        if autopilot == 'ardupilot':
            assert not pose.any() and not twist.any()
            return
        (pn, pe, pd), orientation, (vn, ve, vd) = VehicleConfig().odometry_variance
        assert np.allclose(pose, np.diag([pe, pn, pd, *orientation]))
        psi = vehicle.truth().yaw                   # NED heading: forward = (cos, sin) N, E
        c, s = math.cos(psi), math.sin(psi)
        forward = c * c * vn + s * s * ve           # variance along the forward axis
        left = s * s * vn + c * c * ve              # along left = -(right) = (s, -c)
        cross = c * s * (vn - ve)
        assert np.allclose(twist[:3, :3], [[forward, cross, 0], [cross, left, 0], [0, 0, vd]])
        assert not twist[3:].any()                  # body rates: PX4 says NaN, unknown
    finally:
        vehicle.stop()
