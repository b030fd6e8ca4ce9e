"""The ROS side of a flight (closed loop or a replay): every pose source, the commands,
the frame stamps and the relay's status recorded into a FlightLog, the setpoint published,
services called.

Used by uav_vs.flight.scenario (missions in closed loop) and uav_vs.flight.replay (a recorded
flight through the open-loop graph).
"""
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import NodeNameNonExistentError
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from uav_vs.flight.report import CommandTrack, FlightLog, PoseTrack
from uav_vs.ros.convert import (MessageError, msg_to_odometry, msg_to_pose, msg_to_twist,
                                pose_to_msg, stamp_to_ns, yaw_of, yaw_quaternion)

RELAY = '/mavlink_relay_node'
# The vision poses as the controller takes them (best effort): across a radio link, what
# it lost is lost here too.
AS_THE_CONTROLLER = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)


class MissionError(RuntimeError):
    """The mission cannot go on; str() says why."""


class FlightRecorder:
    """A mission's ROS side: records every pose source, the commands, the frame stamps
    and the relay's status; publishes the setpoint (re-sent at 2 Hz); calls services."""

    def __init__(self, first_camera: str, namespace: str = '',
                 home: tuple[float, float] = (0.0, 0.0)) -> None:
        """`namespace`: the vehicle's (/uav1), where its topics, services and nodes are;
        the ground cameras' stay at the root, shared by every vehicle. `home`: where the
        vehicle's autopilot has its local origin in world (x, y, m), which places its
        autopilot/odom (in that local frame) in world."""
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.ns = namespace
        self.home = np.array([home[0], home[1], 0.0])
        self.node = rclpy.create_node('scenario_runner', namespace=namespace or None,
                                      context=self.context)
        self.rows: dict[str, list] = {k: [] for k in (
            'truth', 'ground', 'onboard', 'odom', 'fused', 'target_truth', 'target', 'commands',
            'ground_frames', 'onboard_frames')}
        self.latest: dict[str, tuple[int, np.ndarray, float]] = {}
        self.relay: dict[str, str] = {}
        self.ekf: list[list[float]] = []        # FlightLog.ekf
        self.reporting: set[str] = set()        # nodes heard on /diagnostics
        self.messages: dict[str, str] = {}      # each node's last diagnostics message
        self.clients: dict[str, object] = {}    # service clients by name, kept (prepare)
        node = self.node
        for name, topic in (('truth', 'truth/pose'), ('ground', 'ground/pose'),
                            ('onboard', 'onboard/pose'), ('target_truth', 'truth/target'),
                            ('target', 'target/pose'), ('fused', 'fused/pose')):
            qos = AS_THE_CONTROLLER if name in ('ground', 'onboard') else 100
            node.create_subscription(PoseStamped, topic, lambda m, n=name: self._on_pose(n, m),
                                     qos)
        node.create_subscription(Odometry, 'autopilot/odom', self._on_odom, 100)
        node.create_subscription(TwistStamped, 'cmd_vel', self._on_cmd_vel, 100)
        for name, topic in (('ground_frames', f'/{first_camera}/camera_info'),
                            ('onboard_frames', 'onboard/camera_info')):
            node.create_subscription(CameraInfo, topic, lambda m, n=name: self.rows[n].append(
                stamp_to_ns(m.header.stamp)), 100)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)
        self.setpoint_pub = node.create_publisher(PoseStamped, 'setpoint', 10)
        self.setpoint: PoseStamped | None = None
        node.create_timer(0.5, self._send_setpoint)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.thread.join(timeout=5.0)

    def _on_pose(self, name: str, msg: PoseStamped) -> None:
        try:
            position, q = msg_to_pose(msg)
        except MessageError:            # an orientation that is no rotation: not a pose
            return
        stamp, yaw = stamp_to_ns(msg.header.stamp), yaw_of(q)
        self.rows[name].append((stamp, time.time_ns(), *position, yaw))
        self.latest[name] = (stamp, position, yaw)

    def _on_odom(self, msg: Odometry) -> None:
        try:
            position, q, _, _ = msg_to_odometry(msg)
        except MessageError:
            return
        self.rows['odom'].append((stamp_to_ns(msg.header.stamp), time.time_ns(),
                                  *(position + self.home), yaw_of(q)))

    def _on_cmd_vel(self, msg: TwistStamped) -> None:
        linear, angular = msg_to_twist(msg)
        self.rows['commands'].append((stamp_to_ns(msg.header.stamp), time.time_ns(), *linear,
                                      angular[2]))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.reporting.add(status.name)
            self.messages[status.name] = status.message
            if status.name == self.ns + RELAY:
                self.relay = {kv.key: kv.value for kv in status.values}
                if self.relay.get('ekf_flags'):
                    self.ekf.append(ekf_row(self.relay))

    def set_setpoint(self, position: tuple[float, float, float], yaw: float) -> None:
        msg = pose_to_msg(np.array(position, float), yaw_quaternion(yaw),
                          Header(stamp=self.node.get_clock().now().to_msg(), frame_id='world'))
        self.setpoint = msg
        self.setpoint_pub.publish(msg)

    def clear_setpoint(self) -> None:
        """Stop re-sending the setpoint (another node sends them now)."""
        self.setpoint = None

    def _send_setpoint(self) -> None:
        if self.setpoint is not None:
            self.setpoint_pub.publish(self.setpoint)

    def subscriptions(self, node_name: str) -> tuple[str, ...]:
        """The topics a node of the vehicle's graph subscribes to, as the ROS graph reports
        them (none while the node is not discovered)."""
        try:
            found = self.node.get_subscriber_names_and_types_by_node(node_name, self.ns or '/')
        except NodeNameNonExistentError:
            return ()
        return tuple(sorted(name for name, _ in found))

    def prepare(self, *services: tuple[type, str]) -> None:
        """Make the clients of (type, name) `services` now, ahead of their calls: across
        a lossy link, discovery of a client made at its call can lag the request, and the
        server then drops its answer (its response writer not matched yet)."""
        for srv_type, name in services:
            self._client(srv_type, name)

    def _client(self, srv_type, name: str, fresh: bool = False):
        client = self.clients.get(name)
        if client is not None and fresh:
            self.node.destroy_client(client)
            client = None
        if client is None:
            client = self.clients[name] = self.node.create_client(srv_type, name)
        return client

    def call(self, srv_type, name: str, request, timeout: float, attempts: int = 1):
        """Call a service and wait for its answer; MissionError if none or unsuccessful.

        With `attempts` > 1 (idempotent services only) an unanswered request is sent
        again from a new client: a server that has just been restarted may still be
        matched to its predecessor's request.
        """
        for attempt in range(attempts):
            client = self._client(srv_type, name, fresh=attempt > 0)
            if not client.wait_for_service(timeout_sec=timeout):
                raise MissionError(f'{name}: service not available')
            future = client.call_async(request)
            deadline = time.monotonic() + timeout
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.02)
            response = future.result() if future.done() else None
            if response is not None:
                break
        else:
            raise MissionError(f'{name}: no answer within {timeout:.0f} s '
                               f'({attempts} attempt{"s" if attempts > 1 else ""})')
        if not response.success:
            raise MissionError(f'{name}: {response.message}')
        return response

    def log(self, scenario: str, **events) -> FlightLog:
        rows = {k: list(v) for k, v in self.rows.items()}
        return FlightLog(scenario, *(PoseTrack.from_rows(rows[k]) for k in
                                          ('truth', 'ground', 'onboard', 'odom')),
                         CommandTrack.from_rows(rows['commands']),
                         np.array(rows['ground_frames'], np.int64),
                         np.array(rows['onboard_frames'], np.int64), ekf=list(self.ekf),
                         target_truth=PoseTrack.from_rows(rows['target_truth']),
                         target=PoseTrack.from_rows(rows['target']),
                         fused=PoseTrack.from_rows(rows['fused']), **events)


def ekf_row(relay: dict[str, str]) -> list[float]:
    """One FlightLog.ekf row from the relay's diagnostics values, received now."""
    fix = relay.get('gps_fix', '')
    return [time.time_ns(), int(relay['ekf_flags'], 16), float(relay['ekf_velocity_ratio']),
            float(relay['ekf_pos_horiz_ratio']), float(relay['ekf_pos_vert_ratio']),
            float(relay['ekf_navigating'] == 'True'), int(fix) if fix else -1]
