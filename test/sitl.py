"""The real ArduCopter SITL as a test fixture: ../shared/sitl/run_arducopter.sh.

SITL binds its ports on 0.0.0.0, so it runs in a network namespace that has only
loopback, and whatever talks to it (a Session, a test's own link) runs in the same
namespace: `Sitl.run_python` starts a Python script there and returns the JSON it prints.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SITL_DIR = REPO.parent / 'shared' / 'sitl'
HOW_TO_GET = (f'ArduCopter SITL not found at {SITL_DIR}: build ArduPilot\'s copter for the '
              'sitl board (ardupilot.org, "Setting up SITL on Linux") and put arducopter, '
              'copter.parm and run_arducopter.sh in ../shared/sitl beside the checkout')


def sitl_dir() -> Path:
    """The SITL folder; CI must have it, elsewhere the test skips."""
    if not (SITL_DIR / 'run_arducopter.sh').is_file():
        if os.environ.get('CI'):
            pytest.fail(HOW_TO_GET)
        pytest.skip(HOW_TO_GET)
    return SITL_DIR


class Sitl:
    """One SITL instance in its own loopback-only namespace; `with` tears it down."""

    def __init__(self, namespace: str, workdir: Path, instance: int = 0, speedup: int = 1):
        self.script = str(sitl_dir() / 'run_arducopter.sh')
        self.namespace, self.workdir = namespace, workdir
        self.instance, self.speedup = instance, speedup
        self.pid: str | None = None

    @property
    def ports(self) -> tuple[int, int, int]:
        """tcp SERIAL0, SERIAL1, SERIAL2 of this instance."""
        base = 5760 + 10 * self.instance
        return base, base + 2, base + 3

    def __enter__(self) -> 'Sitl':
        up = subprocess.run([self.script, 'up', self.namespace, str(self.workdir),
                             str(self.instance), str(self.speedup)],
                            capture_output=True, text=True, check=True, timeout=30)
        self.pid = up.stdout.strip()
        return self

    def __exit__(self, *exc) -> None:
        if self.pid:
            subprocess.run([self.script, 'down', self.namespace, self.pid], timeout=30)

    def run_python(self, script: Path, *args: str, timeout: float = 120.0) -> dict:
        """Run `script` with this Python inside the namespace; the JSON of its last stdout line."""
        run = subprocess.run([self.script, 'exec', self.namespace, sys.executable, str(script),
                              *args], capture_output=True, text=True, timeout=timeout,
                             cwd=REPO)
        lines = run.stdout.strip().splitlines()
        assert run.returncode == 0 and lines, (
            f'{script.name} failed ({run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}\n'
            f'SITL log:\n{self.log()[-2000:]}')
        return json.loads(lines[-1])

    def log(self) -> str:
        path = self.workdir / f'sitl-{self.instance}.log'
        return path.read_text(errors='replace') if path.exists() else ''
