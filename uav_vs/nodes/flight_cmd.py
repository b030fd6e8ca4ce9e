"""uav_vs_cmd: the flight commands of `ros2 service call` / `ros2 topic pub`, without the ros2 CLI.

    uav_vs_cmd [--ns NS] [--timeout S] set_guided | arm | disarm | takeoff | land
    uav_vs_cmd [--ns NS] [--timeout S] enable | disable
    uav_vs_cmd [--ns NS] [--timeout S] setpoint X Y Z [YAW_DEG]  [--ros-args ...]

set_guided, takeoff and land call the relay's std_srvs/Trigger services of those names,
arm and disarm its `arm` (std_srvs/SetBool true / false); enable and disable the
controller's `controller/enable` (SetBool); all under `--ns`.
setpoint publishes a geometry_msgs/PoseStamped on `setpoint` in frame `world` (ENU, m;
yaw in degrees from east, counter-clockwise, default 90: north, the heading the vehicle
boots with), reliable and transient local: it waits for a subscriber, sends the pose
a few times (the mission, too, sends its setpoint again) and waits for the
acknowledgements.

Exit status: 0 when the service answered success (its message on stdout) or the
setpoint was delivered; 1 when it answered failure (its message on stderr), did not
answer, or no subscriber took the setpoint within `--timeout`; 2 on bad arguments.
"""
import argparse
import math
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.exceptions import InvalidNamespaceException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from std_msgs.msg import Header
from std_srvs.srv import SetBool, Trigger

from uav_vs.ros.convert import pose_to_msg, yaw_quaternion

# Command -> (service type, service name relative to --ns, SetBool data or None, help).
SERVICES = {
    'set_guided': (Trigger, 'set_guided', None, 'the mode flying velocities (GUIDED, OFFBOARD)'),
    'arm': (SetBool, 'arm', True, 'arm (the relay needs allow_arming)'),
    'disarm': (SetBool, 'arm', False, 'disarm'),
    'takeoff': (Trigger, 'takeoff', None, "take off to the relay's takeoff_height"),
    'land': (Trigger, 'land', None, 'land where the vehicle is'),
    'enable': (SetBool, 'controller/enable', True, 'start servoing'),
    'disable': (SetBool, 'controller/enable', False, 'stop servoing (zero commands)'),
}
SETPOINT_REPEATS = 3          # sends of one setpoint, SETPOINT_PERIOD_S apart
SETPOINT_PERIOD_S = 0.1
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class CommandFailed(Exception):
    """A refused, unanswered or undelivered command; the message says why."""


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='uav_vs_cmd', description=__doc__.splitlines()[0])
    parser.add_argument('--ns', default='', help='namespace of the relay and the controller')
    parser.add_argument('--timeout', type=float, default=30.0,
                        help='s to wait for the service (or a setpoint subscriber) and its '
                             'answer (default %(default)s; a takeoff answers at its height)')
    commands = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for name, (_, _, _, text) in SERVICES.items():
        commands.add_parser(name, help=text)
    setpoint = commands.add_parser('setpoint', help='publish a setpoint in world')
    for axis in 'XYZ':
        setpoint.add_argument(axis.lower(), metavar=axis, type=float, help=f'{axis}, m (ENU)')
    setpoint.add_argument('yaw_deg', metavar='YAW_DEG', type=float, nargs='?', default=90.0,
                          help='heading, deg from east counter-clockwise (default 90: north)')
    args = parser.parse_args(argv)
    if args.timeout <= 0:
        parser.error('--timeout must be positive')
    if args.command == 'setpoint' and not all(map(math.isfinite, (args.x, args.y, args.z,
                                                                  args.yaw_deg))):
        parser.error('setpoint: X, Y, Z and YAW_DEG must be finite')
    return args


def call_service(node: Node, command: str, timeout: float) -> str:
    """Call the command's service; its message on success, CommandFailed otherwise."""
    srv_type, name, data, _ = SERVICES[command]
    client = node.create_client(srv_type, name)
    service = node.resolve_service_name(client.srv_name)
    deadline = time.monotonic() + timeout
    if not client.wait_for_service(timeout_sec=timeout):
        raise CommandFailed(f'{service}: service not available within {timeout:g} s')
    request = srv_type.Request() if data is None else SetBool.Request(data=data)
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future,
                                     timeout_sec=max(deadline - time.monotonic(), 0.0))
    if not future.done():
        raise CommandFailed(f'{service}: no answer within {timeout:g} s')
    response = future.result()
    if not response.success:
        raise CommandFailed(response.message or f'{service}: refused')
    return response.message


def setpoint_msg(node: Node, x: float, y: float, z: float, yaw_deg: float) -> PoseStamped:
    """The setpoint pose in world, stamped now."""
    yaw = math.radians(yaw_deg)
    header = Header(stamp=node.get_clock().now().to_msg(), frame_id='world')
    return pose_to_msg(np.array([x, y, z]), yaw_quaternion(yaw), header)


def publish_setpoint(node: Node, args: argparse.Namespace) -> str:
    """Once a subscriber is matched, send the setpoint a few times; wait for the
    acknowledgements."""
    pub = node.create_publisher(PoseStamped, 'setpoint', LATCHED)
    timeout = args.timeout
    deadline = time.monotonic() + timeout
    while pub.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            raise CommandFailed(f'{pub.topic_name}: no subscriber within {timeout:g} s')
        time.sleep(0.05)
    msg = setpoint_msg(node, args.x, args.y, args.z, args.yaw_deg)
    for k in range(SETPOINT_REPEATS):
        if k:
            time.sleep(SETPOINT_PERIOD_S)
        pub.publish(msg)
    remaining = max(deadline - time.monotonic(), 0.5)
    if not pub.wait_for_all_acked(Duration(seconds=remaining)):
        raise CommandFailed(f'{pub.topic_name}: not acknowledged within {timeout:g} s')
    return (f'{pub.topic_name}: ({args.x:g}, {args.y:g}, {args.z:g}) m, yaw {args.yaw_deg:g} deg '
            f'in world, sent to {pub.get_subscription_count()} subscriber(s)')


def run(node: Node, args: argparse.Namespace) -> str:
    if args.command == 'setpoint':
        return publish_setpoint(node, args)
    return call_service(node, args.command, args.timeout)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else ['uav_vs_cmd', *argv]
    args = parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    try:
        node = rclpy.create_node('uav_vs_cmd', namespace='/' + args.ns.strip('/'),
                                 start_parameter_services=False)
    except InvalidNamespaceException as err:
        print(f'uav_vs_cmd: error: --ns: {err}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        print(run(node, args))
        return 0
    except CommandFailed as err:
        print(f'uav_vs_cmd {args.command}: {err}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
