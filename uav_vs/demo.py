"""`make demo`: the whole graph in closed loop around the simulated vehicle (section 5).

sim_world (the MAVLink vehicle and its cameras), three camshift_node and the
trinocular_pose_node, the homography_pose_node, the fuzzy_controller_node and the
mavlink_relay_node run as separate processes; the vehicle takes off, holds, flies
through setpoints on the ground station's pose and lands on a pad on the onboard pose
(uav_vs.flight.scenario.DEMO). The summary (each pose source against truth, setpoint and
landing errors, latencies) is printed and written to the output folder with the flight
log (flight.npz), PNG plots and every node's log.

The simulated world's cameras and vehicle have the `realistic` sensor profile
(config/sensors_realistic.yaml: noise, distortion, motion blur, exposure drift, JPEG
artefacts, dropped frames, latency, unsynchronised ground cameras, partly occluded
landmarks, wind gusts, a drifting estimate); `make demo SENSORS=ideal` (`--sensors
ideal`) switches every effect off but the calibrated lens.

`make demo AUTOPILOT=ardupilot-sitl` (`--autopilot ardupilot-sitl`) flies the same mission
with ArduCopter SITL as the vehicle (its physics, EKF and GUIDED controller) at real time:
run as root, it starts the SITL binary (uav_vs.sim.sitl_process) in a loopback-only
network namespace that the whole graph joins, its boot on the ground (until ready to arm)
run faster than real time; `SITL=tcp:HOST:PORT` (`--sitl`) attaches
to a SITL already running instead (the relay on that port, the truth on `--sitl-truth`,
by default the same host's next SERIAL port, PORT + 2).
`SCENARIO=gps_denied` (`--scenario gps_denied`, ArduPilot SITL only) flies without GPS:
SITL gets config/ardupilot_gps_denied.parm (an attached SITL must run with it), EKF3
navigates on the ground station's pose, which the relay forwards with the EKF origin;
the summary adds what the EKF reported over the flight. `SCENARIO=gps_denied_fused` feeds
it the pose filter's estimate (fused/odom, with its covariance) instead, SITL getting
config/ardupilot_fused_nav.parm after the first.
`SCENARIO=follow` (`--scenario follow`, any vehicle) follows a target driving on the
ground after the hold, with target_tracker_node and target_follower_node; the summary
adds how close the vehicle stayed to it.
`SCENARIO=blind` (`--scenario blind`, any vehicle) flies the hold and two setpoints on
the pose filter's estimate (fused/pose) and covers the ground cameras for the first 3 s
of the way to the first setpoint; the summary adds how far the estimate was from the
truth while they saw nothing.

`make demo HOSTS=2` (`--hosts 2`, root) runs the ground station and the vehicle on two
hosts, network namespaces joined by a radio link of 20 +- 10 ms and 2 % loss
(uav_vs.sim.radio_link), DDS across it by static peers; the summary adds what the link
carried and the commands as the vehicle received them. `CUT_LINK=3` (`--cut-link 3`)
cuts the link for 3 s once the vehicle holds: the relay stops the vehicle, the ground's
link_monitor_node reports it, both go on when it returns.

`make demo VEHICLES=2` (`--vehicles 2`) flies two simulated vehicles at once, /uav1 and
/uav2 (uav_vs.flight.fleet): each its own autopilot (system ids 1 and 2), onboard camera,
ground station tracking its own landmark colours in the shared ground cameras' images,
controller and relay, each through its own hold and setpoint; the summary adds, per
vehicle, what the ROS graph and its relay showed of crosstalk (none is expected). The
output folder has a folder per vehicle.

`make demo VIEW=1` (`--view`) also runs foxglove_node (config/foxglove.yaml) and
frames_node (the TF tree of the 3D view), and prints the address to open in Foxglove or
Lichtblick and the layout to import, config/foxglove/uav_vs.json (docs/live_view.md).

`make demo BAG=<bag>` (`--bag`) replays a bag instead (the flight bag a closed-loop run
records into the output folder, or bags/ground_trinocular, bags/onboard) through the
open-loop part of the graph (uav_vs.flight.replay) and reports the same way.
"""
import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from uav_vs.bag.reader import BagError
from uav_vs.flight.fleet import FLEET, FLEET_SCENARIOS, fly_fleet
from uav_vs.flight.plots import plot_flight
from uav_vs.flight.recorder import MissionError
from uav_vs.flight.replay import commands_from_bag, replay_flight, stamps_from_bag
from uav_vs.flight.report import FlightLog, FlightReport, command_latencies, score_link_cut
from uav_vs.flight.scenario import (SCENARIOS, Configs, SitlLink, fly, sitl_params,
                                    vehicle_bag)
from uav_vs.sim import netns, radio_link
from uav_vs.sim.radio_link import LinkConfig, TwoHosts
from uav_vs.sim.sitl_process import (HOW_TO_GET, WARM_UP_SPEEDUP, ArduCopterSitl,
                                     enter_loopback_namespace, find_binary)
from uav_vs.vision.ground_config import default_config_path, read_params_file

AUTOPILOTS = ('ardupilot', 'px4', 'ardupilot-sitl')
SENSORS = ('realistic', 'ideal')     # config/sensors_<profile>.yaml
SITL_STARTUP_S = 120.0    # an attached SITL is ready to arm ~45 s after its start (GPS, EKF3)


def replay(bag: Path, out: Path, rate: float) -> int:
    """A recorded bag through the open-loop graph, scored against its truth."""
    print(f'replaying {bag} through the open-loop graph (logs in {out}/logs/)', flush=True)
    try:
        log = replay_flight(bag, out / 'logs', rate=rate)
    except (MissionError, BagError) as err:
        print(f'replay failed: {err}', file=sys.stderr)
        return 1
    return report(log, out)


def closed_loop(scenario_name: str, out: Path, autopilot: str, sensors: str,
                sitl: SitlLink | None = None, hosts: TwoHosts | None = None,
                cut_link: float = 0.0, view: bool = False) -> int:
    """Fly a scenario (recording its bag into out/bag) with the `sensors` profile; print
    and save the summary and plots. With `view`, foxglove_node serves the graph too."""
    scenario = SCENARIOS[scenario_name]
    vehicle = f'ArduCopter SITL on {sitl.relay}' if sitl else f'simulated {autopilot}'
    if hosts is not None:
        print(f"two hosts: ground {hosts.names['ground']} ({hosts.address('ground')}), vehicle "
              f"{hosts.names['air']} ({hosts.address('air')}), over a radio link of "
              f'{hosts.config}', flush=True)
    profile = default_config_path(f'sensors_{sensors}.yaml')
    nodes = ['3 camshift_node', 'trinocular_pose_node',
             *(['homography_pose_node'] if scenario.setpoints or scenario.landing else []),
             *(['target_tracker_node', 'target_follower_node'] if scenario.follow else []),
             'fuzzy_controller_node', 'mavlink_relay_node', 'pose_filter_node']
    print(f'closed loop: scenario {scenario.name}, {sensors} sensors ({profile.name}), '
          f"sim_world ({vehicle}) + {' + '.join(nodes)}, recorded to {out}/bag "
          f'(logs in {out}/logs/)', flush=True)
    viewer = default_config_path('foxglove.yaml') if view else None
    configs = Configs(sensors=profile, pose_filter=default_config_path('pose_filter.yaml'),
                      foxglove=viewer,
                      frames=default_config_path('frames.yaml') if view else None)
    if viewer is not None:
        p = read_params_file(viewer)
        print(f"live view: open ws://{p['foxglove.host']}:{p['foxglove.port']} in Foxglove or "
              'Lichtblick (Open connection, Foxglove WebSocket), then import the layout '
              f'{default_config_path("foxglove/uav_vs.json")} (docs/live_view.md)', flush=True)
    return report(fly(scenario, out, configs, autopilot=autopilot, sitl=sitl,
                      startup_timeout=SITL_STARTUP_S if sitl else 90.0, hosts=hosts,
                      cut_link=cut_link), out)


def fleet_closed_loop(out: Path, autopilot: str, sensors: str) -> int:
    """Two vehicles at once (uav_vs.flight.fleet); a summary, plots and flight log per
    vehicle in out/<name>, the crosstalk counts and CPU times in out/fleet.json."""
    profile = default_config_path(f'sensors_{sensors}.yaml')
    names = ', '.join(f'{m.name} (system id {m.system_id}, home {m.start})' for m in FLEET)
    print(f'closed loop, {len(FLEET)} vehicles: {names}; {sensors} sensors ({profile.name}); '
          f'per vehicle sim_world + ground_station + homography_pose_node + '
          f'fuzzy_controller_node + mavlink_relay_node, and sim_cameras for the ground '
          f'cameras (logs in {out}/<vehicle>/logs/)', flush=True)
    run = fly_fleet(list(zip(FLEET, FLEET_SCENARIOS)), out, Configs(sensors=profile),
                    autopilot=autopilot)
    code = 0
    counts = {}
    for member, log, seen in zip(FLEET, run.logs, run.crosstalk):
        print(f'--- {member.name}', flush=True)
        code |= report(log, out / member.name)
        counts[member.name] = dict(looks=seen.samples, count=seen.count,
                                   foreign_publishers=sorted(seen.foreign_publishers),
                                   foreign_subscribers=sorted(seen.foreign_subscribers),
                                   wrong_system=seen.wrong_system)
        print(f'{member.name} crosstalk: {seen.count} over {seen.samples} looks (cmd_vel '
              f'publishers or subscribers outside /{member.name}: '
              f'{len(seen.foreign_publishers) + len(seen.foreign_subscribers)}; relay reports '
              f'of another system id: {seen.wrong_system})')
    (out / 'fleet.json').write_text(json.dumps(dict(
        crosstalk=counts, cpu_s=run.cpu_s, run_s=run.run_s), indent=1) + '\n')
    print(f'CPU over the {run.run_s:.0f} s run: ' + ', '.join(
        f'{name} {s:.0f} s ({s / run.run_s:.2f} of a core)' for name, s in run.cpu_s.items())
        + ' (sim_cameras: the simulated ground cameras, every vehicle drawn)')
    failed = {label: rc for label, rc in run.exit_codes.items() if rc}
    if failed:
        print(f'shared processes failed: {failed} (logs in {out}/logs/)', file=sys.stderr)
    return 1 if code or failed else 0


def two_hosts_closed_loop(scenario_name: str, out: Path, autopilot: str, sensors: str,
                          cut_link: float = 0.0) -> int:
    """The closed loop on two hosts joined by the default radio link (radio_link): this
    process enters the ground host. With `cut_link` the link is cut for that long once the
    vehicle holds."""
    hosts = TwoHosts(str(os.getpid()), LinkConfig(), stats=out / 'link.json')
    try:
        hosts.__enter__()
    except (PermissionError, OSError, subprocess.CalledProcessError, RuntimeError) as err:
        print(f'cannot make two hosts (network namespaces need root): {err}', file=sys.stderr)
        return 2
    try:
        netns.enter(hosts.names['ground'])
        os.environ.update(hosts.ros_env('ground'))
        code = closed_loop(scenario_name, out, autopilot, sensors, hosts=hosts,
                           cut_link=cut_link)
    finally:
        hosts.__exit__()
    summary = radio_link.summary(hosts.stats())
    if vehicle_bag(out).exists() and (out / 'flight.npz').exists():
        log = FlightLog.load(out / 'flight.npz')
        received = commands_from_bag(vehicle_bag(out))
        on_vehicle = replace(log, commands=received)
        for source, where in (('ground', 'across the link'), ('onboard', 'on the vehicle')):
            latency = command_latencies(on_vehicle, source)
            if len(latency):
                summary += (f'\ncmd_vel on the vehicle from {source} frames (controller '
                            f'{where}): {len(latency)} commands; image stamp to command: '
                            f'median {np.median(latency):.1f} ms, '
                            f'p95 {np.percentile(latency, 95):.1f} ms')
        summary += '\nacross the link: ' + '; '.join(
            f'{what} {arrived} of {sent} arrived ({sent - arrived} lost)'
            for what, sent, arrived in (
                ('cmd_vel of the ground frames', *arrivals(ground_commands(log),
                                                           received.stamps)),
                ('onboard/pose', *arrivals(stamps_from_bag(vehicle_bag(out), '/onboard/pose'),
                                           log.onboard.stamps))))
        summary += f'\nCPU over the {log.run_s:.0f} s run: ' + ', '.join(
            f'{host} {s:.0f} s ({s / log.run_s:.2f} of a core)' for host, s in log.cpu_s.items())
        cut = score_link_cut(log, received)
        if cut is not None:
            summary += (f'\nlink cut for {cut.cut_s:.1f} s: the ground reported it after '
                        f'{cut.reported_after_s:.2f} s and heard the vehicle again '
                        f'{cut.heard_again_after_s:.2f} s after it returned; no cmd_vel on the '
                        f'vehicle for {cut.command_gap_s:.2f} s; the vehicle moved '
                        f'{cut.drift_m * 100:.1f} cm meanwhile')
    print(summary)
    with open(out / 'summary.txt', 'a') as f:
        f.write(summary + '\n')
    return code


def ground_commands(log: FlightLog) -> np.ndarray:
    """The stamps of the commands the controller sent from the ground host: those of the
    ground cameras' frames (on the onboard pose it flies on the vehicle)."""
    stamps = log.commands.stamps
    return stamps[np.isin(stamps, log.ground_frames)]


def arrivals(sent: np.ndarray, received: np.ndarray) -> tuple[int, int]:
    """How many messages were sent, and how many of them arrived (matched by stamp)."""
    return len(np.unique(sent)), len(np.intersect1d(sent, received))


def sitl_closed_loop(scenario_name: str, out: Path, sensors: str, attach: str | None,
                     truth: str | None) -> int:
    """The closed loop on ArduCopter SITL: attached to `attach`, or started here."""
    gps_denied = SCENARIOS[scenario_name].gps_denied
    extra = sitl_params(SCENARIOS[scenario_name])
    if attach:
        if extra:
            print(f'the SITL at {attach} must run with {", ".join(map(str, extra))}',
                  flush=True)
        return closed_loop(scenario_name, out, 'ardupilot', sensors,
                           SitlLink(attach, truth or next_serial_port(attach)))
    binary = find_binary()
    if binary is None:
        print(f'no ArduCopter SITL: {HOW_TO_GET}', file=sys.stderr)
        return 2
    namespace = f'uavvs_demo_{os.getpid()}'
    try:
        enter_loopback_namespace(namespace)
    except (PermissionError, OSError, subprocess.CalledProcessError) as err:
        print(f'cannot start SITL: {err}', file=sys.stderr)
        return 2
    try:
        with ArduCopterSitl(binary, out / 'sitl', extra_params=extra) as sitl:
            relay, serial1, _ = sitl.serial_ports
            print(f'ArduCopter SITL {binary} started in network namespace {namespace} '
                  f'(log {sitl.log_path})', flush=True)
            if not gps_denied:      # without GPS it waits for the vision pose: real time
                start = time.monotonic()
                ready = sitl.warm_up()
                print(f'ArduCopter SITL ready to arm at {ready:.1f} s of its time, '
                      f'{time.monotonic() - start:.1f} s after its start (run at SIM_SPEEDUP '
                      f'{WARM_UP_SPEEDUP:g} until then)' if ready is not None else
                      'ArduCopter SITL not ready to arm after its warm-up: waiting', flush=True)
            return closed_loop(scenario_name, out, 'ardupilot', sensors,
                               SitlLink(f'tcp:127.0.0.1:{relay}', f'tcp:127.0.0.1:{serial1}'))
    finally:
        netns.delete(namespace)


def next_serial_port(connection: str) -> str:
    """tcp:HOST:PORT -> tcp:HOST:PORT+2, SITL's SERIAL1 beside its SERIAL0."""
    head, _, port = connection.rpartition(':')
    if not port.isdigit():
        raise SystemExit(f'--sitl {connection}: expected tcp:HOST:PORT')
    return f'{head}:{int(port) + 2}'


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
    parser.add_argument('--autopilot', default='ardupilot', choices=AUTOPILOTS,
                        help="whose MAVLink behaviour the simulated vehicle follows, or "
                             "ardupilot-sitl: ArduCopter SITL is the vehicle "
                             "(default %(default)s)")
    parser.add_argument('--sensors', default='realistic', choices=SENSORS,
                        help="the simulated world's sensor profile, config/sensors_<profile>"
                             '.yaml (default %(default)s)')
    parser.add_argument('--sitl', help='with ardupilot-sitl: the connection of a SITL already '
                        'running, for the relay (e.g. tcp:127.0.0.1:5760); default: start one')
    parser.add_argument('--sitl-truth', help="that SITL's port for the SIM_STATE truth "
                        '(default: --sitl PORT + 2)')
    parser.add_argument('--hosts', type=int, default=1, choices=(1, 2),
                        help='2: the ground station and the vehicle on two hosts (network '
                        'namespaces, needs root) joined by a radio link of 20 +- 10 ms and '
                        '2 %% loss (default %(default)s)')
    parser.add_argument('--vehicles', type=int, default=1, choices=(1, 2),
                        help='2: two simulated vehicles, /uav1 and /uav2, each flying its own '
                        'hold and setpoint in view of the same ground cameras')
    parser.add_argument('--cut-link', type=float, default=0.0, metavar='SECONDS',
                        help='with --hosts 2: cut the radio link for SECONDS once the '
                        'vehicle holds (default: never)')
    parser.add_argument('--view', action='store_true',
                        help='serve the graph to Foxglove or Lichtblick while it flies '
                        '(foxglove_node, config/foxglove.yaml); simulated vehicle, one host')
    parser.add_argument('--out', type=Path, help='output folder (default demo-output, '
                        'demo-output/replay with --bag)')
    args = parser.parse_args(argv)
    # As `make` sets them: shared-memory transport for images, discovery on this host.
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE',
                          str(default_config_path('fastdds_shm.xml')))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    out = args.out or Path('demo-output', *(['replay'] if args.bag else []))
    out.mkdir(parents=True, exist_ok=True)
    if args.view and (args.bag is not None or args.autopilot == 'ardupilot-sitl'
                      or args.hosts == 2 or args.vehicles == 2):
        parser.error('--view watches a closed-loop flight of the simulated vehicle on one '
                     'host: no --bag, ardupilot-sitl, --hosts 2 or --vehicles 2')
    if args.bag is not None:
        return replay(args.bag, out, args.rate)
    if SCENARIOS[args.scenario].gps_denied and args.autopilot != 'ardupilot-sitl':
        parser.error(f'--scenario {args.scenario} needs --autopilot ardupilot-sitl (an EKF '
                     'that navigates on the vision pose)')
    if args.autopilot == 'ardupilot-sitl':
        if args.hosts == 2 or args.vehicles == 2:
            parser.error(f'--{"hosts" if args.hosts == 2 else "vehicles"} 2 flies the simulated '
                         'vehicle: --autopilot ardupilot or px4')
        return sitl_closed_loop(args.scenario, out, args.sensors, args.sitl, args.sitl_truth)
    if args.cut_link and args.hosts != 2:
        parser.error('--cut-link cuts the radio link between two hosts: give --hosts 2')
    if args.vehicles == 2:
        if args.hosts == 2 or args.scenario != 'demo':
            parser.error('--vehicles 2 flies its own two missions on one host: no --hosts, '
                         'no --scenario')
        return fleet_closed_loop(out, args.autopilot, args.sensors)
    if args.hosts == 2:
        return two_hosts_closed_loop(args.scenario, out, args.autopilot, args.sensors,
                                     args.cut_link)
    return closed_loop(args.scenario, out, args.autopilot, args.sensors, view=args.view)


if __name__ == '__main__':
    sys.exit(main())
