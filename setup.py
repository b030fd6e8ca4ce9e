"""ament_python package uav_vs (built by pip into a venv or by colcon)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'uav_vs'

# One console script per executable; `ros2 run uav_vs <name>` finds them in lib/uav_vs.
EXECUTABLES = {
    'camshift_node': 'uav_vs.nodes.camshift_node:main',
    'trinocular_pose_node': 'uav_vs.nodes.trinocular_pose_node:main',
    'ground_station': 'uav_vs.nodes.ground_station:main',
    'mavlink_relay_node': 'uav_vs.nodes.mavlink_relay_node:main',
    'sim_vehicle': 'uav_vs.sim.mavlink_vehicle:main',
    'make_ground_bag': 'uav_vs.sim.ground_bag:main',
    'homography_pose_node': 'uav_vs.nodes.homography_pose_node:main',
    'target_tracker_node': 'uav_vs.nodes.target_tracker_node:main',
    'target_follower_node': 'uav_vs.nodes.target_follower_node:main',
    'pose_filter_node': 'uav_vs.nodes.pose_filter_node:main',
    'link_monitor_node': 'uav_vs.nodes.link_monitor_node:main',
    'foxglove_node': 'uav_vs.nodes.foxglove_node:main',
    'make_onboard_bag': 'uav_vs.sim.onboard_bag:main',
    'fuzzy_controller_node': 'uav_vs.nodes.fuzzy_controller_node:main',
    'bag_play': 'uav_vs.nodes.bag_player:main',
    'bag_record': 'uav_vs.nodes.bag_recorder:main',
    'sim_world': 'uav_vs.nodes.sim_world_node:main',
    'frames_node': 'uav_vs.nodes.frames_node:main',
    'uav_vs_cmd': 'uav_vs.nodes.flight_cmd:main',
    'uav_vs_calibrate': 'uav_vs.calibrate:main',
}

DATA_FILES = [
    ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
    ('share/' + PACKAGE, ['package.xml']),
    ('share/' + PACKAGE + '/config', sorted(glob('config/*.*'))),
    ('share/' + PACKAGE + '/config/foxglove', sorted(glob('config/foxglove/*.json'))),
    ('share/' + PACKAGE + '/launch', sorted(glob('launch/*.launch.py'))),
]

if __name__ == '__main__':
    setup(
        name=PACKAGE,
        version='0.1.0',
        packages=find_packages(include=[PACKAGE, PACKAGE + '.*']),
        package_data={PACKAGE + '.sim': ['assets/*']},
        data_files=DATA_FILES,
        install_requires=['setuptools'],
        zip_safe=True,
        maintainer='uav_vs developers',
        description='Visual servoing for UAVs with ROS 2 Jazzy.',
        license='BSD-3-Clause',
        entry_points={
            'console_scripts': [f'{name} = {target}' for name, target in EXECUTABLES.items()],
        },
    )
