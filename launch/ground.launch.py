"""Ground station (chapter section 3): one camshift_node per camera, each in the camera's
namespace (cam1, cam2, cam3: the params file's `cameras.names`), and the
trinocular_pose_node, all with config/ground_trinocular.yaml; by default all in one
ground_station process (layout:=one_process), or each in a process of its own
(layout:=processes); every process on the executor `executor` names (docs/latency.md).

    ros2 launch uav_vs ground.launch.py [namespace:=uav1] [use_sim_time:=true]
        [ground_params:=my_station.yaml] [layout:=one_process|processes]
        [executor:=events|single]
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, GroupAction, OpaqueFunction
from launch_ros.actions import Node, PushRosNamespace

from uav_vs.flight.ground_replay import DEFAULT_LAYOUT, LAYOUTS
from uav_vs.ros.node_main import DEFAULT_EXECUTOR, EXECUTOR_ENV, EXECUTORS
from uav_vs.vision.ground_config import read_params_file

CONFIG = Path(get_package_share_directory('uav_vs')) / 'config'


def nodes(context: LaunchContext) -> list:
    """The ground_station, or a camshift_node per camera of the params file then the
    trinocular_pose_node."""
    args = context.launch_configurations
    params, layout, executor = args['ground_params'], args['layout'], args['executor']
    common = dict(package='uav_vs', output='screen', additional_env={EXECUTOR_ENV: executor})
    ros_args = ['--params-file', params, '-p', f"use_sim_time:={args['use_sim_time']}"]
    if layout == 'one_process':
        nodes = [Node(executable='ground_station', ros_arguments=ros_args, **common)]
    else:
        cameras = read_params_file(Path(params))['cameras.names']
        nodes = [Node(executable='camshift_node', namespace=cam,
                      ros_arguments=[*ros_args, '-p', f'camera:={cam}'], **common)
                 for cam in cameras]
        nodes.append(Node(executable='trinocular_pose_node', ros_arguments=ros_args, **common))
    return [GroupAction([PushRosNamespace(args['namespace']), *nodes])]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the station (the cameras go below it)'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='take the time from /clock'),
        DeclareLaunchArgument('ground_params',
                              default_value=str(CONFIG / 'ground_trinocular.yaml'),
                              description='params file: cameras and landmarks'),
        DeclareLaunchArgument('layout', default_value=DEFAULT_LAYOUT, choices=list(LAYOUTS),
                              description='one_process: one ground_station process; '
                              'processes: a process per node'),
        DeclareLaunchArgument('executor', default_value=DEFAULT_EXECUTOR,
                              choices=list(EXECUTORS),
                              description='events: EventsExecutor; single: '
                              'SingleThreadedExecutor'),
        OpaqueFunction(function=nodes),
    ])
