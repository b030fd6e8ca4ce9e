"""Parameters set at run time: a live one takes effect, checked as at start-up; the
others are read-only and refused.

Truth: the simulated copter's own state (the speed it flies at), the commands and
landmarks the nodes publish, and the SetParametersResult each change gets, through
the parameter services (rcl_interfaces SetParameters, SetParametersAtomically) and
through the real `ros2 param set`.
"""
import time

import numpy as np
import pytest
from geometry_msgs.msg import PolygonStamped
from rcl_interfaces.msg import Parameter as ParameterMsg, ParameterType
from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters, \
    SetParametersAtomically
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from conftest import REPO, wait_for
from test_fuzzy_controller_node import NORTH, Probe as ControllerProbe, start as start_controller
from test_mavlink_relay_node import Probe as RelayProbe, settle, start_relay, take_off, \
    vehicle_and_connection
from uav_vs.ros.convert import bgr_to_image, ns_to_stamp, polygon_to_array, pose_to_msg

GROUND = REPO / 'config' / 'ground_trinocular.yaml'
RELAY, CONTROLLER, CAMSHIFT = '/mavlink_relay_node', '/fuzzy_controller_node', '/cam1/camshift_node'


def call(node, kind, name: str, request, timeout: float = 20.0):
    client = node.create_client(kind, name)
    assert client.wait_for_service(timeout_sec=timeout), f'no {name} service'
    future = client.call_async(request)
    assert wait_for(future.done, timeout), f'{name} did not answer'
    node.destroy_client(client)
    return future.result()


def set_params(node, target: str, **values):
    """One SetParametersResult per value, each set on its own (as `ros2 param set`);
    keyword names stand for dotted ones: limits__max_speed is limits.max_speed."""
    request = SetParameters.Request(parameters=[_msg(k, v) for k, v in values.items()])
    return call(node, SetParameters, f'{target}/set_parameters', request).results


def set_atomically(node, target: str, **values):
    request = SetParametersAtomically.Request(parameters=[_msg(k, v) for k, v in values.items()])
    return call(node, SetParametersAtomically, f'{target}/set_parameters_atomically',
                request).result


def get_param(node, target: str, name: str):
    values = call(node, GetParameters, f'{target}/get_parameters',
                  GetParameters.Request(names=[name])).values
    return Parameter.from_parameter_msg(ParameterMsg(name=name, value=values[0])).value


def describe(node, target: str, names: list[str]) -> dict:
    descriptors = call(node, DescribeParameters, f'{target}/describe_parameters',
                       DescribeParameters.Request(names=names)).descriptors
    return {d.name: d for d in descriptors}


def _msg(name: str, value):
    kind = Parameter.Type.DOUBLE_ARRAY if isinstance(value, list) else None
    return Parameter(name.replace('__', '.'), kind, value).to_parameter_msg()




# ---------------------------------------------------------------- params.LiveParams
@pytest.fixture
def bare_node():
    import rclpy
    from rclpy.node import Node
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx)
    node = Node('live_params_test', context=ctx)
    yield node
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def test_live_params_check_as_declared_then_apply_once_stored(bare_node):
    """A live change goes through the spec's checks and then the node's hook, which sees
    every value; its apply runs only after rclpy stored the value; a read-only one is
    refused by rclpy; an integer is taken for a double; an empty list keeps its type."""
    from uav_vs.ros.params import LiveParams, Param, ParameterError, T, declare
    specs = [Param('low', T.DOUBLE, 0.0, 'lower bound', -10.0, 10.0, live=True),
             Param('high', T.DOUBLE, 1.0, 'upper bound', -10.0, 10.0, live=True),
             Param('mode', T.STRING, 'a', 'mode', choices=('a', 'b'), live=True),
             Param('box', T.DOUBLE_ARRAY, [], 'corner, m (empty: none)', live=True),
             Param('topic', T.STRING, 'in', 'input topic')]
    node = bare_node
    applied: list[tuple[float, float, object]] = []

    def prepare(p: dict, changed: set[str]):
        if p['low'] >= p['high']:
            raise ParameterError(f"low: expected below high ({p['high']}), got {p['low']}")
        return lambda: applied.append((node.get_parameter('low').value, p['low'], changed))

    LiveParams(node, specs, declare(node, specs), prepare)
    assert node.get_parameter('box').type_ == T.DOUBLE_ARRAY
    results = node.set_parameters([Parameter('low', value=0.5), Parameter('low', value=2.0),
                                   Parameter('mode', value='c'), Parameter('topic', value='x'),
                                   Parameter('low', value=-3), Parameter('box', value=[1, 2])])
    assert [r.successful for r in results] == [True, False, False, False, True, True]
    assert results[1].reason == 'low: expected below high (1.0), got 2.0'
    assert results[2].reason == "mode: expected a string (one of a, b), got 'c'"
    assert results[3].reason == 'Trying to set a read-only parameter: topic.'
    assert applied == [(0.5, 0.5, {'low'}), (-3.0, -3.0, {'low'}), (-3.0, -3.0, {'box'})]
    assert node.get_parameter('low').value == -3.0 and node.get_parameter('mode').value == 'a'
    assert list(node.get_parameter('box').value) == [1.0, 2.0]
    both = node.set_parameters_atomically([Parameter('low', value=4.0),
                                           Parameter('high', value=5.0)])
    assert both.successful and applied[-1][1:] == (4.0, {'low', 'high'})


def test_session_reconfigure_checks_as_at_start_and_changes_only_what_may_change():
    from uav_vs.autopilot.session import Limits, Session, SessionConfig
    session = Session(SessionConfig(connection='udpin:127.0.0.1:0'))
    session.reconfigure(limits=Limits(max_speed=0.3), command_timeout=1.0)
    assert session.config.limits.max_speed == 0.3 and session.config.command_timeout == 1.0
    with pytest.raises(ValueError, match='max_send_rate must be at least stream_rate'):
        session.reconfigure(max_send_rate=5.0)
    with pytest.raises(ValueError, match='cannot be changed while running: connection'):
        session.reconfigure(connection='udpin:127.0.0.1:1')
    assert session.config.max_send_rate == 50.0


# ---------------------------------------------------------------- the relay
def test_relay_speed_limit_set_live_is_what_the_vehicle_flies(ros_node, processes):
    """limits.max_speed 0.3 set in flight: a 1.5 m/s command is flown at 0.3 m/s."""
    vehicle, connection = vehicle_and_connection('udp')
    try:
        start_relay(processes, connection, 'allow_arming:=true', 'command_timeout:=2.5')
        probe = RelayProbe(ros_node)
        assert wait_for(lambda: probe.cmd.get_subscription_count() > 0, 20)
        take_off(probe, vehicle)
        (result,) = set_params(ros_node, RELAY, limits__max_speed=0.3)
        assert result.successful, result.reason
        assert get_param(ros_node, RELAY, 'limits.max_speed') == 0.3

        p0, fastest = vehicle.truth().position, 0.0
        end = time.monotonic() + 1.5
        while time.monotonic() < end:       # 1.5 m/s east for 1.5 s
            probe.send('world', [1.5, 0.0, 0.0])
            fastest = max(fastest, float(np.hypot(*vehicle.truth().velocity[:2])))
            time.sleep(0.05)
        probe.send('world', [0.0, 0.0, 0.0])
        settle(vehicle)
        assert 0.25 < fastest <= 0.3 * 1.02
        # east is NED y: 0.3 m/s for 1.5 s
        assert np.allclose(vehicle.truth().position - p0, [0.0, 0.45, 0.0], atol=0.08)
    finally:
        vehicle.stop()


def test_relay_refuses_a_fence_or_rates_that_do_not_hold_together(ros_node, processes):
    vehicle, connection = vehicle_and_connection('udp')
    try:
        start_relay(processes, connection)
        one_corner, = set_params(ros_node, RELAY, geofence__min=[-5.0, -5.0, 0.0])
        assert not one_corner.successful
        assert one_corner.reason.startswith('geofence.min: expected 3 numbers with geofence.max')
        box = set_atomically(ros_node, RELAY, geofence__min=[-5.0, -5.0, 0.0],
                             geofence__max=[5.0, 5.0, 3.0])
        assert box.successful, box.reason
        inverted, = set_params(ros_node, RELAY, geofence__min=[6.0, -5.0, 0.0])
        assert not inverted.successful
        assert inverted.reason == ('geofence.min: expected below geofence.max on every axis, '
                                   'got [6.0, -5.0, 0.0] and [5.0, 5.0, 3.0]')
        assert get_param(ros_node, RELAY, 'geofence.min').tolist() == [-5.0, -5.0, 0.0]
        slow, = set_params(ros_node, RELAY, max_send_rate=5.0)     # stream_rate is 10 Hz
        assert not slow.successful
        assert slow.reason == 'max_send_rate: expected at least stream_rate (10.0 Hz), got 5.0'
        fast, = set_params(ros_node, RELAY, max_send_rate=200.0)
        assert fast.successful, fast.reason
        read_only, = set_params(ros_node, RELAY, allow_arming=True)
        assert not read_only.successful and 'read-only' in read_only.reason
        assert get_param(ros_node, RELAY, 'allow_arming') is False
    finally:
        vehicle.stop()


# ---------------------------------------------------------------- the controller
def _horizontal(probe) -> float:
    linear, _ = probe.last_cmd()
    return float(np.hypot(linear[0], linear[1]))


def test_controller_limits_and_rules_set_live_shape_the_commands(ros_node, processes):
    """A setpoint 10 m east saturates the command at max_horizontal_speed (1.0 m/s); set
    to 0.3 at run time, the commands follow; a new axis limit in the rule base rebuilds
    the controller; an invalid rule base is refused and changes nothing."""
    probe = ControllerProbe(ros_node)
    start_controller(processes, 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([10.0, 0.0, 1.0], NORTH, Header(frame_id='world')))
    poses = probe.publish_poses([0.0, 0.0, 1.0], NORTH)
    try:
        assert wait_for(lambda: probe.cmds and abs(_horizontal(probe) - 1.0) < 1e-6, 10)
        (result,) = set_params(ros_node, CONTROLLER, controller__max_horizontal_speed=0.3)
        assert result.successful, result.reason
        mark = len(probe.cmds)
        assert wait_for(lambda: len(probe.cmds) > mark + 10, 5)
        assert abs(_horizontal(probe) - 0.3) < 1e-6

        (result,) = set_params(ros_node, CONTROLLER, controller__max_horizontal_speed=1.0)
        assert result.successful, result.reason
        assert wait_for(lambda: abs(_horizontal(probe) - 1.0) < 1e-6, 5)
        (result,) = set_params(ros_node, CONTROLLER, fuzzy__axes__x__limit=0.2)
        assert result.successful, result.reason
        assert wait_for(lambda: abs(_horizontal(probe) - 0.2) < 1e-6, 5)

        bad = Parameter('fuzzy.axes.x.rules', Parameter.Type.STRING_ARRAY,
                        ['IF error IS HUGE THEN command IS PB'])
        refused = call(ros_node, SetParameters, f'{CONTROLLER}/set_parameters',
                       SetParameters.Request(parameters=[bad.to_parameter_msg()])).results[0]
        assert not refused.successful and 'HUGE' in refused.reason, refused.reason
        assert len(get_param(ros_node, CONTROLLER, 'fuzzy.axes.x.rules')) == 35
        zero, unknown = set_params(ros_node, CONTROLLER, fuzzy__axes__x__error__gain=0.0,
                                   controller__speed=1.0)
        assert (zero.successful, zero.reason) == (
            False, "axis 'x': error.gain must be finite and non-zero")
        assert (unknown.successful, unknown.reason) == (
            False, 'controller.speed: unknown parameter')
        mark = len(probe.cmds)
        assert wait_for(lambda: len(probe.cmds) > mark + 10, 5)
        assert abs(_horizontal(probe) - 0.2) < 1e-6
    finally:
        probe.stop_publishing(poses)


# ---------------------------------------------------------------- camshift
def test_camshift_min_confidence_set_live_decides_what_is_found(ros_node, processes):
    from uav_vs.sim.ground_scene import GroundScene, figure_eight
    from uav_vs.vision.ground_config import load_ground_config, read_params_file
    processes('camshift_node', ['--params-file', str(GROUND), '-r', '__ns:=/cam1',
                                '-p', 'camera:=cam1', '-p', 'camshift.image_qos:=reliable'],
              label='cam1')
    out: list[PolygonStamped] = []
    ros_node.create_subscription(PolygonStamped, '/cam1/landmarks', out.append, 10)
    pub = ros_node.create_publisher(Image, '/cam1/image_raw', 10)
    assert wait_for(lambda: pub.get_subscription_count() > 0, 30)
    scene = GroundScene(load_ground_config(read_params_file(GROUND)), seed=1)
    frames = iter(range(1, 100))

    images, _ = scene.render(figure_eight(0.0))

    def landmarks() -> np.ndarray:
        """The landmarks the node finds in the same image, stamped anew."""
        n = len(out)
        stamp = ns_to_stamp(next(frames) * 100_000_000)
        pub.publish(bgr_to_image(images[0], Header(stamp=stamp, frame_id='cam1_optical')))
        assert wait_for(lambda: len(out) > n, 10)
        return polygon_to_array(out[-1])

    found = np.isfinite(landmarks()[:, 0])
    assert found.sum() >= 3
    (result,) = set_params(ros_node, CAMSHIFT, camshift__min_confidence=1.0)
    assert result.successful, result.reason
    assert np.isnan(landmarks()[:, 0]).all()      # a window is never all landmark
    (result,) = set_params(ros_node, CAMSHIFT, camshift__min_confidence=0.2)
    assert result.successful, result.reason
    assert (np.isfinite(landmarks()[:, 0]) == found).all()

    too_high, = set_params(ros_node, CAMSHIFT, camshift__min_confidence=1.5)
    assert not too_high.successful and 'camshift.min_confidence' in too_high.reason
    qos, = set_params(ros_node, CAMSHIFT, camshift__image_qos='bogus')
    assert not qos.successful
    assert qos.reason == 'Trying to set a read-only parameter: camshift.image_qos.'
    assert get_param(ros_node, CAMSHIFT, 'camshift.image_qos') == 'reliable'
    descriptors = describe(ros_node, CAMSHIFT, ['camshift.image_qos', 'camera',
                                                'cameras.cam1.K', 'camshift.min_confidence',
                                                'camshift.future_tolerance'])
    assert [d.read_only for d in descriptors.values()] == [True, True, True, False, False]
    assert descriptors['cameras.cam1.K'].type == ParameterType.PARAMETER_DOUBLE_ARRAY


def test_a_live_choice_is_checked_as_at_start_up(ros_node, processes):
    """trinocular.method bogus is refused with the start-up check's words; a valid one is
    taken and poses go on."""
    processes('trinocular_pose_node', ['--params-file', str(GROUND)])
    node = '/trinocular_pose_node'
    bogus, = set_params(ros_node, node, trinocular__method='bogus')
    assert not bogus.successful
    assert bogus.reason == "trinocular.method: expected a string (one of lsq, opencv), got 'bogus'"
    too_many, = set_params(ros_node, node, trinocular__min_cameras=4)
    assert not too_many.successful
    assert too_many.reason == 'trinocular.min_cameras: expected <= 3 (cameras.names)'
    opencv, = set_params(ros_node, node, trinocular__method='opencv')
    assert opencv.successful, opencv.reason
    frame_id, = set_params(ros_node, node, trinocular__frame_id='map')
    assert not frame_id.successful and 'read-only' in frame_id.reason


# ---------------------------------------------------------------- onboard vision
def test_onboard_thresholds_set_live_take_effect_and_are_checked_together(ros_node, processes):
    """image_quality.min_sharpness set high turns the next frame into a loss; thresholds
    that start-up checks together are refused together; what builds the tracker is
    read-only. The target tracker refuses a min_inliers its template cannot give."""
    from test_onboard_nodes import ASSETS, CONFIG, POSE_NODE_ARGS, Probe as PoseProbe, header, \
        level_pose
    from uav_vs.sim.onboard_scene import OnboardScene
    from uav_vs.ros.convert import stamp_to_ns
    from uav_vs.vision.ground_config import read_params_file
    from uav_vs.vision.onboard_config import load_onboard_config
    processes('homography_pose_node', POSE_NODE_ARGS)
    processes('target_tracker_node', ['--params-file', str(CONFIG),
                                      '-p', f"target.template:={ASSETS / 'box.png'}"])
    probe, node = PoseProbe(ros_node), '/homography_pose_node'
    assert wait_for(lambda: probe.ready() and ros_node.count_publishers('/onboard/pose'), 30)
    cfg = load_onboard_config(read_params_file(CONFIG))
    frame = OnboardScene(cfg.camera, cfg.camera_to_body, seed=1).render(
        *level_pose(0.0, 0.0, 1.0, 0.0))
    # Frames until one comes back as a pose: the node's pose publisher may match the
    # probe's subscription after the first pose went out.
    k = -1
    while not probe.poses and k < 20:
        k += 1
        probe.image.publish(bgr_to_image(frame, header(k)))
        wait_for(lambda: stamp_to_ns(header(k).stamp) in probe.poses, 1.0)
    assert probe.poses, 'no onboard/pose for 20 frames'
    (result,) = set_params(ros_node, node, image_quality__min_sharpness=1e6)
    assert result.successful, result.reason
    probe.image.publish(bgr_to_image(frame, header(k + 1)))
    lost = f'{stamp_to_ns(header(k + 1).stamp) * 1e-9:.3f}'
    assert wait_for(lambda: probe.value('last_loss_stamp') == lost, 15), probe.status
    assert probe.value('last_loss').startswith('blurred or texture-less image')
    assert stamp_to_ns(header(k + 1).stamp) not in probe.poses

    together, = set_params(ros_node, node, homography__min_inliers=30)
    assert not together.successful
    assert together.reason == 'homography.min_inliers: 30 must not exceed features.min_tracks (20)'
    method, = set_params(ros_node, node, homography__method='bogus')
    assert not method.successful and method.reason.startswith(
        'homography.method: expected a string (one of ransac, ')
    window, = set_params(ros_node, node, klt__win_size=15)
    assert not window.successful and 'read-only' in window.reason

    tracker = '/target_tracker_node'
    ratio, = set_params(ros_node, tracker, target__ratio=0.6)
    assert ratio.successful, ratio.reason
    greedy, = set_params(ros_node, tracker, target__min_inliers=10000)
    assert not greedy.successful
    assert greedy.reason.startswith('target.template: ') and 'fewer than min_inliers=10000' \
        in greedy.reason, greedy.reason
    assert get_param(ros_node, tracker, 'target.min_inliers') == 12


# ---------------------------------------------------------------- the ros2 command line
def test_ros2_param_set_takes_a_live_value_and_refuses_a_read_only_one(ros_node, processes,
                                                                      ros2_cli):
    probe = ControllerProbe(ros_node)
    start_controller(processes, 'controller.enabled:=true')
    assert wait_for(lambda: probe.setpoint.get_subscription_count() > 0, 30)
    probe.setpoint.publish(pose_to_msg([10.0, 0.0, 1.0], NORTH, Header(frame_id='world')))
    poses = probe.publish_poses([0.0, 0.0, 1.0], NORTH)
    try:
        assert wait_for(lambda: probe.cmds and abs(_horizontal(probe) - 1.0) < 1e-6, 10)
        live = ros2_cli('param', 'set', '--no-daemon', CONTROLLER,
                        'controller.max_horizontal_speed', '0.3')
        assert live.stdout.strip() == 'Set parameter successful', live.stdout + live.stderr
        assert wait_for(lambda: abs(_horizontal(probe) - 0.3) < 1e-6, 5)
        # an integer where a double is declared, as a params file may write it
        integer = ros2_cli('param', 'set', '--no-daemon', CONTROLLER,
                           'controller.max_horizontal_speed', '1')
        assert integer.stdout.strip() == 'Set parameter successful', integer.stderr
        assert wait_for(lambda: abs(_horizontal(probe) - 1.0) < 1e-6, 5)

        fixed = ros2_cli('param', 'set', '--no-daemon', CONTROLLER, 'controller.mode', 'tracking')
        assert fixed.stderr.strip() == ('Setting parameter failed: Trying to set a read-only '
                                        'parameter: controller.mode.'), fixed.stdout + fixed.stderr
        # out of the declared range: refused by rclpy (the controller's own checks are
        # the test above's)
        bad = ros2_cli('param', 'set', '--no-daemon', CONTROLLER, 'fuzzy.axes.x.limit', '-1.0')
        assert bad.stderr.strip() == ('Setting parameter failed: Parameter fuzzy.axes.x.limit '
                                      'out of range Min: 1e-09, Max: 1000.0, value: -1.0'), \
            bad.stdout + bad.stderr
        shown = ros2_cli('param', 'describe', '--no-daemon', CONTROLLER, 'controller.mode',
                         'fuzzy.axes.yaw.limit')
        mode, _, limit = shown.stdout.partition('Parameter name: fuzzy.axes.yaw.limit')
        assert 'Parameter name: controller.mode' in mode and 'Read only: true' in mode, \
            shown.stdout + shown.stderr
        assert 'Description: |command| saturation after the output gain, rad/s' in limit
        assert 'Min value: 1e-09' in limit and 'Read only' not in limit, \
            shown.stdout + shown.stderr
    finally:
        probe.stop_publishing(poses)
