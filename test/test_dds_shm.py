"""Shared memory: a node leaves none behind, whether it stops or is killed."""
import fcntl
import os
import time
from pathlib import Path

import pytest

from uav_vs import dds_shm, graph
from uav_vs.ros.node_main import EXECUTOR_ENV, EXECUTORS

from conftest import REPO, wait_for

CONTROLLER = ['--params-file', str(REPO / 'config' / 'fuzzy_controller.yaml')]


def _segment(shm_dir: Path, name: str, age_s: float) -> Path:
    for path in (shm_dir / name, shm_dir / f'{name}_el'):
        path.write_bytes(b'')
        os.utime(path, (time.time() - age_s,) * 2)
    return shm_dir / name


def test_only_segments_no_process_holds_are_removed(tmp_path):
    gone = _segment(tmp_path, 'fastrtps_0123456789abcdef', 60)
    held = _segment(tmp_path, 'fastrtps_fedcba9876543210', 60)
    young = _segment(tmp_path, 'fastrtps_00000000000000aa', 0)
    other = tmp_path / 'fastrtps_port7000_el'
    other.write_bytes(b'')
    with open(f'{held}_el', 'ab') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert dds_shm.remove_orphaned(tmp_path) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [held.name, f'{held.name}_el', young.name, f'{young.name}_el', other.name])
    assert not gone.exists()


def test_a_process_removes_the_segments_it_holds_and_no_other(tmp_path):
    """remove_own (a node's last step before it exits) takes this process's segments, the
    ones whose lock it holds, and leaves another process's and an unheld one."""
    mine = _segment(tmp_path, 'fastrtps_0123456789abcdef', 0)
    unheld = _segment(tmp_path, 'fastrtps_fedcba9876543210', 0)
    with open(f'{mine}_el', 'ab') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert dds_shm.held_by(os.getpid(), tmp_path) == [mine]
        assert dds_shm.held_by(os.getpid() + 1, tmp_path) == []
        assert dds_shm.remove_own(tmp_path) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [unheld.name, f'{unheld.name}_el']


@pytest.fixture
def controller(tmp_path):
    started = []

    def start(executor: str):
        proc = graph.start('fuzzy_controller_node', CONTROLLER, tmp_path,
                           env={EXECUTOR_ENV: executor})
        started.append(proc)
        assert wait_for(lambda: 'pose mode' in proc.log_path.read_text(), 30), \
            proc.log_path.read_text()
        return proc, dds_shm.held_by(proc.pid)
    yield start
    graph.stop(started)


@pytest.mark.parametrize('executor', sorted(EXECUTORS))
def test_a_node_that_stops_removes_its_shared_memory(controller, executor):
    proc, segments = controller(executor)
    assert graph.stop([proc]) == [0], proc.log_path.read_text()
    assert not [s for s in segments if s.exists()]


def test_stop_removes_the_shared_memory_of_a_killed_node(controller):
    proc, segments = controller('events')
    time.sleep(dds_shm.MIN_AGE_S)
    proc.kill()
    proc.wait()
    assert all(s.exists() for s in segments)
    graph.stop([proc])
    assert not [s for s in segments if s.exists()]
