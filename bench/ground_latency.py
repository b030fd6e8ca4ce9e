"""ground/latency: image stamp -> ground/pose, three cameras at 30 Hz, 640x480.

Three camera-driver processes, one per camera, publish frames rendered by the
simulator as raw bgr8 images (sensor-data QoS), each stamped with its publish time, to
the ground station; a probe process takes the latency of each pose (arrival time minus
its stamp) on the default executor, as the fuzzy_controller_node takes `ground/pose`,
and the CPU time the station's processes took meanwhile. Each pose is matched by its
stamp to the frame it came from, so `poses` counts the frames of the measured window
(WARMUP_S to SECONDS) that got one, out of `expected_poses`. The station runs in each
layout (uav_vs.flight.ground_replay.LAYOUTS: one ground_station process, or a process
per node) with each executor
(uav_vs.ros.node_main.EXECUTORS), and the one process with its landmarks through topics
instead of handed over (ground_station --landmark-topics), one after the other in the
same run; the reference of
every case is the separate processes on rclpy's SingleThreadedExecutor. Then the first
hop (each camera's landmarks) in the default configuration, measured in a run of its
own: three more subscriptions in the probe add three wake-ups per frame set to the
very latency being measured; and the default configuration with four cameras at 60 Hz.
All runs use the shared-memory Fast DDS profile (config/fastdds_shm.xml), read once per
process, so each run's processes all start with its environment.

`python -m bench.ground_latency` runs it all; `python -m bench.ground_latency LAYOUT
EXECUTOR [--landmark-topics]` one case (and its reference). `... probe OUT.npz
pose|landmarks LAYOUT CONFIG RATE [STATION_ARGS]` is one measurement, `... driver CAMERA
START CONFIG RATE` one camera driver.
"""
import copy
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rclpy
import yaml
from geometry_msgs.msg import PolygonStamped, PoseStamped
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from bench.common import report
from uav_vs import graph
from uav_vs.flight.ground_replay import DEFAULT_LAYOUT, LAYOUTS, ground_graph
from uav_vs.ros.convert import bgr_to_image, stamp_to_ns
from uav_vs.ros.node_main import DEFAULT_EXECUTOR, EXECUTOR_ENV, EXECUTORS
from uav_vs.sim.ground_scene import GroundScene, figure_eight
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file

RATE_HZ = 30.0
SECONDS = 8.0
WARMUP_S = 1.5
N_FRAMES = 60
REFERENCE = ('processes', 'single')        # the station as it was: a process per node
TARGET_P95_MS, TARGET_MEDIAN_MS = 10.0, 5.0


def _spin_until(executor, predicate, deadline: float) -> None:
    while not predicate() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)


def _cameras(config: Path) -> list[str]:
    return list(read_params_file(config)['cameras.names'])


def driver(camera: str, start: float, config: Path, rate: float) -> None:
    """Publish this camera's rendered frames at `rate` from CLOCK_MONOTONIC `start`.

    The drivers end together; each then waits its turn (graph.SETTLE_S apart, in camera
    order) to destroy its node: Fast DDS can deadlock a node's teardown while a peer is
    leaving (uav_vs.graph.stop)."""
    cfg = load_ground_config(read_params_file(config))
    index = [c.name for c in cfg.cameras].index(camera)
    scene = GroundScene(cfg)
    msgs = [bgr_to_image(scene.render(figure_eight(k / rate))[0][index],
                         Header(frame_id=f'{camera}_optical')) for k in range(N_FRAMES)]
    rclpy.init()
    node = rclpy.create_node(f'{camera}_driver')
    pub = node.create_publisher(Image, f'{camera}/image_raw', qos_profile_sensor_data)
    clock = node.get_clock()
    k = 0
    while (now := time.monotonic()) < start + SECONDS:
        due = start + k / rate
        if now < due:
            time.sleep(due - now)
            continue
        msg = msgs[k % N_FRAMES]
        msg.header.stamp = clock.now().to_msg()
        pub.publish(msg)
        k += 1
    time.sleep(index * graph.SETTLE_S)
    node.destroy_node()
    rclpy.shutdown()


def _cpu_s(pid: int) -> float:
    """User + system CPU time of a process so far, s."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _window(rate: float) -> range:
    """The measured frames: those due from WARMUP_S to SECONDS after the drivers' start."""
    return range(math.ceil(WARMUP_S * rate), math.ceil(SECONDS * rate))


def frames_in_window(stamps_ns: np.ndarray, start_ns: int, rate: float) -> np.ndarray:
    """The driver frame index of each stamp (frame k is due at start + k / rate and
    stamped when published, at most a tenth of a period early and nine tenths late),
    -1 outside the measured frames (_window)."""
    k = np.floor((stamps_ns - start_ns) * 1e-9 * rate + 0.1).astype(int)
    window = _window(rate)
    return np.where((k >= window.start) & (k < window.stop), k, -1)


def expected_frames(rate: float) -> int:
    """Frames the drivers publish in the measured window."""
    return len(_window(rate))


def measure(log_dir: Path, what: str, layout: str, config: Path, rate: float,
            station_args: list[str] = ()) -> tuple[np.ndarray, np.ndarray, float]:
    """Latencies (ms) of one run, of every `ground/pose` (what='pose') or of every
    camera's `landmarks` (what='landmarks', the first hop) of the measured frames, the
    frame each came from, and the CPU the station's processes took while they were
    measured, in % of one core. The probe takes them on the default executor, as the
    fuzzy_controller_node takes `ground/pose`."""
    cameras = _cameras(config)
    procs = list(ground_graph(config, cameras, log_dir, layout=layout,
                              station_args=station_args).values())
    rclpy.init()
    node = rclpy.create_node('latency_probe')
    executor = EXECUTORS[DEFAULT_EXECUTOR]()
    executor.add_node(node)
    clock = node.get_clock()
    received: list[tuple[int, int]] = []

    def on_message(msg) -> None:
        received.append((clock.now().nanoseconds, stamp_to_ns(msg.header.stamp)))

    if what == 'pose':
        node.create_subscription(PoseStamped, 'ground/pose', on_message, 100)
    else:
        for c in cameras:
            node.create_subscription(PolygonStamped, f'{c}/landmarks', on_message, 100)
    # The station is up (subscribing every camera, publishing its output) before the
    # drivers are started, however long a loaded machine takes; they then start, render
    # and are discovered before `start`.
    def station_up() -> bool:
        return (all(node.count_subscribers(f'{c}/image_raw') for c in cameras)
                and node.count_publishers('ground/pose') > 0)
    _spin_until(executor, station_up, time.monotonic() + 60.0)
    start = time.monotonic() + 6.0
    start_ns = clock.now().nanoseconds + int((start - time.monotonic()) * 1e9)
    drivers = [subprocess.Popen([sys.executable, '-m', 'bench.ground_latency', 'driver', c,
                                 repr(start), str(config), repr(rate)]) for c in cameras]
    try:
        _spin_until(executor, lambda: time.monotonic() >= start + WARMUP_S, start + WARMUP_S + 1)
        cpu0, t0 = sum(_cpu_s(p.pid) for p in procs), time.monotonic()
        _spin_until(executor, lambda: time.monotonic() >= start + SECONDS, start + SECONDS)
        cpu = (sum(_cpu_s(p.pid) for p in procs) - cpu0) / (time.monotonic() - t0) * 100
        _spin_until(executor, lambda: False, start + SECONDS + 0.5)
    finally:
        _end_drivers(drivers, cameras)
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()
        graph.stop(procs)
    arrival, stamp = np.array(received, np.int64).reshape(-1, 2).T
    frames = frames_in_window(stamp, start_ns, rate)
    keep = frames >= 0
    return (arrival - stamp)[keep] / 1e6, frames[keep], cpu


def _end_drivers(drivers: list[subprocess.Popen], cameras: list[str],
                 timeout: float = 30.0) -> None:
    """Wait for the drivers to exit; stop (and report) any still running after `timeout`:
    one hung in its teardown must neither hold the run nor outlive it."""
    deadline = time.monotonic() + timeout
    for d in drivers:
        try:
            d.wait(max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            pass
    hung = [c for c, d in zip(cameras, drivers) if d.poll() is None]
    if hung:
        print(f'ground/latency: driver(s) {", ".join(hung)} still running {timeout:.0f} s after '
              'their last frame; stopped', file=sys.stderr)
        graph.stop(drivers)


def _run(what: str, layout: str, executor: str, config: Path | None = None,
         rate: float = RATE_HZ, station_args: tuple[str, ...] = ()
         ) -> tuple[np.ndarray, int, float]:
    """One measurement in a process of its own, its station on `executor`: latencies
    (ms), how many of the measured frames got one, CPU %."""
    shm = str(Path(__file__).resolve().parents[1] / 'config' / 'fastdds_shm.xml')
    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=shm, **{EXECUTOR_ENV: executor})
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'latency.npz'
        subprocess.run([sys.executable, '-m', 'bench.ground_latency', 'probe', str(out), what,
                        layout, str(config or default_config_path()), repr(rate),
                        *station_args],
                       env=env, check=True)
        found = np.load(out)
        ages, frames, cpu = found['ages'], found['frames'], float(found['cpu'])
    if not len(ages):
        raise RuntimeError(f'ground/latency: no {what} received in {SECONDS} s with '
                           f'{layout}/{executor} (is the machine busy with other jobs?)')
    return ages, len(np.unique(frames)), cpu


def four_cameras(path: Path) -> Path:
    """The default params file with a fourth camera: cam1's, turned 180 deg about the
    vertical through the world origin (west of the area, looking at its centre)."""
    doc = yaml.safe_load(default_config_path().read_text())
    cams = doc['/**']['ros__parameters']['cameras']
    cam4 = dict(copy.deepcopy(cams['cam1']), frame_id='cam4_optical')   # no YAML aliases
    turn = np.diag([-1.0, -1.0, 1.0])      # x_w' = turn x_w, so R' = R turn^T
    cam4['R'] = (np.reshape(cams['cam1']['R'], (3, 3)) @ turn.T).ravel().tolist()
    cams['cam4'] = cam4
    cams['names'] = [*cams['names'], 'cam4']
    path.write_text(yaml.safe_dump(doc))
    return path


def case(layout: str, executor: str, station_args: tuple[str, ...],
         ref: tuple[np.ndarray, int, float]) -> None:
    """One layout on one executor, next to the reference run."""
    ages, poses, cpu = _run('pose', layout, executor, station_args=station_args)
    expected = expected_frames(RATE_HZ)
    name = '/'.join([layout, executor, *(a.strip('-') for a in station_args)])
    meets = (np.percentile(ages, 95) <= TARGET_P95_MS and np.median(ages) <= TARGET_MEDIAN_MS
             and poses == expected)
    report('ground', f'ground/latency/{name}', ages,
           reference='/'.join(REFERENCE), ref_ms=ref[0], poses=poses,
           expected_poses=expected, ref_poses=ref[1], cpu_percent=round(cpu),
           ref_cpu_percent=round(ref[2]), meets_target=bool(meets))


def latency(cases: list[tuple[str, str, tuple[str, ...]]]) -> None:
    ref = _run('pose', *REFERENCE)
    for layout, executor, station_args in cases:
        case(layout, executor, station_args, ref)


def main(argv: list[str] = ()) -> None:
    if argv:
        latency([(argv[0], argv[1], tuple(argv[2:]))])
        return
    latency([*((layout, executor, ()) for layout in LAYOUTS for executor in EXECUTORS),
             ('one_process', DEFAULT_EXECUTOR, ('--landmark-topics',))])
    hops, _, _ = _run('landmarks', DEFAULT_LAYOUT, DEFAULT_EXECUTOR)
    report('ground', 'ground/latency/landmarks', hops, layout=DEFAULT_LAYOUT,
           executor=DEFAULT_EXECUTOR)
    with tempfile.TemporaryDirectory() as tmp:
        config = four_cameras(Path(tmp) / 'four_cameras.yaml')
        ages, poses, cpu = _run('pose', DEFAULT_LAYOUT, DEFAULT_EXECUTOR, config, 60.0)
    report('ground', 'ground/latency/4cams_60hz', ages, poses=poses,
           expected_poses=expected_frames(60.0), cpu_percent=round(cpu),
           layout=DEFAULT_LAYOUT, executor=DEFAULT_EXECUTOR)


if __name__ == '__main__':
    # No argument (or LAYOUT EXECUTOR): the benchmark. `driver` and `probe` are its own
    # child processes.
    if len(sys.argv) < 2 or sys.argv[1] not in ('driver', 'probe'):
        main(sys.argv[1:])
    elif sys.argv[1] == 'driver':
        driver(sys.argv[2], float(sys.argv[3]), Path(sys.argv[4]), float(sys.argv[5]))
    else:
        with tempfile.TemporaryDirectory(prefix='uav_vs_latency_') as logs:
            ages, frames, cpu = measure(Path(logs), sys.argv[3], sys.argv[4],
                                        Path(sys.argv[5]), float(sys.argv[6]), sys.argv[7:])
            np.savez(sys.argv[2], ages=ages, frames=frames, cpu=cpu)
