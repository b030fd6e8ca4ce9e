"""Make the venv a ROS prefix: link each console script into <prefix>/lib/uav_vs/.

pip puts console scripts in <prefix>/bin; `ros2 run uav_vs <exe>` looks only in
<prefix>/lib/uav_vs (where colcon puts them). A relative link serves both.
"""
import sys
from importlib.metadata import distribution
from pathlib import Path


def main() -> None:
    prefix = Path(sys.prefix)
    lib = prefix / 'lib' / 'uav_vs'
    lib.mkdir(parents=True, exist_ok=True)
    for old in lib.iterdir():
        if old.is_symlink():
            old.unlink()
    for ep in distribution('uav_vs').entry_points.select(group='console_scripts'):
        if not (prefix / 'bin' / ep.name).exists():
            sys.exit(f'console script {ep.name} missing from {prefix / "bin"}')
        (lib / ep.name).symlink_to(Path('..', '..', 'bin', ep.name))


if __name__ == '__main__':
    main()
