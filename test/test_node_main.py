"""ThrottledWarnings: one warning per kind of defect per period, kinds independent. run():
a node asked to stop exits 0 on either executor, whatever the interpreter's teardown would
do; one whose own teardown hangs exits 1 after the grace, showing where it hung."""
import os
import signal
import subprocess
import sys
import time

import pytest

from uav_vs.ros import node_main
from uav_vs.ros.node_main import ThrottledWarnings


class FakeLogger:
    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warn(self, text: str) -> None:
        self.warnings.append(text)


class FakeNode:
    def __init__(self) -> None:
        self.logger = FakeLogger()

    def get_logger(self) -> FakeLogger:
        return self.logger


def test_one_warning_per_kind_per_period_and_kinds_do_not_hide_each_other(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(node_main.time, 'monotonic', lambda: clock[0])
    node = FakeNode()
    warnings = ThrottledWarnings(node, period_s=5.0)

    def at(t: float, kind: str, text: str) -> None:
        clock[0] = 100.0 + t
        warnings.warn(kind, text)

    at(0.0, 'encoding', 'enc 1')
    at(0.1, 'encoding', 'enc 2')        # same kind inside the period: dropped
    at(0.2, 'size', 'size 1')           # another kind: not hidden by the first
    at(4.9, 'encoding', 'enc 3')        # still inside encoding's period
    at(5.0, 'encoding', 'enc 4')        # period over: logged again
    at(5.1, 'size', 'size 2')           # size's period (from 0.2) ends at 5.2
    at(5.2, 'size', 'size 3')
    at(9.9, 'encoding', 'enc 5')        # the period restarts at the last logged one (5.0)
    at(10.0, 'encoding', 'enc 6')
    assert node.logger.warnings == ['enc 1', 'size 1', 'enc 4', 'size 3', 'enc 6']


HANGING_NODE = '''
import time
from rclpy.node import Node
from uav_vs.ros.node_main import run

class Hangs(Node):
    def __init__(self):
        super().__init__('hangs')
        self.get_logger().info('up')

    def destroy_node(self):
        HANG()                   # a teardown that never finishes

run(Hangs, 'hangs', [])
'''
# Asleep with the GIL released (as Python code waits), or holding it (as a call into
# rclpy's C++ was seen to, destroying the DDS participant): libc's sleep called the
# ctypes.PyDLL way keeps the GIL.
HANGS = {'releasing the GIL': 'import time; HANG = lambda: time.sleep(600)',
         'holding the GIL': 'import ctypes; HANG = lambda: ctypes.PyDLL(None).sleep(600)'}


# The interpreter's teardown after run() never ends; and SIGINT, arriving while a callback
# is inside rclpy's C++, comes out of spin as a RuntimeError (as pybind11 reports it).
SLOW_EXIT_NODE = '''
import atexit
import time
from rclpy.node import Node
from uav_vs.ros.node_main import run

class InsideRclpy(Node):
    def __init__(self):
        super().__init__('inside_rclpy')
        self.create_timer(0.01, self.tick)
        self.get_logger().info('up')

    def tick(self):
        try:
            time.sleep(0.05)
        except KeyboardInterrupt:
            raise RuntimeError('Unable to convert call argument to Python object')

atexit.register(time.sleep, 600)
run(InsideRclpy, 'inside_rclpy', [])
'''


def stop(script: str, timeout: float = node_main.SHUTDOWN_GRACE_S + 20,
         env: dict[str, str] | None = None) -> tuple[int, str]:
    """Start `script`, wait for its node to be up, SIGINT it: its exit status and output."""
    proc = subprocess.Popen([sys.executable, '-c', script], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)
    try:
        assert 'up' in proc.stdout.readline()
        time.sleep(1.0)                          # spinning by now
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=timeout)
    finally:
        proc.kill()
    return proc.returncode, out


@pytest.mark.parametrize('hang', sorted(HANGS))
def test_a_node_whose_shutdown_hangs_still_exits_and_says_where(hang):
    status, out = stop(f'{HANGS[hang]}\n{HANGING_NODE}')
    assert status == 1, out
    assert f'Timeout (0:00:{node_main.SHUTDOWN_GRACE_S:02.0f})!' in out and 'in destroy_node' in out, out


def test_a_node_that_stopped_exits_0_at_once_without_the_interpreters_teardown():
    status, out = stop(SLOW_EXIT_NODE)
    assert status == 0, out
    assert 'Traceback' not in out and 'Timeout' not in out, out


QUIET_NODE = '''
from rclpy.node import Node
from uav_vs.ros.node_main import run

class Quiet(Node):
    def __init__(self):
        super().__init__('quiet')
        self.create_timer(0.1, lambda: None)
        self.get_logger().info('up')

run(Quiet, 'quiet', [])
'''


@pytest.mark.parametrize('executor', sorted(node_main.EXECUTORS))
def test_a_node_on_either_executor_stops_on_sigint(executor):
    """EventsExecutor.spin() would not return after the signal; the node's loop does."""
    status, out = stop(QUIET_NODE, node_main.SHUTDOWN_GRACE_S - 1,
                       {**os.environ, node_main.EXECUTOR_ENV: executor})
    assert status == 0 and 'Timeout' not in out, out


def test_an_unknown_executor_stops_the_node_with_one_fatal_line():
    run = subprocess.run([sys.executable, '-c', QUIET_NODE], capture_output=True, text=True,
                         timeout=60, env={**os.environ, node_main.EXECUTOR_ENV: 'multi'})
    assert run.returncode == 2
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and 'FATAL' in lines[0] and 'UAV_VS_EXECUTOR' in lines[0], lines
