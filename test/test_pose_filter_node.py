"""pose_filter_node: poses in, one fused estimate out (uav_vs.control.pose_filter).

Two sources publish noisy poses of a vehicle moving at constant velocity, stamped with
the time they stand for, so every fused estimate has an analytic answer at its own stamp;
malformed input is counted and skipped; when the sources stop the node goes quiet; a
bad parameter stops it with one line."""
import math
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header

from conftest import REPO, refused_at_start, wait_for
from uav_vs.ros.convert import (msg_to_odometry, pose_cov_to_msg, pose_to_msg, stamp_to_ns,
                                yaw_quaternion)
from uav_vs.vision.ground_config import read_params_file

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
VELOCITY, START = np.array([0.4, -0.2, 0.1]), np.array([1.0, 0.5, 1.5])
SIGMAS = {'ground': 0.03, 'onboard': 0.05}


def listen(ros_node) -> tuple[list[Odometry], list[dict]]:
    """What the filter publishes: fused/odom, and its /diagnostics (level, message, values)."""
    fused: list[Odometry] = []
    diagnostics: list[dict] = []
    ros_node.create_subscription(Odometry, '/fused/odom', fused.append, RELIABLE)
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diagnostics.extend(
        {'level': s.level[0], 'message': s.message, **{kv.key: kv.value for kv in s.values}}
        for s in m.status if s.name == '/pose_filter_node'), RELIABLE)
    return fused, diagnostics


def test_two_sources_fused_better_than_either_and_quiet_when_they_stop(ros_node, processes):
    processes('pose_filter_node', ['-p', 'pose_filter.accel_sigma:=0.5',
                                   '-p', 'pose_filter.position_sigmas:=[0.03, 0.05]',
                                   '-p', 'pose_filter.timeout:=0.3',
                                   '-p', 'pose_filter.diagnostics_period:=0.1'], label='filter')
    fused, diagnostics = listen(ros_node)
    pubs = {s: ros_node.create_publisher(PoseStamped, f'/{s}/pose', RELIABLE) for s in SIGMAS}
    assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 30)

    clock, rng = ros_node.get_clock(), np.random.default_rng(0)
    t0 = clock.now().nanoseconds * 1e-9
    truth = lambda t: START + VELOCITY * (t - t0)           # noqa: E731
    raw: list[float] = []

    def publish_both() -> float:
        now = clock.now()
        t = now.nanoseconds * 1e-9
        for source, sigma in SIGMAS.items():
            measured = truth(t) + rng.normal(0.0, sigma, 3)
            if source == 'ground':
                raw.append(np.linalg.norm(measured - truth(t)))
            pubs[source].publish(pose_to_msg(measured, yaw_quaternion(0.5),
                                             Header(stamp=now.to_msg(), frame_id='world')))
        time.sleep(1 / 30)
        return t

    def applied(source: str) -> int:
        return int(diagnostics[-1].get(f'{source}/pose.applied', 0)) if diagnostics else 0

    # A subscriber may match a publisher later than the publisher matches it, and what is
    # sent in between never arrives: poses go out until the node has applied some of each.
    deadline = time.monotonic() + 30
    while not all(applied(s) for s in SIGMAS) and time.monotonic() < deadline:
        publish_both()
    assert all(applied(s) for s in SIGMAS), diagnostics[-1:]
    before = applied('ground')      # no later than the node's count, so a lower bound
    raw.clear()
    # Malformed: a pose in another frame, one with no rotation.
    now = clock.now()
    pubs['ground'].publish(pose_to_msg(START, yaw_quaternion(0.0),
                                       Header(stamp=now.to_msg(), frame_id='map')))
    pubs['ground'].publish(pose_to_msg(START, np.zeros(4),
                                       Header(stamp=now.to_msg(), frame_id='world')))
    first = publish_both()
    for _ in range(89):                                      # 3 s at 30 Hz
        last = publish_both()
    assert wait_for(lambda: diagnostics and diagnostics[-1]['level'] == 2, 10), diagnostics[-1:]
    assert diagnostics[-1]['message'].startswith('no measurement for')
    assert diagnostics[-1]['malformed'] == '2'
    assert applied('ground') - before >= len(raw) - 5       # the gate may refuse a few

    stamps = np.array([stamp_to_ns(m.header.stamp) * 1e-9 for m in fused])
    assert len(fused) > 50 and stamps.max() <= last + 0.3 + 0.05     # quiet after the timeout
    errors, sigmas = [], []
    for msg, t in zip(fused, stamps):
        if first + 1.0 < t <= last:
            position, q, v_body, _ = msg_to_odometry(msg)
            errors.append(np.linalg.norm(position - truth(t)))
            sigmas.append(math.sqrt(msg.pose.covariance[0]))
            assert msg.header.frame_id == 'world' and msg.child_frame_id == 'base_link'
    rmse = math.sqrt(np.mean(np.square(errors)))
    assert len(errors) > 50 and rmse < 0.7 * math.sqrt(np.mean(np.square(raw))), rmse
    assert 0.0 < np.median(sigmas) < 0.03


def test_a_pose_with_covariance_is_fused_with_the_covariance_it_carries(ros_node, processes):
    """A vehicle at rest seen on one PoseWithCovarianceStamped topic: first with 0.2 m of
    noise and that covariance, then with 0.02 m and that one. The fused variance follows
    what the messages say (a hundredth of the variance in: over ten times smaller out),
    the estimate stays within its own 4 sigma; a covariance with a zero diagonal is
    malformed."""
    processes('pose_filter_node', ['-p', 'pose_filter.covariance_topics:=[cov/pose]',
                                   '-p', "pose_filter.odometry_topic:=''",
                                   '-p', 'pose_filter.accel_sigma:=0.5',
                                   '-p', 'pose_filter.diagnostics_period:=0.1'], label='filter')
    fused, diagnostics = listen(ros_node)
    pub = ros_node.create_publisher(PoseWithCovarianceStamped, '/cov/pose', RELIABLE)
    assert wait_for(lambda: pub.get_subscription_count() > 0, 30)
    clock, rng = ros_node.get_clock(), np.random.default_rng(1)

    def publish(sigma: float, n: int) -> None:
        cov = np.diag([sigma ** 2] * 3 + [1e6, 1e6, 0.01 ** 2])
        for _ in range(n):
            header = Header(stamp=clock.now().to_msg(), frame_id='world')
            pub.publish(pose_cov_to_msg(START + rng.normal(0.0, sigma, 3), yaw_quaternion(0.5),
                                        cov, header))
            time.sleep(1 / 30)

    def applied() -> int:
        return int(diagnostics[-1].get('cov/pose.applied', 0)) if diagnostics else 0

    deadline = time.monotonic() + 30
    while not applied() and time.monotonic() < deadline:
        publish(0.2, 1)
    publish(0.2, 45)
    coarse = fused[-1]
    publish(0.02, 45)
    fine = fused[-1]
    for msg in (coarse, fine):
        position, *_ = msg_to_odometry(msg)
        sd = np.sqrt(np.diag(np.reshape(msg.pose.covariance, (6, 6)))[:3])
        assert np.all(np.abs(position - START) <= 4 * sd), (position, sd)
    assert fine.pose.covariance[0] < coarse.pose.covariance[0] / 10
    pub.publish(pose_cov_to_msg(START, yaw_quaternion(0.5), np.zeros((6, 6)),
                                Header(stamp=clock.now().to_msg(), frame_id='world')))
    assert wait_for(lambda: diagnostics and diagnostics[-1]['malformed'] == '1', 10)


def test_a_bad_parameter_stops_the_node_with_one_line(tmp_path: Path):
    fatal = refused_at_start('pose_filter_node', ['-p', 'pose_filter.position_sigmas:=[0.03]'],
                             tmp_path)
    assert 'pose_filter.position_sigmas' in fatal, fatal


def test_every_parameter_is_in_the_yaml_with_its_default():
    from uav_vs.nodes.pose_filter_node import PARAMS

    yaml = read_params_file(REPO / 'config' / 'pose_filter.yaml')
    assert yaml == {spec.name: spec.default for spec in PARAMS}
