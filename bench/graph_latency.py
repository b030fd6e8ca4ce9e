"""graph/latency: image stamp -> cmd_vel in the full closed-loop graph.

The `setpoints` scenario (uav_vs.scenario) flown by the whole graph as separate
processes: sim_world (the MAVLink vehicle and its four cameras), three camshift_node and
the trinocular_pose_node, the homography_pose_node, the fuzzy_controller_node and the
mavlink_relay_node. A command computed from a vision pose carries the stamp of that
pose's image, the instant the simulator sampled the truth it rendered; its latency is
its arrival at the mission's recorder minus that stamp: rendering, transport, detection,
triangulation, control, transport. The reference is the first part of that chain,
image stamp -> ground/pose, in the same flight. Target: p95 <= 50 ms.
"""
import tempfile
from pathlib import Path

from bench.common import report
from uav_vs.flight_report import FlightReport, command_latencies
from uav_vs.scenario import SETPOINTS, fly


def main() -> None:
    with tempfile.TemporaryDirectory(prefix='uav_vs_graph_') as tmp:
        log = fly(SETPOINTS, Path(tmp), record=False)
    latency = command_latencies(log)
    pose = (log.ground.received - log.ground.stamps) * 1e-6
    scores = FlightReport.from_log(log)
    report('graph', 'graph/latency', latency, 'image stamp -> ground/pose', pose,
           commands=len(latency), failure=log.failure or None,
           ground_rmse_cm=round(scores.sources['ground'].position_rmse_m * 100, 2),
           target_p95_ms=50)
