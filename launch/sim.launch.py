"""The whole graph in closed loop around the simulated vehicle, as `make demo` starts it
(uav_vs/flight/scenario.py): sim_world (the MAVLink vehicle and its four cameras, with the
vision nodes' params files and config/sim_world.yaml), the ground station
(ground.launch.py), the onboard vision (onboard.launch.py) and the controller on
ground/pose with the relay connected to the vehicle (control.launch.py).

Nothing flies until told: set_guided, arm, takeoff, controller/enable, then
setpoints (docs/simulation.md, Closed loop). The onboard pose node ties its first frame (at
sim_world's onboard.min_height, while climbing) to the params file's init.*; to fly on
it, start it at the hover as the scenarios do (onboard:=false here).

    ros2 launch uav_vs sim.launch.py [port:=5760] [autopilot:=px4] [onboard:=false]
        [namespace:=uav1] [ground_params:=...] [onboard_params:=...] [world_params:=...]
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import (DeclareLaunchArgument, GroupAction, IncludeLaunchDescription,
                            OpaqueFunction)
from launch.conditions import IfCondition
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node, PushRosNamespace

SHARE = Path(get_package_share_directory('uav_vs'))
CONFIG = SHARE / 'config'


def include(name: str, condition: IfCondition | None = None, **arguments: str):
    """launch/<name>.launch.py with the shared arguments and `arguments`."""
    shared = {arg: LaunchConfiguration(arg) for arg in
              ('namespace', 'use_sim_time', 'ground_params', 'onboard_params')}
    return IncludeLaunchDescription(
        PythonLaunchDescriptionSource(str(SHARE / 'launch' / f'{name}.launch.py')),
        launch_arguments={**shared, **arguments}.items(), condition=condition)


def vehicle(context: LaunchContext) -> list:
    """sim_world serving MAVLink on `port`, in `namespace`."""
    args = context.launch_configurations
    files = [args['ground_params'], args['onboard_params'], args['world_params']]
    world = Node(package='uav_vs', executable='sim_world', output='screen',
                 ros_arguments=[*(item for f in files for item in ('--params-file', f)),
                                '-p', f"vehicle.connection:=tcpin:127.0.0.1:{args['port']}",
                                '-p', f"vehicle.autopilot:={args['autopilot']}",
                                '-p', f"use_sim_time:={args['use_sim_time']}"])
    return [GroupAction([PushRosNamespace(args['namespace']), world])]


def generate_launch_description() -> LaunchDescription:
    port = LaunchConfiguration('port')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the graph'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='take the time from /clock'),
        DeclareLaunchArgument('port', default_value='5760',
                              description="TCP port of the vehicle's MAVLink endpoint (loopback)"),
        DeclareLaunchArgument('autopilot', default_value='ardupilot',
                              description='whose MAVLink behaviour the vehicle follows: '
                                          'ardupilot or px4'),
        DeclareLaunchArgument('takeoff_height', default_value='1.5',
                              description='takeoff service height, m (a float)'),
        DeclareLaunchArgument('onboard', default_value='true',
                              description='start the onboard vision nodes too'),
        DeclareLaunchArgument('ground_params',
                              default_value=str(CONFIG / 'ground_trinocular.yaml'),
                              description='params file: ground cameras and landmarks'),
        DeclareLaunchArgument('onboard_params', default_value=str(CONFIG / 'onboard.yaml'),
                              description='params file: onboard camera and tracking'),
        DeclareLaunchArgument('world_params', default_value=str(CONFIG / 'sim_world.yaml'),
                              description='params file of the simulator'),
        DeclareLaunchArgument('controller_params',
                              default_value=str(CONFIG / 'fuzzy_controller.yaml'),
                              description='params file of the controller'),
        DeclareLaunchArgument('relay_params', default_value=str(CONFIG / 'mavlink_relay.yaml'),
                              description='params file of the relay'),
        OpaqueFunction(function=vehicle),
        include('ground'),
        include('onboard', IfCondition(LaunchConfiguration('onboard'))),
        include('control', connection=['tcp:127.0.0.1:', port], allow_arming='true',
                takeoff_height=LaunchConfiguration('takeoff_height'), pose_topic='ground/pose',
                controller_params=LaunchConfiguration('controller_params'),
                relay_params=LaunchConfiguration('relay_params')),
    ])
