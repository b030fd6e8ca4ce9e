"""package.xml names only dependencies rosdep resolves on ROS 2 Jazzy, and covers the imports.

Every key below was checked in ros/rosdistro at ROSDISTRO_COMMIT: the system keys in
rosdep/python.yaml, with what they install on Ubuntu, and the ROS packages in
jazzy/distribution.yaml, with the repository releasing them. The test reads no network:
a new dependency is checked there first, then added here and to package.xml.
"""
import ast
import sys
import xml.etree.ElementTree as ET

from conftest import REPO

ROSDISTRO_COMMIT = '8468e88ccd523427f9131e39d2af0938f1c298b2'

# rosdep/python.yaml: key -> what `rosdep install` installs on Ubuntu (installer, package).
ROSDEP_KEYS = {
    'python3-numpy': ('apt', 'python3-numpy'),
    'python3-opencv': ('apt', 'python3-opencv'),
    'python3-scipy': ('apt', 'python3-scipy'),
    'python3-matplotlib': ('apt', 'python3-matplotlib'),
    'python3-yaml': ('apt', 'python3-yaml'),
    'python3-pymavlink-pip': ('pip', 'pymavlink'),
    'python3-rosbags-pip': ('pip', 'rosbags'),
    'python3-pytest': ('apt', 'python3-pytest'),
    'python3-hypothesis': ('apt', 'python3-hypothesis'),
}

# jazzy/distribution.yaml: package -> the repository whose release holds it.
JAZZY_PACKAGES = {
    'rclpy': 'rclpy',
    'rcl_interfaces': 'rcl_interfaces',
    'builtin_interfaces': 'rcl_interfaces',
    'rosgraph_msgs': 'rcl_interfaces',
    'test_msgs': 'rcl_interfaces',
    'std_msgs': 'common_interfaces',
    'std_srvs': 'common_interfaces',
    'geometry_msgs': 'common_interfaces',
    'sensor_msgs': 'common_interfaces',
    'nav_msgs': 'common_interfaces',
    'diagnostic_msgs': 'common_interfaces',
    'visualization_msgs': 'common_interfaces',
    'ament_index_python': 'ament_index',
    'tf2_msgs': 'geometry2',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
}

# Ubuntu 24.04 (noble) versions of the apt packages above (packages.ubuntu.com, noble).
NOBLE_VERSIONS = {
    'python3-numpy': '1.26.4',
    'python3-opencv': '4.6.0',
    'python3-scipy': '1.11.4',
    'python3-matplotlib': '3.6.3',
    'python3-yaml': '6.0.1',
}

# Modules the package imports whose name is not their dependency's.
MODULE_KEYS = {
    'numpy': 'python3-numpy',
    'cv2': 'python3-opencv',
    'scipy': 'python3-scipy',
    'matplotlib': 'python3-matplotlib',
    'yaml': 'python3-yaml',
    'pymavlink': 'python3-pymavlink-pip',
    'rosbags': 'python3-rosbags-pip',
    'backports': 'python3-rosbags-pip',   # backports.zstd: rosbags requires it before Python 3.14
}
# The standard library's from Python 3.14 (compression.zstd); backports.zstd before.
LATER_STDLIB = {'compression'}
# The fuzzy engine's references, imported only by the tests and benchmarks that compare.
TEST_ONLY = {'skfuzzy', 'simpful'}
# No rosdep key at ROSDISTRO_COMMIT (rosdep/python.yaml has none; jazzy's foxglove-sdk
# repository releases the C++ foxglove_bridge): pip installs it from requirements.txt,
# and foxglove_node, its only user, stops with one line naming it when it is missing.
PIP_ONLY = {'foxglove'}

# Pip distributions of requirements.txt -> their rosdep key (the ROS wheels are JAZZY_PACKAGES).
DISTRIBUTION_KEYS = {
    'numpy': 'python3-numpy',
    'opencv-python-headless': 'python3-opencv',
    'scipy': 'python3-scipy',
    'matplotlib': 'python3-matplotlib',
    'PyYAML': 'python3-yaml',
    'pymavlink': 'python3-pymavlink-pip',
    'rosbags': 'python3-rosbags-pip',
}


def dependencies(tags=('depend', 'build_depend', 'exec_depend', 'test_depend',
                       'build_export_depend', 'buildtool_depend')) -> dict[str, str]:
    """package.xml's dependencies: name -> tag."""
    root = ET.parse(REPO / 'package.xml').getroot()
    return {e.text.strip(): e.tag for tag in tags for e in root.iter(tag)}


def imported_modules() -> set[str]:
    """Top-level names of every module the package's code and launch files import."""
    names = set()
    for path in [*(REPO / 'uav_vs').rglob('*.py'), *(REPO / 'launch').glob('*.py')]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(a.name.split('.')[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module.split('.')[0])
    return names - set(sys.stdlib_module_names) - {'uav_vs'}


def pins(name: str) -> dict[str, str]:
    """A requirements file's own pins (not those of the files it includes): name -> version."""
    out = {}
    for line in (REPO / name).read_text().splitlines():
        if line.strip() and not line.startswith(('#', '-r')):
            dist, version = line.split('==')
            out[dist.split('[')[0]] = version
    return out


def test_every_dependency_is_a_key_rosdep_resolves():
    unknown = [d for d in dependencies() if d not in ROSDEP_KEYS and d not in JAZZY_PACKAGES]
    assert not unknown, (f'not rosdep keys at ros/rosdistro {ROSDISTRO_COMMIT[:12]} '
                         f'(rosdep/*.yaml or jazzy/distribution.yaml): {unknown}')


def test_every_module_the_package_imports_is_an_exec_dependency():
    deps = dependencies(('depend', 'exec_depend'))
    missing = {}
    for module in imported_modules() - LATER_STDLIB - TEST_ONLY - PIP_ONLY:
        key = MODULE_KEYS.get(module, module)
        if key not in deps:
            missing[module] = key
    assert not missing, f'imported without an exec_depend (module: key): {missing}'


def test_ubuntu_pins_are_nobles_apt_versions_and_requirements_txt_for_the_rest():
    pinned, ubuntu = pins('requirements.txt'), pins('requirements-ubuntu2404.txt')
    assert set(ubuntu) == set(pinned)
    for dist, version in pinned.items():
        key = DISTRIBUTION_KEYS.get(dist)
        if key is not None and ROSDEP_KEYS[key][0] == 'apt':
            assert ubuntu[dist].startswith(NOBLE_VERSIONS[key]), (dist, ubuntu[dist])
        else:
            assert ubuntu[dist] == version, (dist, ubuntu[dist], version)
