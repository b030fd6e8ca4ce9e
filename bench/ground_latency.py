"""ground/latency: image stamp -> ground/pose, three camera processes at 30 Hz, 640x480.

Frames rendered by the simulator are published as raw bgr8 images, stamped with the
publish time, by a camera-driver-like node (sensor-data QoS) to three camshift_node
processes feeding a trinocular_pose_node process. The latency of a pose is its
arrival time minus its stamp. The reference is the same graph on Fast DDS's builtin
transports (no shared-memory profile). Fast DDS reads its profile once per process,
so each run measures in a process of its own.
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


def _frames(config: Path, n: int) -> list[list[np.ndarray]]:
    scene = GroundScene(load_ground_config(read_params_file(config)))
    return [scene.render(figure_eight(k / RATE_HZ))[0] for k in range(n)]


def measure(config: Path, frames: list[list[np.ndarray]]) -> np.ndarray:
    """Latencies (ms) of one run, in this process's Fast DDS set-up: row 0 the poses',
    row 1 the cameras' landmarks (the first hop), NaN-padded to equal length."""
    cams = [f'cam{k + 1}' for k in range(len(frames[0]))]
    log_dir = Path(tempfile.mkdtemp(prefix='uav_vs_latency_'))
    procs = ground_graph(config, cams, log_dir)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('latency_bench', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    latencies: list[float] = []
    hops: list[float] = []
    clock = node.get_clock()

    def age_ms(msg) -> float:
        return (clock.now().nanoseconds - stamp_to_ns(msg.header.stamp)) / 1e6

    node.create_subscription(PoseStamped, 'ground/pose', lambda m: latencies.append(age_ms(m)),
                             100)
    for c in cams:
        node.create_subscription(PolygonStamped, f'{c}/landmarks', lambda m: hops.append(age_ms(m)),
                                 100)
    pubs = [node.create_publisher(Image, f'{c}/image_raw', qos_profile_sensor_data) for c in cams]
    msgs = [[bgr_to_image(img, Header(frame_id=f'{c}_optical')) for img, c in zip(fs, cams)]
            for fs in frames]
    try:
        deadline = time.monotonic() + 30
        while (min(p.get_subscription_count() for p in pubs) == 0
               or node.count_publishers('ground/pose') == 0) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        start = time.monotonic()
        k = 0
        while (now := time.monotonic()) - start < SECONDS:
            if now >= start + k / RATE_HZ:
                stamp = clock.now().to_msg()
                for pub, msg in zip(pubs, msgs[k % len(msgs)]):
                    msg.header.stamp = stamp
                    pub.publish(msg)
                if now - start < WARMUP_S:
                    latencies.clear()
                    hops.clear()
                k += 1
            executor.spin_once(timeout_sec=max(0.0, start + k / RATE_HZ - time.monotonic()))
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        graph.stop(procs)
    out = np.full((2, max(len(latencies), len(hops))), np.nan)
    out[0, :len(latencies)], out[1, :len(hops)] = latencies, hops
    return out


def _run(profile: str | None) -> np.ndarray:
    env = {k: v for k, v in os.environ.items() if k != 'FASTRTPS_DEFAULT_PROFILES_FILE'}
    if profile:
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = profile
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'latency.npy'
        subprocess.run([sys.executable, '-m', 'bench.ground_latency', str(out)], env=env,
                       check=True)
        return np.load(out)


def latency() -> None:
    shm = str(Path(__file__).resolve().parents[1] / 'config' / 'fastdds_shm.xml')
    (ours, hops), (builtin, _) = _run(shm), _run(None)
    ours, hops, builtin = (a[np.isfinite(a)] for a in (ours, hops, builtin))
    expected = int((SECONDS - WARMUP_S) * RATE_HZ)
    report('ground', 'ground/latency', ours, reference='builtin transports', ref_ms=builtin,
           poses=len(ours), expected_poses=expected, ref_poses=len(builtin),
           landmarks_median_ms=round(float(np.median(hops)), 2),
           landmarks_p95_ms=round(float(np.percentile(hops, 95)), 2))


def main() -> None:
    latency()


if __name__ == '__main__':
    config = default_config_path()
    np.save(sys.argv[1], measure(config, _frames(config, 60)))
