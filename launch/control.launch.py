"""Control (chapter section 6): fuzzy_controller_node (pose error to cmd_vel) and
mavlink_relay_node (cmd_vel to the autopilot, autopilot/odom back), with
config/fuzzy_controller.yaml and config/mavlink_relay.yaml. An empty argument leaves
the params file's value.

    ros2 launch uav_vs control.launch.py connection:=udpin:127.0.0.1:14550 allow_arming:=true
        [namespace:=uav1] [pose_topic:=onboard/pose] [controller_params:=...] [relay_params:=...]
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, OpaqueFunction
from launch_ros.actions import Node, PushRosNamespace

CONFIG = Path(get_package_share_directory('uav_vs')) / 'config'

# Launch argument -> parameter it sets when given.
CONTROLLER_OVERRIDES = {'pose_topic': 'controller.pose_topic'}
RELAY_OVERRIDES = {'connection': 'connection', 'allow_arming': 'allow_arming',
                   'takeoff_height': 'takeoff_height'}


def ros_arguments(args: dict, params_file: str, names: dict[str, str]) -> list[str]:
    """The params file, then `-p parameter:=value` for use_sim_time and for each argument
    of `names` that is set (a rule after the file wins over it)."""
    rules = [f"use_sim_time:={args['use_sim_time']}",
             *(f'{param}:={args[arg]}' for arg, param in names.items() if args[arg])]
    return ['--params-file', args[params_file], *(item for rule in rules for item in ('-p', rule))]


def nodes(context: LaunchContext) -> list:
    """The controller and the relay."""
    args = context.launch_configurations
    controller = Node(package='uav_vs', executable='fuzzy_controller_node', output='screen',
                      ros_arguments=ros_arguments(args, 'controller_params', CONTROLLER_OVERRIDES))
    relay = Node(package='uav_vs', executable='mavlink_relay_node', output='screen',
                 ros_arguments=ros_arguments(args, 'relay_params', RELAY_OVERRIDES))
    return [GroupAction([PushRosNamespace(args['namespace']), controller, relay])]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the nodes'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='take the time from /clock'),
        DeclareLaunchArgument('controller_params',
                              default_value=str(CONFIG / 'fuzzy_controller.yaml'),
                              description='params file of the controller (e.g. '
                                          'fuzzy_controller_pid.yaml)'),
        DeclareLaunchArgument('relay_params', default_value=str(CONFIG / 'mavlink_relay.yaml'),
                              description='params file of the relay'),
        DeclareLaunchArgument('connection', default_value='',
                              description='autopilot MAVLink connection, e.g. tcp:127.0.0.1:5760, '
                                          'udpin:0.0.0.0:14540, /dev/ttyACM0'),
        DeclareLaunchArgument('allow_arming', default_value='',
                              description='true: the arm service may arm'),
        DeclareLaunchArgument('takeoff_height', default_value='',
                              description='takeoff service height, m (a float: 1.5)'),
        DeclareLaunchArgument('pose_topic', default_value='',
                              description='pose the controller flies on: ground/pose or '
                                          'onboard/pose'),
        OpaqueFunction(function=nodes),
    ])
