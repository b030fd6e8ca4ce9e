"""The venv is a ROS prefix, and colcon builds the package the way a ROS user would."""
import os
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

SETUP = runpy.run_path(str(REPO / 'setup.py'), run_name='test_install')
PREFIX = Path(sys.prefix)


def test_venv_prefix_has_executables_index_marker_and_share():
    for name in SETUP['EXECUTABLES']:
        exe = PREFIX / 'lib' / 'uav_vs' / name
        assert exe.exists() and os.access(exe, os.X_OK), exe
        assert shutil.which(name, path=str(PREFIX / 'bin')), name
    assert (PREFIX / 'share/ament_index/resource_index/packages/uav_vs').exists()
    for dest, files in SETUP['DATA_FILES']:
        for f in files:
            assert (PREFIX / dest / Path(f).name).read_bytes() == (REPO / f).read_bytes()


def test_ament_index_finds_the_package():
    from ament_index_python.packages import get_package_share_directory
    env_prefix = os.environ.get('AMENT_PREFIX_PATH', '')
    os.environ['AMENT_PREFIX_PATH'] = str(PREFIX)
    try:
        share = Path(get_package_share_directory('uav_vs'))
    finally:
        os.environ['AMENT_PREFIX_PATH'] = env_prefix
    assert (share / 'config' / 'ground_trinocular.yaml').exists()


def test_colcon_build_installs_every_executable(tmp_path):
    colcon = PREFIX / 'bin' / 'colcon'
    if not colcon.exists():
        pytest.fail('colcon is missing from the venv (requirements-dev.txt)')
    src = tmp_path / 'src' / 'uav_vs'
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        '.venv*', '.git', 'build', 'install', 'log', '*.egg-info', '__pycache__', 'bags'))
    run = subprocess.run([str(colcon), 'build', '--base-paths', 'src'], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    install = tmp_path / 'install' / 'uav_vs'
    for name in SETUP['EXECUTABLES']:
        assert os.access(install / 'lib' / 'uav_vs' / name, os.X_OK), name
    assert (install / 'share' / 'uav_vs' / 'package.xml').exists()
    assert (install / 'share/ament_index/resource_index/packages/uav_vs').exists()
