"""Finish the venv's editable install as a ROS prefix (like `colcon build --symlink-install`).

`pip install -e .` puts console scripts in <prefix>/bin and installs no data files.
ROS looks for executables in <prefix>/lib/uav_vs and for the package in the ament
index under <prefix>/share. This links both to the checkout, so edits are live.
"""
import runpy
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def link(target: Path, link_path: Path) -> None:
    link_path.parent.mkdir(parents=True, exist_ok=True)
    if link_path.is_symlink() or link_path.exists():
        link_path.unlink()
    link_path.symlink_to(target)


def main() -> None:
    prefix = Path(sys.prefix)
    setup = runpy.run_path(str(REPO / 'setup.py'), run_name='install_ros_prefix')
    package = setup['PACKAGE']
    lib = prefix / 'lib' / package
    if lib.is_dir():
        for old in lib.iterdir():
            old.unlink()
    for name in setup['EXECUTABLES']:
        script = prefix / 'bin' / name
        if not script.exists():
            sys.exit(f'console script {name} missing from {script.parent}')
        link(script, lib / name)
    for dest, files in setup['DATA_FILES']:
        for f in files:
            link(REPO / f, prefix / dest / Path(f).name)


if __name__ == '__main__':
    main()
