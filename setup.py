"""ament_python package uav_vs (built by pip into a venv or by colcon)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'uav_vs'

# One console script per executable; `ros2 run uav_vs <name>` finds them in lib/uav_vs.
EXECUTABLES = {
}

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=[PACKAGE, PACKAGE + '.*']),
    package_data={PACKAGE + '.sim': ['assets/*']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='uav_vs developers',
    description='Visual servoing for UAVs with ROS 2 Jazzy.',
    license='BSD-3-Clause',
    entry_points={
        'console_scripts': [f'{name} = {target}' for name, target in EXECUTABLES.items()],
    },
)
