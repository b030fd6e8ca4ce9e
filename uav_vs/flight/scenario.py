"""Chapter section 5 in closed loop: take off and hold, move through setpoints, land on a pad.

`fly(scenario, out_dir)` starts the graph as separate processes, each the way
`ros2 run` would (uav_vs.graph.start with `--ros-args --params-file config/...`):

    sim_world                  the MAVLink vehicle and its cameras (config/sim_world.yaml)
    mavlink_relay_node         cmd_vel to the vehicle, autopilot/odom back
    camshift_node x3, trinocular_pose_node    ground/pose (section 3)
    fuzzy_controller_node      pose error to cmd_vel (section 6), on ground/pose, and on
                               onboard/pose for the landing (restarted with that input)
    homography_pose_node       onboard/pose (section 4), started once the vehicle hovers
                               at the hold setpoint, initialised at the ground station's
                               pose of it (so both vision poses share `world`)
    target_tracker_node,       following a target (section 5): the target found in the
    target_follower_node       onboard images, placed on the ground from ground/pose,
                               becomes the setpoint; started after the hold
    pose_filter_node           with Configs.pose_filter (the demo's): fused/pose from both
                               vision poses and autopilot/odom, recorded and scored beside
                               them; the controller flies the hold and the setpoints on it
                               in a `fused` scenario

and flies the mission: the relay's `set_guided`, `arm`, `takeoff`, `set_guided` again
(PX4 holds in AUTO.LOITER after its takeoff); the controller's
`controller/enable`; one `setpoint` after another, each accepted once the
vision pose the controller flies on has stayed within the tolerance for the hold; over
the pad, the relay's `land`. The mission never looks at the truth or at the autopilot's
estimate; it records them, with both vision poses and the commands, into a
`FlightLog` that uav_vs.flight.report scores.
"""
import math
import resource
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
from std_srvs.srv import SetBool, Trigger

from uav_vs import graph
from uav_vs.autopilot.frames import wrap_angle
from uav_vs.flight.ground_replay import DEFAULT_LAYOUT, ground_graph
from uav_vs.flight.recorder import FlightRecorder, MissionError
from uav_vs.flight.report import FlightLog, SetpointEvent
from uav_vs.sim.radio_link import TwoHosts
from uav_vs.sim.sitl_process import HOME_LLA
from uav_vs.vision.ground_config import default_config_path, read_params_file

NORTH = math.pi / 2          # ENU heading of the vehicle at boot (MAVLink yaw 0 = north)
TRUTH_PORT = 5762            # the vehicle's SIM_STATE port on two hosts (SITL's SERIAL1)


@dataclass(frozen=True)
class Setpoint:
    """A pose to reach and hold (section 5): position in world ENU, m; yaw, rad."""

    position: tuple[float, float, float]
    yaw: float = NORTH
    hold: float = 2.0            # s the vision pose must stay within the tolerance
    tolerance: float = 0.05      # m, distance of the vision pose from the setpoint
    yaw_tolerance: float = 0.05  # rad
    timeout: float = 30.0        # s to settle and hold


@dataclass(frozen=True)
class Landing:
    """Land on a pad with the onboard pose (section 5): centre over it at `approach`
    height, descend to `final` height, then the autopilot's LAND (straight down)."""

    pad: tuple[float, float]     # x, y in world, m
    approach: float = 1.2        # m
    final: float = 0.8           # m
    hold: float = 1.5            # s at each height
    tolerance: float = 0.03      # m


@dataclass(frozen=True)
class Follow:
    """Follow the target moving on the ground (section 5) after the hold: sim_world
    drives it (ground_target.*), target_tracker_node finds it in the onboard images and
    target_follower_node turns it into setpoints `height` above it. Scored for `duration`
    s once `settle` s have passed since its first estimate."""

    duration: float = 30.0       # s
    settle: float = 6.0          # s
    height: float = 1.5          # m
    lost_after: float = 2.0      # s without a target estimate: the mission fails


@dataclass(frozen=True)
class Scenario:
    """Take off to `takeoff_height`, hold `hold`, fly `setpoints`, land (on the pad of
    `landing`, with the onboard pose; without one, where the vehicle is); with `follow`,
    follow the moving target after the hold, then land where the vehicle is.

    With `gps_denied` the autopilot has no GPS: the relay feeds it the ground station's
    pose as external navigation (vision_pose_topic, ekf_origin), and ArduPilot SITL runs
    with config/ardupilot_gps_denied.parm; with `external_nav` 'fused' it feeds the pose
    filter's fused/odom instead, with its covariance (SITL adds
    config/ardupilot_fused_nav.parm), the filter run without the autopilot's odometry,
    which would bring EKF3's own estimate back into it.

    With `fused` the controller flies the hold and the setpoints on the pose filter's
    estimate (fused/pose; Configs.pose_filter), and with `blind` the ground cameras are
    covered for that many seconds from the start of the flight to the first setpoint
    (sim_world's ground_cameras/enable), the setpoint held only once they see again."""

    name: str
    takeoff_height: float
    hold: Setpoint
    setpoints: tuple[Setpoint, ...] = ()
    landing: Landing | None = None
    gps_denied: bool = False
    follow: Follow | None = None
    external_nav: str = 'ground'     # without GPS: 'ground' (ground/pose) or 'fused'
    fused: bool = False
    blind: float = 0.0           # s

    @property
    def fused_external_nav(self) -> bool:
        """Whether the autopilot navigates without GPS on the pose filter's fused/odom."""
        return self.gps_denied and self.external_nav == 'fused'


HOLD = Scenario('hold', 1.5, Setpoint((0.0, 0.0, 1.5), hold=5.0))
SETPOINTS = Scenario('setpoints', 1.5, Setpoint((0.0, 0.0, 1.5)), (
    Setpoint((1.0, 0.6, 1.8)),
    Setpoint((1.0, -0.8, 1.2), yaw=NORTH - 0.6),
    Setpoint((-0.8, -0.6, 1.5), yaw=NORTH + 0.4),
))
LAND_ON_PAD = Scenario('land_on_pad', 1.5, Setpoint((0.0, 0.0, 1.5)),
                       landing=Landing((0.8, -0.5)))
DEMO = Scenario('demo', 1.5, Setpoint((0.0, 0.0, 1.5), hold=3.0), SETPOINTS.setpoints,
                Landing((0.6, 0.4)))
GPS_DENIED = Scenario('gps_denied', 1.5, Setpoint((0.0, 0.0, 1.5), hold=5.0), gps_denied=True)
GPS_DENIED_FUSED = Scenario('gps_denied_fused', 1.5, Setpoint((0.0, 0.0, 1.5), hold=5.0),
                            gps_denied=True, external_nav='fused')
FOLLOW = Scenario('follow', 1.5, Setpoint((0.0, 0.0, 1.5)), follow=Follow())
BLIND = Scenario('blind', 1.5, Setpoint((0.0, 0.0, 1.5), hold=3.0), SETPOINTS.setpoints[:2],
                 Landing((0.6, 0.4)), fused=True, blind=3.0)
SCENARIOS = {s.name: s for s in (HOLD, SETPOINTS, LAND_ON_PAD, DEMO, GPS_DENIED,
                                 GPS_DENIED_FUSED, FOLLOW, BLIND)}
# The parameters ArduPilot flies GPS_DENIED with, after its defaults; and after those, on
# the fused estimate (GPS_DENIED_FUSED).
GPS_DENIED_PARAMS = default_config_path('ardupilot_gps_denied.parm')
FUSED_NAV_PARAMS = default_config_path('ardupilot_fused_nav.parm')


def sitl_params(scenario: Scenario) -> tuple[Path, ...]:
    """The parameter files ArduPilot SITL flies `scenario` with, after its defaults."""
    if not scenario.gps_denied:
        return ()
    return (GPS_DENIED_PARAMS, *((FUSED_NAV_PARAMS,) if scenario.fused_external_nav
                                 else ()))


@dataclass(frozen=True)
class Configs:
    """The params files the graph is started with, and the ground station's layout
    (uav_vs.flight.ground_replay.LAYOUTS)."""

    ground: Path = default_config_path('ground_trinocular.yaml')
    onboard: Path = default_config_path('onboard.yaml')
    world: Path = default_config_path('sim_world.yaml')
    sensors: Path | None = None      # a sensor profile given after `world`, e.g. SENSORS
    controller: Path = default_config_path('fuzzy_controller.yaml')
    relay: Path = default_config_path('mavlink_relay.yaml')
    pose_filter: Path | None = None     # pose_filter_node's params file; None: not run
    foxglove: Path | None = None        # foxglove_node's (the live view); None: not run
    frames: Path | None = None          # frames_node's (the TF tree a 3D view places the
                                        # cameras and vehicle by); None: not run
    ground_layout: str = DEFAULT_LAYOUT
    # The ground rig as it really is, which sim_world renders, when the ground station is
    # given another calibration in `ground` (one solved by uav_vs_calibrate); default: ground.
    world_ground: Path | None = None


@dataclass(frozen=True)
class Member:
    """One vehicle of several in the same world and ground cameras (uav_vs.flight.fleet):
    its namespace (/name), MAVLink system id, home in world (x, y, m) and a params file
    of its landmark colours, given after Configs.ground (None: Configs.ground's own)."""

    name: str
    system_id: int
    start: tuple[float, float]
    landmarks: Path | None = None


@dataclass(frozen=True)
class SitlLink:
    """An ArduPilot SITL flying the vehicle: the relay's MAVLink port, and another one
    where sim_world reads the SIM_STATE truth (uav_vs.sim.sitl_truth)."""

    relay: str = 'tcp:127.0.0.1:5760'
    truth: str = 'tcp:127.0.0.1:5762'
    # Where the EKF's origin goes without GPS: latitude, longitude (deg), altitude AMSL (m).
    origin: tuple[float, float, float] = HOME_LLA


def fly(scenario: Scenario, out_dir: Path, configs: Configs = Configs(),
        startup_timeout: float = 90.0, record: bool = True,
        autopilot: str = 'ardupilot', sitl: SitlLink | None = None,
        hosts: TwoHosts | None = None, cut_link: float = 0.0) -> FlightLog:
    """Start the graph, fly `scenario`, stop the graph; node logs go to out_dir/logs and,
    with `record`, the flight's topics (recorded_topics) to the bag out_dir/bag. The
    vehicle is the simulated one, behaving as `autopilot` ('ardupilot' or 'px4') does,
    or with `sitl` that ArduPilot SITL (started, ready within `startup_timeout`).

    With `hosts` the graph runs on two hosts joined by a radio link (uav_vs.sim.
    radio_link): this process, the ground cameras and station, the controller while it
    flies on the ground pose and the recorder on `ground`, which the calling thread must
    have entered (netns.enter, with hosts.ros_env('ground') in os.environ); the vehicle,
    its onboard camera and nodes, the controller while it flies on the onboard pose and
    the relay on `air`. Only poses, setpoints, commands and diagnostics cross the link.
    link_monitor_node on the ground says whether the vehicle is heard; with `cut_link` the
    link is cut for that many seconds once the hold is reached, then the mission goes on.

    A step that fails ends the mission (the vehicle is told to land where it is) and
    is named in the log's `failure`.
    """
    bag = out_dir / 'bag' if record else None
    for old in (bag, vehicle_bag(out_dir)) if record else ():
        if old.exists():
            shutil.rmtree(old)
    return _Mission(scenario, out_dir / 'logs', configs, bag, autopilot, sitl, hosts,
                    cut_link).run(startup_timeout)


def recorded_topics(cameras: list[str], onboard_images: bool = True) -> list[str]:
    """What a flight's bag holds: every camera's JPEG images and calibration, the truth,
    both vision poses, the ground landmarks (and the windows they were found in, which
    a viewer draws over the images), the setpoints, the commands and the autopilot's
    estimate; enough to replay the flight through the open-loop graph.
    Without `onboard_images`, not the onboard camera's (a recorder on another host)."""
    per_camera = [f'{cam}/{topic}' for cam in [*cameras, 'onboard']
                  for topic in ('image_raw/compressed', 'camera_info')
                  if onboard_images or cam != 'onboard' or topic == 'camera_info']
    return [*per_camera, *(f'{cam}/{topic}' for cam in cameras
                           for topic in ('landmarks', 'landmark_windows')),
            *(['onboard/target_outline'] if onboard_images else []), 'truth/pose',
            'ground/pose', 'ground/landmarks', 'onboard/pose', 'setpoint', 'cmd_vel',
            'autopilot/odom', 'truth/target', 'onboard/target', 'target/pose']


def vehicle_bag(out_dir: Path) -> Path:
    """The bag recorded on the vehicle's host, with two hosts: cmd_vel as it arrived there
    (best effort, as the relay takes it: no command is sent again) and onboard/pose as it
    left."""
    return out_dir / 'vehicle_bag'


def world_args(c: Configs, landmarks: Path | None = None) -> list[str]:
    """sim_world's params files: the rig it renders (with `landmarks` over its own), the
    onboard camera, the world and the sensor profile."""
    return ['--params-file', str(c.world_ground or c.ground),
            *(['--params-file', str(landmarks)] if landmarks else []),
            '--params-file', str(c.onboard), '--params-file', str(c.world),
            *(['--params-file', str(c.sensors)] if c.sensors else [])]


def xy_param(name: str, xy: tuple[float, float]) -> list[str]:
    """`-p name:=[x, y]`, a point in world (m) as a parameter."""
    return ['-p', f'{name}:=[{xy[0]:.3f}, {xy[1]:.3f}]']


def at_setpoint(sp: Setpoint, positions: np.ndarray, yaws: np.ndarray) -> bool:
    """Whether every pose (world positions, m; yaws, rad) is within `sp`'s tolerances."""
    off = np.linalg.norm(np.reshape(positions, (-1, 3)) - sp.position, axis=1)
    turn = np.abs(wrap_angle(np.asarray(yaws, float) - sp.yaw))
    return bool((off <= sp.tolerance).all() and (turn <= sp.yaw_tolerance).all())


def free_port() -> int:
    """A TCP port nobody listens on now, for the vehicle's MAVLink endpoint."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class _Mission:
    """One flight of a scenario: processes, mission steps, events."""

    def __init__(self, scenario: Scenario, log_dir: Path, configs: Configs,
                 bag: Path | None, autopilot: str, sitl: SitlLink | None,
                 hosts: TwoHosts | None, cut_link: float, member: Member | None = None,
                 truth_port: int = 0, ready: Callable[[], None] | None = None) -> None:
        """With `member`, one vehicle of a fleet (uav_vs.flight.fleet): its sim_world serves
        its truth on `truth_port`, and `ready()` returns once every vehicle's world is up
        and the ground cameras render them (MissionError if they never do)."""
        self.scenario, self.log_dir, self.configs, self.bag = scenario, log_dir, configs, bag
        self.autopilot, self.sitl, self.hosts, self.cut_link = autopilot, sitl, hosts, cut_link
        self.member, self.truth_port, self.ready = member, truth_port, ready
        self.ns = f'/{member.name}' if member else ''     # the vehicle's namespace
        self.procs: dict[str, subprocess.Popen] = {}      # running
        self.retired: list[tuple[str, subprocess.Popen]] = []   # stopped on purpose
        self.controller_source = ''
        self.events: dict = dict(setpoints=[], pad=scenario.landing.pad if scenario.landing
                                 else None)

    def _fused_nav(self) -> bool:
        """Whether the controller or the autopilot's EKF flies on the pose filter's estimate."""
        return self.scenario.fused or self.scenario.fused_external_nav

    @property
    def _source(self) -> str:
        """The pose the controller flies the hold and the setpoints on."""
        return 'fused' if self.scenario.fused else 'ground'

    def run(self, startup_timeout: float) -> FlightLog:
        if self._fused_nav() and self.configs.pose_filter is None:
            raise ValueError(f'scenario {self.scenario.name} flies on the fused estimate: '
                             'Configs.pose_filter must name the pose filter\'s params file')
        self.cameras = list(read_params_file(self.configs.ground)['cameras.names'])
        self.rec = FlightRecorder(self.cameras[0], self.ns,
                                  self.member.start if self.member else (0.0, 0.0))
        start = time.monotonic()
        try:
            self._start_graph(self.cameras, startup_timeout)
            self._fly(startup_timeout)
        except MissionError as err:
            self.events['failure'] = str(err)
            self._land_anyway()
        finally:
            graph.stop(list(self.procs.values()))
            log = self.rec.log(self.scenario.name, run_s=time.monotonic() - start, **self.events)
            self.rec.close()
        procs = self.all_procs()
        log.exit_codes = {label: proc.returncode for label, proc in procs.items()}
        mission = resource.getrusage(resource.RUSAGE_SELF)
        log.cpu_s = {'ground': mission.ru_utime + mission.ru_stime}
        for proc in procs.values():
            host = getattr(proc, 'host', 'ground')
            log.cpu_s[host] = log.cpu_s.get(host, 0.0) + getattr(proc, 'cpu_s', math.nan)
        log.failed_logs = graph.failed_logs(procs)
        return log

    def all_procs(self) -> dict[str, subprocess.Popen]:
        """Every process the mission started, by label: the retired, then the running."""
        return dict([*self.retired, *self.procs.items()])

    # ---------------------------------------------------------------- graph
    def _start(self, label: str, name: str, ros_args: list[str], args: list[str] = (),
               log_name: str | None = None, on_vehicle: bool = False) -> None:
        """Start a node here, or `on_vehicle` on the vehicle's host if there are two."""
        wrap, env = (), None
        if on_vehicle and self.hosts is not None:
            wrap, env = self.hosts.exec('air'), self.hosts.ros_env('air')
        if self.ns:
            ros_args = [*ros_args, '-r', f'__ns:={self.ns}']
        self.procs[label] = graph.start(name, ros_args, self.log_dir, log_name or label,
                                        env=env, args=args, wrap=wrap)
        self.procs[label].host = 'air' if wrap else 'ground'

    def _start_member_world(self, timeout: float) -> str:
        """The member vehicle's sim_world in its namespace: the vehicle (home at its start,
        its system id), its onboard camera, no ground cameras (the fleet's sim_cameras
        draws every vehicle), its truth served as SIM_STATE; once every vehicle's is up
        and the ground cameras run (ready), the relay's connection to it."""
        port, m = free_port(), self.member
        self._start('sim_world', 'sim_world', [
            *world_args(self.configs), '-p', f'vehicle.connection:=tcpin:127.0.0.1:{port}',
            '-p', f'vehicle.autopilot:={self.autopilot}', '-p', f'vehicle.system_id:={m.system_id}',
            *xy_param('vehicle.start', m.start),
            '-p', f'vehicle.truth_connection:=tcpin:127.0.0.1:{self.truth_port}',
            '-p', 'ground.rate:=0.0', '-p', f'world.seed:={m.system_id}'])
        self._wait(f'{self.ns}/sim_world', lambda: f'{self.ns}/sim_world' in self.rec.reporting,
                   timeout)
        self.ready()
        return f'tcp:127.0.0.1:{port}'

    def _start_graph(self, cameras: list[str], timeout: float) -> None:
        """The recorder, then everything but the onboard pose node; the relay once the
        vehicle serves."""
        c = self.configs
        if self.member is not None:
            vehicle, relay = [], self._start_member_world(timeout)
        elif self.sitl is None:
            port = free_port()
            vehicle = ['-p', f'vehicle.connection:=tcpin:127.0.0.1:{port}',
                       '-p', f'vehicle.autopilot:={self.autopilot}']
            relay = f'tcp:127.0.0.1:{port}'
        else:
            vehicle = ['-p', 'vehicle.model:=sitl',
                       '-p', f'vehicle.sitl_connection:={self.sitl.truth}']
            relay = self.sitl.relay
        if self.bag is not None:
            topics = recorded_topics(cameras, onboard_images=self.hosts is None)
            self._start('bag_record', 'bag_record', [], args=['-o', str(self.bag), *topics])
            if self.hosts is not None:     # the commands as the relay receives them
                self._start('bag_record_vehicle', 'bag_record', [], args=[
                    '-o', str(vehicle_bag(self.bag.parent)), '--best-effort', 'cmd_vel',
                    'onboard/pose'], on_vehicle=True)
        world = world_args(c)
        target = ['-p', 'ground_target.enabled:=true'] if self.scenario.follow else []
        if self.hosts is None and self.member is None:
            self._start('sim_world', 'sim_world', [*world, *vehicle, *target])
        elif self.hosts is not None:
            # The vehicle and its camera fly; the ground cameras are rendered on the ground
            # from the truth the vehicle serves on the world's wire (radio_link).
            truth = f'{self.hosts.world_address("air")}:{TRUTH_PORT}'
            self._start('sim_world', 'sim_world', [
                *world, *vehicle, *target, '-p', 'ground.rate:=0.0',
                '-p', f'vehicle.truth_connection:=tcpin:{truth}'], on_vehicle=True)
            self._wait('sim_world', lambda: '/sim_world' in self.rec.reporting, timeout)
            # Both publish truth/pose at the instants their cameras sample it.
            self._start('sim_cameras', 'sim_world', [
                *world, '-r', '__node:=sim_cameras', '-p', 'vehicle.model:=sitl',
                '-p', f'vehicle.sitl_connection:=tcp:{truth}', '-p', 'onboard.rate:=0.0'])
        self.procs.update(ground_graph(c.ground, cameras, self.log_dir, self._station_args(),
                                       layout=c.ground_layout))
        if self.hosts is not None:
            self._start('link_monitor_node', 'link_monitor_node', [
                '--params-file', str(default_config_path('link_monitor.yaml'))])
        if c.pose_filter is not None:
            own_odometry = (['-p', "pose_filter.odometry_topic:=''"]
                            if self.scenario.fused_external_nav else [])
            self._start('pose_filter_node', 'pose_filter_node',
                        ['--params-file', str(c.pose_filter), *own_odometry])
        if c.frames is not None:
            self._start('frames_node', 'frames_node', [
                a for f in (c.frames, c.ground, c.onboard) for a in ('--params-file', str(f))])
        if c.foxglove is not None:
            self._start('foxglove_node', 'foxglove_node', ['--params-file', str(c.foxglove)])
        self._start_controller(self._source)
        for sim in ('sim_world', 'sim_cameras'):
            if sim in self.procs:
                self._wait(sim, lambda: f'{self.ns}/{sim}' in self.rec.reporting, timeout)
        if self.scenario.gps_denied:
            if self.sitl is None:
                raise MissionError(f'{self.scenario.name} needs an autopilot with an EKF: '
                                   'ArduPilot SITL')
            lat, lon, alt = self.sitl.origin
            nav = (['-p', 'vision_pose_topic:=fused/odom', '-p', 'vision_pose_type:=odometry']
                   if self.scenario.fused_external_nav else
                   ['-p', 'vision_pose_topic:=ground/pose'])
            relay_args = [*nav, '-p', f'ekf_origin:=[{lat:.7f}, {lon:.7f}, {alt:.2f}]']
        else:
            relay_args = []
        if self.member is not None:
            relay_args.extend(['-p', f'target_system:={self.member.system_id}'])
        self._start('mavlink_relay_node', 'mavlink_relay_node', [
            '--params-file', str(c.relay), '-p', f'connection:={relay}',
            '-p', 'allow_arming:=true',
            '-p', f'takeoff_height:={self.scenario.takeoff_height:.3f}', *relay_args],
            on_vehicle=True)

    def _station_args(self) -> list[str]:
        """A member's ground station: its landmarks over the rig's, in its namespace, on
        the shared cameras' images (/camK/image_raw)."""
        if self.member is None:
            return []
        remaps = [a for cam in self.cameras for topic in ('image_raw', 'image_raw/compressed')
                  for a in ('-r', f'{self.ns}/{cam}/{topic}:=/{cam}/{topic}')]
        landmarks = self.member.landmarks
        return [*(['--params-file', str(landmarks)] if landmarks else []),
                '-r', f'__ns:={self.ns}', *remaps]

    def _start_controller(self, source: str) -> None:
        """(Re)start fuzzy_controller_node flying on `source`'s pose (ground or onboard),
        on the host that makes that pose: on two hosts an onboard pose never crosses the
        link, and its commands neither."""
        old = self.procs.pop('fuzzy_controller_node', None)
        if old is not None:
            graph.stop([old])
            self.retired.append((f'fuzzy_controller_node on {self.controller_source}/pose', old))
        self.controller_source = source
        self._start('fuzzy_controller_node', 'fuzzy_controller_node', [
            '--params-file', str(self.configs.controller),
            '-p', f'controller.pose_topic:={source}/pose', '-p', 'controller.command_frame:=world'],
            log_name=f'fuzzy_controller_node_{source}', on_vehicle=source == 'onboard')

    def _check_alive(self) -> None:
        for label, proc in self.procs.items():
            if proc.poll() is not None:
                raise MissionError(f'{label} exited with status {proc.returncode} '
                                   f'(log: {proc.log_path})')

    def _wait(self, what: str, predicate, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            self._check_alive()
            if time.monotonic() > deadline:
                raise MissionError(f'timed out after {timeout:.0f} s waiting for {what}')
            time.sleep(0.05)

    # ---------------------------------------------------------------- mission
    def _fly(self, startup_timeout: float) -> None:
        rec, s = self.rec, self.scenario
        rec.prepare((Trigger, 'set_guided'), (SetBool, 'arm'), (Trigger, 'takeoff'),
                    (Trigger, 'land'), *([(SetBool, 'ground_cameras/enable')] if s.blind else []))
        self._wait('the relay to connect and the vehicle to be ready to arm',
                   lambda: rec.relay.get('link') == 'connected'
                   and rec.relay.get('prearm_ok') == 'True', startup_timeout)
        self._wait('ground/pose', lambda: self._fresh('ground'), startup_timeout)
        self._wait(f'{self._source}/pose', lambda: self._fresh(self._source), startup_timeout)
        rec.call(Trigger, 'set_guided', Trigger.Request(), 15.0)
        rec.call(SetBool, 'arm', SetBool.Request(data=True), 15.0)
        self.events['takeoff_ns'] = time.time_ns()
        rec.call(Trigger, 'takeoff', Trigger.Request(), 30.0)
        # PX4 holds in AUTO.LOITER after a takeoff: back to OFFBOARD (ArduPilot stays GUIDED).
        rec.call(Trigger, 'set_guided', Trigger.Request(), 15.0)
        self._enable_controller()
        self._fly_to('hold', s.hold, self._source)
        if self.cut_link > 0:
            self._cut_link(self.cut_link)
        if s.follow is not None:
            self._follow(s.follow)
        if s.setpoints or s.landing is not None:
            self._start_onboard()
        for k, sp in enumerate(s.setpoints, 1):
            self._fly_to(f'setpoint {k}', sp, self._source, blind=s.blind if k == 1 else 0.0)
        if s.landing is not None:
            self._land_on_pad(s.landing)
        else:
            self._land()

    def _cut_link(self, seconds: float) -> None:
        """Cut the radio link for `seconds`, noting when the ground's link monitor says the
        vehicle is not heard, and heard again once it is restored."""
        monitor = '/link_monitor_node'
        ev = self.events

        def said(prefix: str, key: str) -> bool:
            if ev.get(key) is None and self.rec.messages.get(monitor, '').startswith(prefix):
                ev[key] = time.time_ns()
            return ev.get(key) is not None

        self.hosts.cut(True)
        ev['link_cut_ns'] = time.time_ns()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._check_alive()
            said('not heard', 'link_reported_ns')
            time.sleep(0.02)
        self.hosts.cut(False)
        ev['link_restored_ns'] = time.time_ns()
        self._wait('the link monitor to hear the vehicle again',
                   lambda: said('heard', 'link_heard_again_ns'), 10.0)

    def _enable_controller(self, on: bool = True) -> None:
        """Enable (disable) the controller once the ROS graph shows it on its pose input."""
        topic = f'{self.ns}/{self.controller_source}/pose'
        self._wait(f'fuzzy_controller_node on {topic}',
                   lambda: topic in self.rec.subscriptions('fuzzy_controller_node'), 30.0)
        self.rec.call(SetBool, 'controller/enable', SetBool.Request(data=on), 5.0,
                      attempts=6)

    def _fresh(self, source: str, max_age: float = 0.5) -> bool:
        latest = self.rec.latest.get(source)
        return latest is not None and time.time_ns() - latest[0] < max_age * 1e9

    def _fly_to(self, name: str, sp: Setpoint, source: str, blind: float = 0.0) -> None:
        """Send `sp`; return once the `source` pose has stayed within its tolerance for
        `sp.hold` s (judged on the poses' stamps). With `blind`, the ground cameras are
        covered for that many seconds from the start, and it returns only once they see."""
        event = SetpointEvent(name, source, (*map(float, sp.position), float(sp.yaw)),
                              time.time_ns())
        self.events['setpoints'].append(event)
        self.rec.set_setpoint(sp.position, sp.yaw)
        covered = blind > 0
        if covered:
            self._cover_ground_cameras(True)
        uncover_at = time.monotonic() + blind

        def held() -> bool:
            nonlocal covered
            if covered and time.monotonic() >= uncover_at:
                self._cover_ground_cameras(False)
                covered = False
            if not self._fresh(source):
                event.settled_ns = None
                return False
            stamp, position, yaw = self.rec.latest[source]
            if not at_setpoint(sp, position, yaw):
                event.settled_ns = None
            elif event.settled_ns is None:
                event.settled_ns = stamp
            elif stamp - event.settled_ns >= sp.hold * 1e9:
                event.reached_ns = stamp
            return event.reached_ns is not None and not covered

        self._wait(f'{name} {sp.position} on {source}/pose', held, sp.timeout)
        event.controller_inputs = self.rec.subscriptions('fuzzy_controller_node')

    def _cover_ground_cameras(self, cover: bool) -> None:
        """Cover (uncover) the simulated ground cameras: no frame, no ground pose."""
        self.rec.call(SetBool, 'ground_cameras/enable', SetBool.Request(data=not cover), 5.0)
        self.events['blind_start_ns' if cover else 'blind_end_ns'] = time.time_ns()

    def _start_onboard(self) -> None:
        """Start homography_pose_node at the hover once every ground station pose of the
        last second is within the hold's tolerance (after a cut link the vehicle flies
        back first), initialised (init.mode pose_topic) at the ground station's pose at
        its first frame's stamp, and wait for its first pose."""
        hold = self.scenario.hold

        def still() -> bool:
            rows = np.array(self.rec.rows['ground'][-90:], dtype=float)
            if not self._fresh('ground') or rows[-1, 0] - rows[0, 0] < 1e9:
                return False
            recent = rows[rows[:, 0] >= rows[-1, 0] - 1e9]
            return at_setpoint(hold, recent[:, 2:5], recent[:, 5])

        self._wait('the vehicle still at the hold on ground/pose', still, hold.timeout)
        self.events['onboard_start_ns'] = time.time_ns()
        self._start('homography_pose_node', 'homography_pose_node', [
            '--params-file', str(self.configs.onboard), '-p', 'init.mode:=pose_topic',
            '-p', 'init.pose_topic:=ground/pose'], on_vehicle=True)
        self._wait('the first onboard/pose', lambda: self._fresh('onboard'), 30.0)

    def _follow(self, follow: Follow) -> None:
        """Start the target tracker and the follower, whose setpoints replace the
        mission's; follow the target for `settle`, then the scored `duration`."""
        c = self.configs
        self._start('target_tracker_node', 'target_tracker_node', [
            '--params-file', str(c.onboard), '-p', 'target.features:=orb',
            '-p', 'target.max_features:=2000'], on_vehicle=True)
        self._start('target_follower_node', 'target_follower_node', [
            '--params-file', str(c.onboard), '-p', f'follow.height:={follow.height:.3f}',
            '-p', f'follow.yaw:={self.scenario.hold.yaw:.5f}'], on_vehicle=True)
        self._wait('the first target/pose', lambda: self._fresh('target'), 30.0)
        self.rec.clear_setpoint()
        self._keep_following(follow.settle, follow.lost_after)
        self.events['follow_start_ns'] = time.time_ns()
        self._keep_following(follow.duration, follow.lost_after)
        self.events['follow_end_ns'] = time.time_ns()
        self.events['follow_inputs'] = {
            node: list(self.rec.subscriptions(node))
            for node in ('fuzzy_controller_node', 'target_follower_node')}

    def _keep_following(self, seconds: float, lost_after: float) -> None:
        """Let the follower fly for `seconds`; MissionError if the target is lost."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._check_alive()
            if not self._fresh('target', lost_after):
                said = '; '.join(f'{name}: {self.rec.messages.get(name, "no diagnostics")}'
                                 for name in ('/target_tracker_node', '/target_follower_node'))
                raise MissionError(f'lost the target: no target/pose for {lost_after:g} s ({said})')
            time.sleep(0.05)

    def _land_on_pad(self, landing: Landing) -> None:
        """Fly over the pad on the onboard pose, descend, then LAND."""
        self._start_controller('onboard')
        yaw = self.rec.latest['onboard'][2]
        over = Setpoint((*landing.pad, landing.approach), yaw, landing.hold, landing.tolerance)
        self._enable_controller()
        self._fly_to('pad approach', over, 'onboard')
        self._fly_to('pad descent', replace(over, position=(*landing.pad, landing.final)),
                     'onboard')
        self._land()

    def _land(self) -> None:
        """Stop servoing, then the autopilot's LAND where the vehicle is."""
        self._enable_controller(False)
        self._land_now()

    def _land_now(self) -> None:
        """LAND, and wait until the autopilot has touched down and disarmed."""
        self.events['land_ns'] = time.time_ns()
        self.rec.call(Trigger, 'land', Trigger.Request(), 15.0)
        self._wait('the vehicle to land and disarm', lambda: self.rec.relay.get('armed') == 'False',
                   30.0)
        self.events['landed_ns'] = time.time_ns()

    def _land_anyway(self) -> None:
        """After a failure in the air: LAND where the vehicle is, best effort."""
        if self.rec.relay.get('armed') != 'True':
            return
        try:
            self._land_now()
        except MissionError:
            pass
