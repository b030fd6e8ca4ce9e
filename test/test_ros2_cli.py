"""The flight steps of docs/relay.md and docs/simulation.md with the real `ros2` command
line (the shared wheels): `ros2 service list/call`, `ros2 topic echo`, `ros2 topic pub`
against the relay, the controller and a simulated copter.

Truth: the simulated copter's own state (armed, mode, NED position), against which
what the CLI prints (service answers, odometry in ENU) is checked.
"""
import numpy as np
import yaml

from conftest import wait_for
from test_fuzzy_controller_node import start as start_controller
from test_mavlink_relay_node import start_relay, vehicle_and_connection


def test_flight_services_and_odometry_with_the_ros2_command_line(processes, ros2_cli):
    vehicle, connection = vehicle_and_connection('udp')
    try:
        start_relay(processes, connection, 'allow_arming:=true')
        start_controller(processes)
        # without the daemon the command line discovers for --spin-time (0.5 s by default):
        # too short for every endpoint of two nodes on a loaded machine
        listed = lambda: ros2_cli('service', 'list', '--no-daemon',
                                  '--spin-time', '3').stdout.split()
        services = {'/arm', '/set_guided', '/takeoff', '/land', '/controller/enable'}
        assert wait_for(lambda: services <= set(listed()), 30, period=1.0), listed()

        def call(name: str, kind: str, request: str = '{}') -> dict:
            run = ros2_cli('service', 'call', f'/{name}', f'std_srvs/srv/{kind}', request)
            assert run.returncode == 0, run.stdout + run.stderr
            # "response:\n<Type>_Response(success=True, message='...')"
            answer = run.stdout.rsplit('response:', 1)[1]
            return {'success': 'success=True' in answer, 'text': answer.strip()}

        assert wait_for(lambda: call('set_guided', 'Trigger')['success'], 30, period=1.0)
        armed = call('arm', 'SetBool', '{data: true}')
        assert armed['success'] and "message='arm: done (GUIDED, armed)'" in armed['text'], armed
        assert call('takeoff', 'Trigger')['success']
        truth = vehicle.truth()
        assert truth.armed and truth.mode == 'GUIDED' and 0.95 < -truth.position[2] < 1.05

        echo = ros2_cli('topic', 'echo', '--once', '--no-daemon', '/autopilot/odom',
                        'nav_msgs/msg/Odometry')
        assert echo.returncode == 0, echo.stderr
        odom = yaml.safe_load(echo.stdout.split('---')[0])
        position = odom['pose']['pose']['position']
        enu = np.array([position['x'], position['y'], position['z']])
        north, east, down = vehicle.truth().position
        assert np.allclose(enu, [east, north, -down], atol=0.05), (enu, vehicle.truth())
        assert odom['header']['frame_id'] == 'world' and odom['child_frame_id'] == 'base_link'

        enabled = call('controller/enable', 'SetBool', '{data: true}')
        assert enabled['success'] and "message='enabled'" in enabled['text'], enabled
        landed = call('land', 'Trigger')
        assert landed['success'], landed
    finally:
        vehicle.stop()


def test_a_refused_call_says_why_on_the_command_line(processes, ros2_cli):
    vehicle, connection = vehicle_and_connection('udp')
    try:
        start_relay(processes, connection)          # allow_arming false, as shipped
        run = lambda: ros2_cli('service', 'call', '/arm', 'std_srvs/srv/SetBool', '{data: true}')
        assert wait_for(lambda: 'response:' in run().stdout, 30, period=1.0)
        answer = run().stdout.rsplit('response:', 1)[1]
        assert 'success=False' in answer and 'allow_arming' in answer, answer
        assert not vehicle.truth().armed
    finally:
        vehicle.stop()
