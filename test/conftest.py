"""Shared fixtures: third-party data and an isolated ROS domain per test process."""
import fcntl
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from uav_vs import dds_shm
from uav_vs.datasets import HOW_TO_GET, shared_data_dir

REPO = Path(__file__).resolve().parents[1]


def _claim_ros_domain() -> int:
    """Hold a lock on a free ROS_DOMAIN_ID (1..200) for this process's lifetime."""
    lock_dir = Path('/tmp/uav_vs_ros_domains')
    lock_dir.mkdir(exist_ok=True)
    start = os.getpid() % 200
    for k in range(200):
        domain = 1 + (start + k) % 200
        fd = os.open(lock_dir / f'{domain}.lock', os.O_CREAT | os.O_RDWR)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return domain  # the fd stays open: the lock lasts as long as the process
    raise RuntimeError('no free ROS_DOMAIN_ID in 1..200')


# Before anything imports rclpy: every test process (xdist worker) gets its own domain.
os.environ['ROS_DOMAIN_ID'] = str(_claim_ros_domain())
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(REPO / 'config' / 'fastdds_shm.xml'))


# OpenCV spreads a routine over every core; beside the other worker and the nodes the tests
# start, that only oversubscribes CI's two cores. One thread per test worker.
if os.environ.get('PYTEST_XDIST_WORKER'):
    cv2.setNumThreads(1)


def pytest_sessionstart(session: pytest.Session) -> None:
    """Free the shared memory of node processes killed by earlier runs (dds_shm)."""
    dds_shm.remove_orphaned()


def pytest_sessionfinish(session: pytest.Session) -> None:
    """... and of this run's: tests kill nodes, ros2 launch and the fuzz harness too."""
    dds_shm.remove_orphaned()


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Where and when each test ran, as properties of its JUnit record (`make test` writes
    build/test-results.xml): the suite's timeline, worker by worker."""
    item.user_properties += [('worker', os.environ.get('PYTEST_XDIST_WORKER', 'main')),
                             ('started', f'{time.time():.1f}')]


# A test that starts node processes or the ros2 tools depends on DDS discovery, process
# start-up and scheduling, none of which it controls; on a loaded machine (CI's two
# cores under three test workers) such a test gets one more try. The summary counts
# reruns ("1 rerun"), so a flaky test stays visible; a test failing twice fails.
GRAPH_FIXTURES = frozenset({'ros_node', 'processes', 'ros2_cli', 'ros2_env', 'launch'})
GRAPH_RERUNS = 1


# The modules that fly a whole graph in real time, or storm nodes on both cores, run one
# after the other on the first worker, the SITL flights last (test/scheduling.py). Two such
# modules at once on CI's two cores (xdist's own order, most tests first) raised the
# image-to-command latency past 280 ms and failed a dozen flights; the SITL flights beside
# OpenCV's calibration (then on every core) could not hold.
HEAVY = ('test_fuzz_nodes', 'test_closed_loop',
         'test_fault_injection', 'test_two_hosts', 'test_calibrated_flight',
         'test_world_switches', 'test_fleet', 'test_sitl_closed_loop')
# The modules that spend their time waiting on real-time MAVLink exchanges with the
# simulated vehicle, or on a node's shutdown, run on a third worker beside the other two:
# five minutes of the suite's time, 35 s of CPU (measured with `time`, alone).
WAITING = ('test_mavlink_session', 'test_mavlink_vehicle', 'test_mavlink_guards',
           'test_mavlink_signing', 'test_node_main', 'test_radio_link')


def pytest_xdist_make_scheduler(config, log):
    if config.getvalue('dist') == 'loadscope':
        from scheduling import HeavyApartScheduling
        HeavyApartScheduling.heavy = frozenset(HEAVY)
        HeavyApartScheduling.waiting = frozenset(WAITING)
        return HeavyApartScheduling(config, log)
    return None


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if GRAPH_FIXTURES & set(getattr(item, 'fixturenames', ())):
            item.add_marker(pytest.mark.flaky(reruns=GRAPH_RERUNS, reruns_delay=1))
    rank = {name: k for k, name in enumerate(HEAVY)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """The third-party data folder; CI must have it, elsewhere the test skips."""
    path = shared_data_dir()
    if path is None:
        if os.environ.get('CI'):
            pytest.fail(HOW_TO_GET)
        pytest.skip(HOW_TO_GET)
    return path


ROS2_WHEELS = REPO.parent / 'shared' / 'wheels' / 'ros2-jazzy-cli'
# `ros2 ...` run from the wheels installed by the ros2_env fixture.
ROS2 = [sys.executable, '-c', 'import sys; from ros2cli.cli import main; sys.exit(main())']


@pytest.fixture(scope='session')
def ros2_env(tmp_path_factory) -> dict[str, str]:
    """An environment in which ROS2 (the real `ros2` command line and launch) runs: the
    shared wheels installed into a temporary folder on PYTHONPATH; their PyPI
    dependencies are in requirements-tools.txt. CI must have them, elsewhere the test skips."""
    wheels = sorted(ROS2_WHEELS.glob('*.whl'))
    if not wheels:
        reason = (f'ROS 2 command line wheels not found in {ROS2_WHEELS} (a full ROS 2 '
                  f'Jazzy install has them as ros2cli, ros2launch, ...)')
        if os.environ.get('CI'):
            pytest.fail(reason)
        pytest.skip(reason)
    site = tmp_path_factory.mktemp('ros2_cli')
    subprocess.run([sys.executable, '-m', 'pip', 'install', '-q', '--no-deps',
                    '--target', str(site), *map(str, wheels)], check=True)
    return dict(os.environ, PYTHONPATH=str(site), AMENT_PREFIX_PATH=sys.prefix,
                ROS_LOG_DIR=str(site / 'log'))


@pytest.fixture(scope='session')
def ros2_cli(ros2_env):
    """`ros2 ARGS` from the shared command-line wheels, retried while the CLI's fresh node
    has not found the graph yet."""
    def ros2(*args: str) -> subprocess.CompletedProcess:
        for _ in range(5):      # a fresh CLI node may not have discovered the graph yet
            run = subprocess.run([*ROS2, *args], env=ros2_env, capture_output=True, text=True,
                                 stdin=subprocess.DEVNULL, timeout=60)
            if 'Node not found' not in run.stdout + run.stderr:
                return run
        return run
    return ros2


@pytest.fixture
def ros_node():
    """A test-side rclpy node spinning in a background thread, in its own context."""
    import threading

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('test_probe', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    yield node
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)
    thread.join(timeout=5)


@pytest.fixture
def processes(tmp_path):
    """Start node processes (uav_vs.graph.start); all are stopped at teardown.

    Usage: `proc = processes('camshift_node', ['-r', '__ns:=/cam1'], label='cam1')`.
    Logs go to tmp_path/logs/<label>.log; `processes.log(label)` reads one.
    """
    from uav_vs import graph

    started = []
    log_dir = tmp_path / 'logs'

    def start(name, ros_args, label=None, env=None):
        proc = graph.start(name, ros_args, log_dir, label, env)
        started.append(proc)
        return proc

    start.log = lambda label: (log_dir / f'{label}.log').read_text(errors='replace')
    start.log_dir = log_dir
    yield start
    graph.stop(started)


def refused_at_start(name: str, ros_args: list[str], cwd: Path) -> str:
    """The one FATAL line with which node `name` refuses `ros_args` at start-up, exiting
    with status 2; the test fails otherwise."""
    from uav_vs.graph import executable

    run = subprocess.run([executable(name), '--ros-args', *ros_args], capture_output=True,
                         text=True, timeout=60, cwd=cwd, stdin=subprocess.DEVNULL)
    fatal = [line for line in (run.stdout + run.stderr).splitlines() if 'FATAL' in line]
    assert run.returncode == 2 and len(fatal) == 1, run.stdout + run.stderr
    return fatal[0]


def wait_for(predicate, timeout: float, period: float = 0.02) -> bool:
    """Poll predicate until true or timeout; returns its last value."""
    import time

    deadline = time.monotonic() + timeout
    while not (ok := predicate()) and time.monotonic() < deadline:
        time.sleep(period)
    return ok
