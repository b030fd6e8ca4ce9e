"""Start and stop the graph's nodes as separate processes, the way `ros2 run` would.

There is no `launch` on PyPI; this is the small part of it the demo, the tests and
the benchmarks need: start an executable with `--ros-args ...`, log its output to a
file, and stop it with SIGINT, escalating to SIGTERM and SIGKILL.
"""
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from uav_vs import dds_shm

# Pause between stopping one process and the next (see stop).
SETTLE_S = 0.1


def executable(name: str) -> str:
    """Path of a console script: the venv's bin/ first, then PATH."""
    here = Path(sys.prefix) / 'bin' / name
    found = str(here) if here.exists() else shutil.which(name)
    if found is None:
        raise FileNotFoundError(f'executable {name!r} not found (is the package installed?)')
    return found


def start(name: str, ros_args: list[str], log_dir: Path, label: str | None = None,
          env: dict[str, str] | None = None, args: list[str] = (),
          wrap: list[str] = ()) -> subprocess.Popen:
    """Start `name args --ros-args ros_args`, stdout and stderr to log_dir/<label>.log
    (the process's `log_path`); after the argv prefix `wrap` if given (e.g. `ip netns exec
    NS`, which passes SIGINT on by exec'ing the node)."""
    log_dir.mkdir(parents=True, exist_ok=True)
    path = log_dir / f'{label or name}.log'
    log = open(path, 'wb')
    argv = [*wrap, executable(name), *args, *(['--ros-args', *ros_args] if ros_args else [])]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log,
                            stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})
    log.close()
    proc.log_path = path
    return proc


def stop(procs: list[subprocess.Popen], timeout: float = 5.0) -> list[int]:
    """Stop the processes one at a time, last started first, with SIGINT; then SIGTERM,
    then SIGKILL the ones still alive; return codes.

    One at a time, because Fast DDS can deadlock deleting a node's entities while it is
    still removing a peer that has just left (eProsima/Fast-DDS#6502): a graph stopped all
    at once then leaves a node hung in its teardown. Each process takes ~25 ms to stop,
    and SETTLE_S lets the ones still running forget it before the next is stopped. The
    shared memory of a process that did not stop cleanly is removed (dds_shm). Each
    process's CPU time so far is kept as its `cpu_s`.
    """
    running = [p for p in procs if p.poll() is None]
    for p in running:
        p.cpu_s = cpu_seconds(p.pid)
    for i, p in enumerate(reversed(running)):
        if i:
            time.sleep(SETTLE_S)
        p.send_signal(signal.SIGINT)
        _wait(p, timeout)
    for sig in (signal.SIGTERM, signal.SIGKILL):
        alive = [p for p in procs if p.poll() is None]
        for p in alive:
            p.send_signal(sig)
        for p in alive:
            _wait(p, timeout)
    dds_shm.remove_orphaned()
    return [p.returncode for p in procs]


def cpu_seconds(pid: int) -> float:
    """User and system CPU time of a living process, s (nan once it has gone)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _wait(proc: subprocess.Popen, timeout: float) -> None:
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        pass


def failed_logs(procs: dict[str, subprocess.Popen], lines: int = 25) -> dict[str, str]:
    """The last `lines` of the log of every stopped process whose status is not 0."""
    return {label: _tail(p.log_path, lines) for label, p in procs.items()
            if p.returncode not in (None, 0)}


def _tail(path: Path, lines: int) -> str:
    text = path.read_text(errors='replace') if path.exists() else ''
    return '\n'.join([f'{path}:', *text.splitlines()[-lines:]])
