"""Several vehicles in one world, each flying its own mission (chapter section 5, a fleet).

`fly_fleet(flights, out_dir)` flies one `Scenario` per vehicle (a scenario.Member: its
namespace /uavN, MAVLink system id, home in world and landmark colours). Each vehicle's
mission is uav_vs.flight.scenario's, in its namespace, on a thread of its own:

    /uavN/sim_world                 its simulated autopilot (its system id, its own MAVLink
                                    port, home at its start) and onboard camera; its truth
                                    served as SIM_STATE
    /uavN/ground_station            the ground station tracking its landmark colours in the
                                    shared cameras' images (/camK/image_raw)
    /uavN/fuzzy_controller_node, /uavN/mavlink_relay_node (target_system N),
    /uavN/homography_pose_node      as for one vehicle

and once every vehicle's world is up, one `sim_cameras` renders the ground cameras (/cam1,
/cam2, /cam3) with every vehicle where its truth says (sim_world's fleet.*), publishing
each vehicle's truth at the frames' instants on /uavN/truth/pose.

Crosstalk is counted from the ROS graph and the relays: every publisher of a vehicle's
cmd_vel and every subscriber to it, sampled twice a second through the flight, must be
in that vehicle's namespace, and its relay must hear only its own system id.
"""
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from uav_vs import graph
from uav_vs.flight.recorder import MissionError
from uav_vs.flight.report import FlightLog
from uav_vs.flight.scenario import NORTH, Configs, Member, Scenario, Setpoint, _Mission, \
    free_port, world_args, xy_param
from uav_vs.vision.ground_config import default_config_path

UNKNOWN_NAMESPACE = '_NODE_NAMESPACE_UNKNOWN_'   # what rclpy names a node not discovered yet

# Two vehicles: homes 1.7 m apart, their holds and setpoints 0.5 m apart in height, their
# paths crossing in the middle of the area in plan (never in space).
FLEET = (Member('uav1', 1, (-0.7, -0.5)),
         Member('uav2', 2, (0.7, 0.5), default_config_path('landmarks_uav2.yaml')))
FLEET_SCENARIOS = (
    Scenario('uav1', 1.3, Setpoint((-0.7, -0.5, 1.3), hold=3.0),
             (Setpoint((0.6, -0.4, 1.3), yaw=NORTH - 0.4),)),
    Scenario('uav2', 1.8, Setpoint((0.7, 0.5, 1.8), hold=3.0),
             (Setpoint((-0.6, 0.4, 1.8), yaw=NORTH + 0.4),)),
)


@dataclass
class Crosstalk:
    """What the graph showed of one vehicle's commands (`FleetRun.crosstalk`)."""

    samples: int = 0                  # looks at the graph
    foreign_publishers: set = field(default_factory=set)    # cmd_vel publishers elsewhere
    foreign_subscribers: set = field(default_factory=set)   # cmd_vel subscribers elsewhere
    wrong_system: int = 0             # relay reports naming another system id

    @property
    def count(self) -> int:
        return len(self.foreign_publishers) + len(self.foreign_subscribers) + self.wrong_system


@dataclass
class FleetRun:
    """What `fly_fleet` gives: per vehicle, in the flights' order, its flight log and
    crosstalk; the shared processes' (sim_cameras) exit codes; the CPU time of each
    vehicle's nodes and of the shared ones, s, over the run's `run_s` s."""

    logs: list[FlightLog]
    crosstalk: list[Crosstalk]
    exit_codes: dict[str, int]
    cpu_s: dict[str, float]
    run_s: float


def fly_fleet(flights: Sequence[tuple[Member, Scenario]], out_dir: Path,
              configs: Configs = Configs(), startup_timeout: float = 120.0,
              autopilot: str = 'ardupilot') -> FleetRun:
    """Fly every (member, scenario) at once; node logs go to out_dir/<name>/logs and the
    ground cameras' to out_dir/logs."""
    if len({m.name for m, _ in flights}) != len(flights) or \
            len({m.system_id for m, _ in flights}) != len(flights):
        raise ValueError('every vehicle needs a name and a system id of its own')
    ports = [free_port() for _ in flights]
    shared: dict = {}

    def start_cameras() -> None:
        (first, _), *others = flights
        args = [*world_args(configs, first.landmarks),
                '-r', '__node:=sim_cameras', '-r', f'truth/pose:=/{first.name}/truth/pose',
                '-p', 'vehicle.model:=sitl', '-p', 'onboard.rate:=0.0',
                '-p', f'vehicle.sitl_connection:=tcp:127.0.0.1:{ports[0]}',
                '-p', f'vehicle.system_id:={first.system_id}',
                *xy_param('vehicle.start', first.start)]
        if others:
            args += ['-p', f'fleet.names:=[{", ".join(m.name for m, _ in others)}]']
        for (m, _), port in zip(others, ports[1:]):
            key = f'fleet.{m.name}'
            args += ['-p', f'{key}.truth_connection:=tcp:127.0.0.1:{port}',
                     '-p', f'{key}.system_id:={m.system_id}',
                     *xy_param(f'{key}.start', m.start),
                     '-p', f'{key}.landmarks:={m.landmarks}']
        shared['sim_cameras'] = graph.start('sim_world', args, out_dir / 'logs', 'sim_cameras')

    barrier = threading.Barrier(len(flights), action=start_cameras)

    def ready() -> None:
        try:
            barrier.wait(startup_timeout)
        except threading.BrokenBarrierError:
            raise MissionError('the fleet did not start: another vehicle\'s world did not '
                               'come up, or the ground cameras could not start') from None

    missions = [_Mission(scenario, out_dir / m.name / 'logs', configs, None, autopilot, None,
                         None, 0.0, member=m, truth_port=port, ready=ready)
                for (m, scenario), port in zip(flights, ports)]
    logs: list[FlightLog | None] = [None] * len(missions)
    threads = [threading.Thread(target=lambda k=k: logs.__setitem__(k, missions[k].run(
        startup_timeout)), name=f'mission {m.name}') for k, (m, _) in enumerate(flights)]
    crosstalk = [Crosstalk() for _ in flights]
    start = time.monotonic()
    try:
        for t in threads:
            t.start()
        while any(t.is_alive() for t in threads):
            for mission, seen in zip(missions, crosstalk):
                look(mission, seen)
            time.sleep(0.5)
    finally:
        for t in threads:
            t.join()
        graph.stop(list(shared.values()))
    cpu = {m.name: sum(getattr(p, 'cpu_s', math.nan) for p in mission.all_procs().values())
           for (m, _), mission in zip(flights, missions)}
    cpu |= {label: getattr(p, 'cpu_s', math.nan) for label, p in shared.items()}
    return FleetRun(logs, crosstalk, {label: p.returncode for label, p in shared.items()}, cpu,
                    time.monotonic() - start)


def look(mission: _Mission, seen: Crosstalk) -> None:
    """One look at the graph around a vehicle's cmd_vel, and at its relay's report."""
    rec = getattr(mission, 'rec', None)
    if rec is None or not rec.context.ok():
        return
    topic = f'{mission.ns}/cmd_vel'
    try:
        publishers = rec.node.get_publishers_info_by_topic(topic)
        subscribers = rec.node.get_subscriptions_info_by_topic(topic)
    except RuntimeError:     # the recorder closed under us (InvalidHandle): its flight is over
        return
    seen.samples += 1
    seen.foreign_publishers |= foreign(publishers, mission.ns)
    seen.foreign_subscribers |= foreign(subscribers, mission.ns)
    system = rec.relay.get('system_id', 'None')
    if system not in ('None', '') and int(system) != mission.member.system_id:
        seen.wrong_system += 1


def foreign(endpoints, namespace: str) -> set[str]:
    """The nodes of `endpoints` (TopicEndpointInfo) outside `namespace`. An endpoint whose
    node DDS has not named yet (it comes after the endpoint) is left for a later look."""
    return {f'{i.node_namespace}/{i.node_name}' for i in endpoints
            if i.node_namespace not in (namespace, UNKNOWN_NAMESPACE)}
