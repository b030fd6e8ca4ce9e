"""Onboard vision (chapter sections 2 and 4): homography_pose_node (onboard/pose) and
target_tracker_node (onboard/target), both with config/onboard.yaml. The pose node ties
its first frame to `world` by the params file's init.*. With follow:=true,
target_follower_node too: it publishes `setpoint` above the tracked target (section 5),
which the controller then flies to.

    ros2 launch uav_vs onboard.launch.py [namespace:=uav1] [use_sim_time:=true]
        [onboard_params:=my_camera.yaml] [follow:=true]
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, OpaqueFunction
from launch_ros.actions import Node, PushRosNamespace

CONFIG = Path(get_package_share_directory('uav_vs')) / 'config'


def nodes(context: LaunchContext) -> list:
    """The onboard nodes on the one params file."""
    args = context.launch_configurations
    sim_time = ['-p', f"use_sim_time:={args['use_sim_time']}"]
    names = ['homography_pose_node', 'target_tracker_node']
    if args['follow'].lower() == 'true':
        names.append('target_follower_node')
    nodes = [Node(package='uav_vs', executable=name, output='screen',
                  ros_arguments=['--params-file', args['onboard_params'], *sim_time])
             for name in names]
    return [GroupAction([PushRosNamespace(args['namespace']), *nodes])]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the nodes'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='take the time from /clock'),
        DeclareLaunchArgument('onboard_params', default_value=str(CONFIG / 'onboard.yaml'),
                              description='params file: camera, mounting, init, tracking, '
                              'target, follow'),
        DeclareLaunchArgument('follow', default_value='false', choices=['true', 'false'],
                              description='also target_follower_node: setpoints above the '
                              'tracked target'),
        OpaqueFunction(function=nodes),
    ])
