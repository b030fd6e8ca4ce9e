"""graph/latency: image stamp -> cmd_vel in the full closed-loop graph.

The `setpoints` scenario (uav_vs.flight.scenario) flown by the whole graph as separate
processes: sim_world (the MAVLink vehicle and its four cameras), three camshift_node and
the trinocular_pose_node, the homography_pose_node, the fuzzy_controller_node and the
mavlink_relay_node. A command computed from a vision pose carries the stamp of that
pose's image, the instant the simulator sampled the truth it rendered; its latency is
its arrival at the mission's recorder minus that stamp: rendering, transport, detection,
triangulation, control, transport. The reference is the first part of that chain,
image stamp -> ground/pose, in the same flight. Target: p95 <= 30 ms. The flight is
flown with the ground station in each layout (uav_vs.flight.ground_replay.LAYOUTS), the
default first.
"""
import tempfile
from pathlib import Path

from bench.common import report
from uav_vs.flight.ground_replay import DEFAULT_LAYOUT, LAYOUTS
from uav_vs.flight.report import FlightReport, command_latencies
from uav_vs.flight.scenario import SETPOINTS, Configs, fly

TARGET_P95_MS = 30


def flight(layout: str) -> None:
    """One flight with the ground station in `layout`."""
    with tempfile.TemporaryDirectory(prefix='uav_vs_graph_') as tmp:
        log = fly(SETPOINTS, Path(tmp), Configs(ground_layout=layout), record=False)
    latency = command_latencies(log)
    pose = (log.ground.received - log.ground.stamps) * 1e-6
    scores = FlightReport.from_log(log)
    report('graph', f'graph/latency/{layout}', latency, 'image stamp -> ground/pose', pose,
           commands=len(latency), failure=log.failure or None,
           ground_rmse_cm=round(scores.sources['ground'].position_rmse_m * 100, 2),
           target_p95_ms=TARGET_P95_MS)


def main() -> None:
    for layout in sorted(LAYOUTS, key=lambda name: name != DEFAULT_LAYOUT):
        flight(layout)
