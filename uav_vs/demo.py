"""`make demo`: the whole graph in closed loop around the simulated vehicle (section 5).

sim_world (the MAVLink vehicle and its cameras), three camshift_node and the
trinocular_pose_node, the homography_pose_node, the fuzzy_controller_node and the
mavlink_relay_node run as separate processes; the vehicle takes off, holds, flies
through setpoints on the ground station's pose and lands on a pad on the onboard pose
(uav_vs.scenario.DEMO). The summary (each pose source against truth, setpoint and
landing errors, latencies) is printed and written to the output folder with the flight
log (flight.npz), PNG plots and every node's log.

`make demo BAG=<bag>` (`--bag`) replays a bag instead (the flight bag a closed-loop run
records into the output folder, or bags/ground_trinocular, bags/onboard) through the
open-loop part of the graph (uav_vs.flight_replay) and reports the same way.
"""
import argparse
import os
import sys
from pathlib import Path

from uav_vs.bag.reader import BagError
from uav_vs.flight_plots import plot_flight
from uav_vs.flight_recorder import MissionError
from uav_vs.flight_replay import replay_flight
from uav_vs.flight_report import FlightLog, FlightReport
from uav_vs.scenario import SCENARIOS, fly
from uav_vs.vision.ground_config import default_config_path


def replay(bag: Path, out: Path, rate: float) -> int:
    """A recorded bag through the open-loop graph, scored against its truth."""
    print(f'replaying {bag} through the open-loop graph (logs in {out}/logs/)', flush=True)
    try:
        log = replay_flight(bag, out / 'logs', rate=rate)
    except (MissionError, BagError) as err:
        print(f'replay failed: {err}', file=sys.stderr)
        return 1
    return report(log, out)


def closed_loop(scenario_name: str, out: Path, autopilot: str) -> int:
    """Fly a scenario (recording its bag into out/bag); print and save the summary and plots."""
    scenario = SCENARIOS[scenario_name]
    print(f'closed loop: scenario {scenario.name}, sim_world ({autopilot}) + 3 camshift_node + '
          'trinocular_pose_node + homography_pose_node + fuzzy_controller_node + '
          f'mavlink_relay_node, recorded to {out}/bag (logs in {out}/logs/)', flush=True)
    return report(fly(scenario, out, autopilot=autopilot), out)


def report(log: FlightLog, out: Path) -> int:
    """Save the log, print and save the summary, draw the plots; 1 if the run failed."""
    log.save(out / 'flight.npz')
    result = FlightReport.from_log(log)
    summary = result.summary()
    (out / 'summary.txt').write_text(summary + '\n')
    print(summary)
    if len(log.truth):
        plots = plot_flight(log, out)
        print('plots: ' + ', '.join(str(p) for p in plots))
    return 1 if result.failure else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', type=Path, help='replay this bag through the open-loop graph')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='bag replay speed (1 = recorded)')
    parser.add_argument('--scenario', default='demo', choices=sorted(SCENARIOS),
                        help='closed-loop scenario (default %(default)s)')
    parser.add_argument('--autopilot', default='ardupilot', choices=('ardupilot', 'px4'),
                        help="whose MAVLink behaviour the simulated vehicle follows "
                             "(default %(default)s)")
    parser.add_argument('--out', type=Path, help='output folder (default demo-output, '
                        'demo-output/replay with --bag)')
    args = parser.parse_args(argv)
    # As `make` sets them: shared-memory transport for images, discovery on this host.
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE',
                          str(default_config_path('fastdds_shm.xml')))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    out = args.out or Path('demo-output', *(['replay'] if args.bag else []))
    out.mkdir(parents=True, exist_ok=True)
    if args.bag is not None:
        return replay(args.bag, out, args.rate)
    return closed_loop(args.scenario, out, args.autopilot)


if __name__ == '__main__':
    sys.exit(main())
