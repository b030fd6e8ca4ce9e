"""graph/two_hosts and graph/vehicles: the closed loop across a radio link, and with a
second vehicle, each beside the same graph on one host with one vehicle.

Every flight has the ideal sensors (config/sensors_ideal.yaml); the latency is its image
stamp -> cmd_vel (uav_vs.flight.report.command_latencies).
- graph/two_hosts: `python -m uav_vs.demo --hosts 2 --scenario land_on_pad` (root: network
  namespaces) beside the same on one host, the commands as the vehicle's own recorder
  received them across the link (20 +- 10 ms, 2 % loss). Target: p95 within the one-host
  p95 + the link's own p95 delay (ground to vehicle) + 10 ms, hold RMS within 1.5 times
  the one-host one. Then the same per camera: graph/two_hosts/ground_frames (the
  controller on the ground, its commands across the link once) and .../onboard_frames
  (the controller on the vehicle, nothing across), each against its one-host p95 + the
  link's p95 per crossing + 10 ms.
- graph/vehicles/<name>: the two vehicles of `--vehicles 2` flown together
  (uav_vs.flight.fleet), each beside its own mission flown alone: its commands' latency,
  its hold (target: within the alone figure + 1 cm), the CPU its nodes took (cores), the
  simulated ground cameras' rendering (sim_cameras) and the crosstalk the flight counted:
  what each extra vehicle costs.
"""
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import report
from uav_vs.flight.fleet import FLEET, FLEET_SCENARIOS, fly_fleet
from uav_vs.flight.replay import commands_from_bag
from uav_vs.flight.report import FlightLog, FlightReport, command_latencies
from uav_vs.flight.scenario import Configs, vehicle_bag
from uav_vs.vision.ground_config import default_config_path


def demo(out: Path, *args: str) -> bool:
    """Run the demo into `out`; False (said) if it failed."""
    run = subprocess.run([sys.executable, '-m', 'uav_vs.demo', '--sensors', 'ideal',
                          '--out', str(out), *args], capture_output=True, text=True, timeout=900)
    if run.returncode:
        print(f'demo {" ".join(args)} failed: {(run.stderr or run.stdout)[-800:]}', flush=True)
    return run.returncode == 0


def hold_rms_cm(log: FlightLog) -> float:
    return round(FlightReport.from_log(log).setpoints[0].error_rms_m * 100, 2)


def two_hosts(out: Path, one: FlightLog) -> None:
    if os.geteuid() != 0:
        print('graph/two_hosts: not run (network namespaces need root)', flush=True)
        return
    if not demo(out, '--hosts', '2', '--scenario', 'land_on_pad'):
        return
    log = FlightLog.load(out / 'flight.npz')
    on_vehicle = replace(log, commands=commands_from_bag(vehicle_bag(out)))
    held = json.loads((out / 'link.json').read_text())['ground_to_air']['held']
    link_p95 = float(np.percentile(held, 95)) * 1e3
    for source, crossings in ((None, 1), ('ground', 1), ('onboard', 0)):
        one_ms = command_latencies(one, source)
        name = f'graph/two_hosts/{source}_frames' if source else 'graph/two_hosts'
        report('graph', name, command_latencies(on_vehicle, source),
               f'one host, {source or "all"} frames, image stamp -> cmd_vel', one_ms,
               crossings=crossings, link_p95_ms=round(link_p95, 1),
               bound_p95_ms=round(float(np.percentile(one_ms, 95)) + crossings * link_p95 + 10, 1),
               hold_rms_cm=hold_rms_cm(log), one_host_hold_rms_cm=hold_rms_cm(one),
               failure=log.failure or None)


def vehicles(out: Path) -> None:
    flights = list(zip(FLEET, FLEET_SCENARIOS))
    ideal = Configs(sensors=default_config_path('sensors_ideal.yaml'))
    alone = [fly_fleet([flight], out / f'{flight[0].name}_alone', ideal) for flight in flights]
    together = fly_fleet(flights, out / 'together', ideal)
    for k, (member, _) in enumerate(flights):
        log, single = together.logs[k], alone[k].logs[0]
        report('graph', f'graph/vehicles/{member.name}', command_latencies(log),
               f'{member.name} alone, image stamp -> cmd_vel', command_latencies(single),
               hold_rms_cm=hold_rms_cm(log), alone_hold_rms_cm=hold_rms_cm(single),
               cpu_cores=round(together.cpu_s[member.name] / together.run_s, 2),
               alone_cpu_cores=round(alone[k].cpu_s[member.name] / alone[k].run_s, 2),
               sim_cameras_cores=round(together.cpu_s['sim_cameras'] / together.run_s, 2),
               alone_sim_cameras_cores=round(alone[k].cpu_s['sim_cameras'] / alone[k].run_s, 2),
               crosstalk=together.crosstalk[k].count,
               failure=log.failure or single.failure or None)


def main() -> None:
    with tempfile.TemporaryDirectory(prefix='uav_vs_scaling_') as tmp:
        tmp = Path(tmp)
        if not demo(tmp / 'one', '--scenario', 'land_on_pad'):
            return
        two_hosts(tmp / 'two_hosts', FlightLog.load(tmp / 'one' / 'flight.npz'))
        vehicles(tmp / 'vehicles')
