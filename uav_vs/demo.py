"""`make demo`: the whole graph in closed loop around the simulated vehicle (section 5).

sim_world (the MAVLink vehicle and its cameras), three camshift_node and the
trinocular_pose_node, the homography_pose_node, the fuzzy_controller_node and the
mavlink_relay_node run as separate processes; the vehicle takes off, holds, flies
through setpoints on the ground station's pose and lands on a pad on the onboard pose
(uav_vs.scenario.DEMO). The summary (each pose source against truth, setpoint and
landing errors, latencies) is printed and written to the output folder with the flight
log (flight.npz), PNG plots and every node's log.

`make demo BAG=<bag>` (`--bag`) replays a ground-camera bag through the ground nodes
instead and scores their poses against the bag's truth.
"""
import argparse
import os
import sys
from pathlib import Path

from uav_vs.flight_plots import plot_flight
from uav_vs.flight_report import FlightReport
from uav_vs.ground_replay import replay_ground_bag
from uav_vs.scenario import SCENARIOS, fly
from uav_vs.vision.ground_config import default_config_path

CAMERAS = ['cam1', 'cam2', 'cam3']


def replay(bag: Path, out: Path, rate: float) -> int:
    """The ground nodes on a recorded bag, scored against its truth."""
    print(f'replaying {bag} through {len(CAMERAS)} camshift_node + trinocular_pose_node '
          f'(logs in {out}/logs/)', flush=True)
    report = replay_ground_bag(bag, default_config_path(), out / 'logs', CAMERAS, rate)
    print(report.summary())
    return 0 if report.poses else 1


def closed_loop(scenario_name: str, out: Path) -> int:
    """Fly a scenario, print and save the summary and the plots."""
    scenario = SCENARIOS[scenario_name]
    print(f'closed loop: scenario {scenario.name}, sim_world + 3 camshift_node + '
          'trinocular_pose_node + homography_pose_node + fuzzy_controller_node + '
          f'mavlink_relay_node (logs in {out}/logs/)', flush=True)
    log = fly(scenario, out)
    log.save(out / 'flight.npz')
    report = FlightReport.from_log(log)
    summary = report.summary()
    (out / 'summary.txt').write_text(summary + '\n')
    print(summary)
    if len(log.truth):
        plots = plot_flight(log, out)
        print('plots: ' + ', '.join(str(p) for p in plots))
    return 1 if report.failure else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', type=Path, help='replay this ground-camera bag instead')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='bag replay speed (1 = recorded)')
    parser.add_argument('--scenario', default='demo', choices=sorted(SCENARIOS),
                        help='closed-loop scenario (default %(default)s)')
    parser.add_argument('--out', type=Path, default=Path('demo-output'), help='output folder')
    args = parser.parse_args(argv)
    # As `make` sets them: shared-memory transport for images, discovery on this host.
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE',
                          str(default_config_path('fastdds_shm.xml')))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    args.out.mkdir(parents=True, exist_ok=True)
    if args.bag is not None:
        return replay(args.bag, args.out, args.rate)
    return closed_loop(args.scenario, args.out)


if __name__ == '__main__':
    sys.exit(main())
