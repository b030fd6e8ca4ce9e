"""ground/latency: image stamp -> ground/pose, three camera processes at 30 Hz, 640x480.

Three camera-driver processes, one per camera, publish frames rendered by the
simulator as raw bgr8 images (sensor-data QoS), each stamped with its publish time,
to three camshift_node processes feeding a trinocular_pose_node process. A probe
process takes the latency of each pose (arrival time minus its stamp), as a controller
would see it. The first hop (each camera's landmarks) is measured in a run of its own:
three more subscriptions in the probe add three wake-ups per frame set on two cores,
about 1 ms at p95, to the very latency being measured. The reference is the same graph
on Fast DDS's builtin transports (no shared-memory profile). Fast DDS reads its profile
once per process, so each run's processes all start with its environment.

`python -m bench.ground_latency probe OUT.npy pose|landmarks` runs one measurement;
`python -m bench.ground_latency driver CAMERA START` is one camera driver.
"""
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import PolygonStamped, PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from bench.common import report
from uav_vs import graph
from uav_vs.ground_replay import ground_graph
from uav_vs.ros.convert import bgr_to_image, stamp_to_ns
from uav_vs.sim.ground_scene import GroundScene, figure_eight
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file

RATE_HZ = 30.0
SECONDS = 8.0
WARMUP_S = 1.5
N_FRAMES = 60
CAMERAS = ['cam1', 'cam2', 'cam3']


def _spin_until(executor, predicate, deadline: float) -> None:
    while not predicate() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)


def driver(camera: str, start: float) -> None:
    """Publish this camera's rendered frames at RATE_HZ from CLOCK_MONOTONIC `start`."""
    config = default_config_path()
    cfg = load_ground_config(read_params_file(config))
    index = [c.name for c in cfg.cameras].index(camera)
    scene = GroundScene(cfg)
    msgs = [bgr_to_image(scene.render(figure_eight(k / RATE_HZ))[0][index],
                         Header(frame_id=f'{camera}_optical')) for k in range(N_FRAMES)]
    rclpy.init()
    node = rclpy.create_node(f'{camera}_driver')
    pub = node.create_publisher(Image, f'{camera}/image_raw', qos_profile_sensor_data)
    clock = node.get_clock()
    k = 0
    while (now := time.monotonic()) < start + SECONDS:
        due = start + k / RATE_HZ
        if now < due:
            time.sleep(due - now)
            continue
        msg = msgs[k % N_FRAMES]
        msg.header.stamp = clock.now().to_msg()
        pub.publish(msg)
        k += 1
    node.destroy_node()
    rclpy.shutdown()


def measure(log_dir: Path, what: str) -> np.ndarray:
    """Latencies (ms) of one run: of every `ground/pose` (what='pose') or of every
    camera's `landmarks` (what='landmarks', the first hop)."""
    procs = ground_graph(default_config_path(), CAMERAS, log_dir)
    rclpy.init()
    node = rclpy.create_node('latency_probe')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    clock = node.get_clock()
    ages: list[float] = []

    def on_message(msg) -> None:
        ages.append((clock.now().nanoseconds - stamp_to_ns(msg.header.stamp)) / 1e6)

    if what == 'pose':
        node.create_subscription(PoseStamped, 'ground/pose', on_message, 100)
    else:
        for c in CAMERAS:
            node.create_subscription(PolygonStamped, f'{c}/landmarks', on_message, 100)
    start = time.monotonic() + 10.0
    drivers = [subprocess.Popen([sys.executable, '-m', 'bench.ground_latency', 'driver', c,
                                 repr(start)]) for c in CAMERAS]
    try:
        _spin_until(executor, lambda: time.monotonic() >= start + WARMUP_S, start + WARMUP_S + 1)
        ages.clear()
        _spin_until(executor, lambda: False, start + SECONDS + 0.5)
    finally:
        for d in drivers:
            d.wait(timeout=30)
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()
        graph.stop(procs)
    return np.array(ages)


def _run(profile: str | None, what: str) -> np.ndarray:
    env = {k: v for k, v in os.environ.items() if k != 'FASTRTPS_DEFAULT_PROFILES_FILE'}
    if profile:
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = profile
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'latency.npy'
        subprocess.run([sys.executable, '-m', 'bench.ground_latency', 'probe', str(out), what],
                       env=env, check=True)
        return np.load(out)


def latency() -> None:
    shm = str(Path(__file__).resolve().parents[1] / 'config' / 'fastdds_shm.xml')
    ours, builtin, hops = _run(shm, 'pose'), _run(None, 'pose'), _run(shm, 'landmarks')
    expected = int((SECONDS - WARMUP_S) * RATE_HZ)
    report('ground', 'ground/latency', ours, reference='builtin transports', ref_ms=builtin,
           poses=len(ours), expected_poses=expected, ref_poses=len(builtin),
           landmarks_median_ms=round(float(np.median(hops)), 2),
           landmarks_p95_ms=round(float(np.percentile(hops, 95)), 2))


def main() -> None:
    latency()


if __name__ == '__main__':
    if sys.argv[1] == 'driver':
        driver(sys.argv[2], float(sys.argv[3]))
    else:
        with tempfile.TemporaryDirectory(prefix='uav_vs_latency_') as logs:
            np.save(sys.argv[2], measure(Path(logs), sys.argv[3]))
