"""Build the ROS interface packages that PyPI lacks into the venv, as `colcon build` would.

tf2_msgs (/tf) and composition_interfaces (which launch_ros imports) have no wheels.
Their definitions are in tools/interfaces/<package>/, unchanged from ROS 2 Jazzy, so
their type hashes match every other Jazzy host. Each is built with the ROS IDL
generators from PyPI (requirements-tools.txt) and installed into the venv's prefix: the
Python package into site-packages, the typesupport libraries into lib/, the
definitions and the ament index entry into share/. Build trees are kept in
build/interfaces/<venv>/<package> (one set per venv: each is configured for its own
Python and NumPy), so a second run only reinstalls what changed.
"""
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
INTERFACES = REPO / 'tools' / 'interfaces'
BUILD = REPO / 'build' / 'interfaces'


def interface_packages() -> list[Path]:
    """The vendored packages: every directory of tools/interfaces with a package.xml."""
    return sorted(p.parent for p in INTERFACES.glob('*/package.xml'))


def build_environment(prefix: Path) -> dict[str, str]:
    """The environment of a ROS workspace whose only underlay is the venv."""
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = str(prefix)
    env['CMAKE_PREFIX_PATH'] = str(prefix)
    env['PATH'] = f'{prefix / "bin"}{os.pathsep}{env.get("PATH", "")}'
    return env


def cached_source(build_dir: Path) -> str | None:
    """The source directory a CMake build tree was configured for, if any."""
    cache = build_dir / 'CMakeCache.txt'
    if not cache.exists():
        return None
    for line in cache.read_text().splitlines():
        if line.startswith('CMAKE_HOME_DIRECTORY:'):
            return line.split('=', 1)[1]
    return None


def run_logged(args: list[str], env: dict[str, str], log: Path) -> None:
    """Run one build step with its output appended to log; on failure show it and exit."""
    with log.open('a') as out:
        out.write(f'$ {" ".join(args)}\n')
        out.flush()
        done = subprocess.run(args, env=env, stdout=out, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        lines = log.read_text().splitlines()
        print('\n'.join(lines[-40:]), file=sys.stderr)
        sys.exit(f'building interfaces failed ({args[0]} exited {done.returncode}); log: {log}')


def build_package(source: Path, prefix: Path, env: dict[str, str]) -> None:
    """Configure, build and install one interface package into prefix."""
    build_dir = BUILD / prefix.name / source.name
    if cached_source(build_dir) not in (None, str(source)):
        shutil.rmtree(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    log = build_dir / 'build.log'
    log.write_text('')
    cmake = str(prefix / 'bin' / 'cmake')
    run_logged([cmake, '-S', str(source), '-B', str(build_dir),
                f'-DCMAKE_INSTALL_PREFIX={prefix}',
                f'-DPython3_EXECUTABLE={prefix / "bin" / "python"}',
                '-DBUILD_TESTING=OFF'], env, log)
    run_logged([cmake, '--build', str(build_dir), '--parallel', str(os.cpu_count() or 1)],
               env, log)
    run_logged([cmake, '--install', str(build_dir)], env, log)


def main() -> None:
    prefix = Path(sys.prefix)
    headers = Path(sysconfig.get_paths()['include']) / 'Python.h'
    if not headers.exists():
        sys.exit(f'building interfaces needs the Python headers: {headers} is missing '
                 '(install the python3.11-dev package of the system)')
    env = build_environment(prefix)
    for source in interface_packages():
        print(f'building {source.name} into {prefix}', flush=True)
        build_package(source, prefix, env)


if __name__ == '__main__':
    main()
