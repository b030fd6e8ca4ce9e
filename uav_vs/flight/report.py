"""What a closed-loop flight recorded, and how well it went against the simulator's truth.

A `FlightLog` holds every pose of the flight by source (the simulator's `truth/pose`,
the ground station's `ground/pose`, the onboard `onboard/pose`, the autopilot's
`autopilot/odom`, the pose filter's `fused/pose`), the velocity commands, the camera
frame stamps and the mission's events; `FlightReport.from_log` scores it:

- each pose source against truth: a vision pose is stamped with its image's stamp, for
  which the simulator published the truth, so they are matched exactly by stamp; the
  autopilot's estimate and the fused one (stamped with the time it is predicted to) are
  compared with truth interpolated at their stamps; and every source against the truth
  at the time each pose arrived ("as received": what the controller had then, latency
  included, the figure that compares the filter with the sources it fuses);
- each setpoint (section 5: hold, move through setpoints): the true distance to it
  over the hold the mission accepted, as judged by the vision pose it flew on;
- the landing: the true touchdown point's horizontal distance to the pad;
- the ground cameras covered mid-flight: the fused estimate against the truth between
  the last ground pose before and the first after;
- following a moving target: the vehicle's true horizontal distance to the target's
  true centre over the scored span, and the vision estimate of the target (target/pose)
  against its truth (both stamped with the onboard image's stamp);
- latencies: a vision pose's arrival at the recorder minus its image's stamp, and a
  command's (cmd_vel computed from a vision pose carries its image's stamp) the same.

No ROS here: the runner (uav_vs.flight.scenario) fills the log, `save` / `load` keep it as .npz.
"""
import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from uav_vs.autopilot.frames import wrap_angle

SOURCES = ('ground', 'onboard', 'odom', 'fused')
TRACKS = ('truth', *SOURCES, 'target_truth', 'target')     # the PoseTracks of a FlightLog
LABELS = {'truth': 'simulator truth', 'ground': 'ground/pose (trinocular, section 3)',
          'onboard': 'onboard/pose (homography, section 4)',
          'odom': 'autopilot/odom (autopilot estimate)',
          'fused': 'fused/pose (pose filter of ground, onboard, autopilot/odom)'}
# Scored against the truth at their own stamps (image stamps); the others interpolated.
EXACT = ('ground', 'onboard')


class _Track:
    """Columns of a topic's messages in arrival order: header stamps, arrival times (ns), a
    3-vector and a scalar per message."""

    @classmethod
    def from_rows(cls, rows: list[tuple[int, int, float, float, float, float]]):
        """From (stamp_ns, received_ns, x, y, z, scalar) rows, in stamp order (two
        publishers' rows may come interleaved)."""
        if not rows:
            return cls()
        a = np.array(sorted(rows, key=lambda row: row[0]), dtype=object)
        return cls(a[:, 0].astype(np.int64), a[:, 1].astype(np.int64),
                   a[:, 2:5].astype(float), a[:, 5].astype(float))

    def __len__(self) -> int:
        return len(self.stamps)


@dataclass
class PoseTrack(_Track):
    """Poses: positions (n, 3) in world ENU, m, and yaws (n,), rad."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    received: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    yaws: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class CommandTrack(_Track):
    """cmd_vel as published: linear (n, 3), m/s, yaw rate (n,), rad/s. A command computed
    from a pose carries that pose's stamp."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    received: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    linear: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    yaw_rate: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class SetpointEvent:
    """One setpoint the mission flew to: what, on which pose, and when (ns, ROS time).

    `settled_ns` is when the vision pose entered the tolerance for good, `reached_ns`
    when it had stayed there for the hold; both are None if it timed out."""

    name: str
    source: str                      # 'ground' or 'onboard': the controller's pose input
    target: tuple[float, float, float, float]   # x, y, z (m, world ENU), yaw (rad)
    start_ns: int
    settled_ns: int | None = None
    reached_ns: int | None = None
    controller_inputs: tuple[str, ...] = ()    # topics the controller subscribed to then


@dataclass
class FlightLog:
    """Everything one closed-loop flight recorded."""

    scenario: str
    truth: PoseTrack
    ground: PoseTrack
    onboard: PoseTrack
    odom: PoseTrack
    commands: CommandTrack
    ground_frames: np.ndarray        # stamps of the ground frame sets, ns
    onboard_frames: np.ndarray       # stamps of the onboard frames, ns
    setpoints: list[SetpointEvent]
    pad: tuple[float, float] | None  # landing pad x, y in world, m
    takeoff_ns: int | None = None    # the takeoff command
    onboard_start_ns: int | None = None   # homography_pose_node started
    land_ns: int | None = None       # the LAND command
    landed_ns: int | None = None     # the autopilot reported disarmed after landing
    failure: str = ''                # why the mission stopped early; '' if it completed
    exit_codes: dict[str, int] = field(default_factory=dict)  # of every process, at the end
    failed_logs: dict[str, str] = field(default_factory=dict)  # log ends of those not 0
    # The autopilot's EKF_STATUS_REPORT as the relay's diagnostics gave it, one row each:
    # received (ns), flags, velocity / horizontal position / height test ratios, navigating
    # (0 or 1: absolute horizontal position, not the constant-position fallback), GPS fix
    # type (-1: none reported). Empty from an autopilot without the report (PX4).
    ekf: list[list[float]] = field(default_factory=list)
    # Following a target: its truth (truth/target) and vision estimate (target/pose), both
    # on the ground (z = 0), yaw its heading; the span scored (the vehicle had caught up).
    target_truth: PoseTrack = field(default_factory=PoseTrack)
    target: PoseTrack = field(default_factory=PoseTrack)
    # The pose filter's estimate (fused/pose), stamped with the time it is predicted to.
    fused: PoseTrack = field(default_factory=PoseTrack)
    follow_start_ns: int | None = None
    follow_end_ns: int | None = None
    # The topics the controller and the follower subscribed to while following, by node.
    follow_inputs: dict[str, list[str]] = field(default_factory=dict)
    # Two hosts, the radio link cut mid-flight: cut and restored; the ground's
    # link_monitor_node first said "not heard", then "heard" again (its diagnostics' receipt).
    link_cut_ns: int | None = None
    link_restored_ns: int | None = None
    link_reported_ns: int | None = None
    link_heard_again_ns: int | None = None
    # The ground cameras covered mid-flight (Scenario.blind): covered, uncovered.
    blind_start_ns: int | None = None
    blind_end_ns: int | None = None
    # CPU time of the graph's processes (and the mission's) by host, s: 'ground', 'air';
    # over run_s s from the graph's start to its stop.
    cpu_s: dict[str, float] = field(default_factory=dict)
    run_s: float = math.nan

    def save(self, path: Path) -> None:
        arrays = {f'{name}.{key}': value for name in TRACKS
                  for key, value in asdict(getattr(self, name)).items()}
        arrays.update({f'commands.{k}': v for k, v in asdict(self.commands).items()})
        meta = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in
                (*TRACKS, 'commands', 'ground_frames', 'onboard_frames')}
        meta['setpoints'] = [asdict(event) for event in self.setpoints]
        np.savez_compressed(path, ground_frames=self.ground_frames,
                            onboard_frames=self.onboard_frames, meta=json.dumps(meta), **arrays)

    @classmethod
    def load(cls, path: Path) -> 'FlightLog':
        with np.load(path) as z:
            tracks = {name: PoseTrack(*(z[f'{name}.{k}'] for k in
                                        ('stamps', 'received', 'positions', 'yaws')))
                      for name in TRACKS if f'{name}.stamps' in z}
            commands = CommandTrack(*(z[f'commands.{k}'] for k in
                                      ('stamps', 'received', 'linear', 'yaw_rate')))
            meta = json.loads(str(z['meta']))
            frames = z['ground_frames'], z['onboard_frames']
        meta['setpoints'] = [SetpointEvent(**{**s, 'target': tuple(s['target']),
                                              'controller_inputs': tuple(s['controller_inputs'])})
                             for s in meta['setpoints']]
        meta['pad'] = tuple(meta['pad']) if meta['pad'] is not None else None
        return cls(commands=commands, ground_frames=frames[0], onboard_frames=frames[1],
                   **tracks, **meta)


@dataclass(frozen=True)
class SourceScore:
    """One pose source against truth."""

    samples: int
    position_rmse_m: float
    position_max_m: float
    yaw_rmse_deg: float
    latency_median_ms: float         # arrival minus stamp
    latency_p95_ms: float
    # Each pose against the truth at the time it arrived: what a consumer (the controller)
    # had then, its latency included.
    arrival_rmse_m: float = math.nan


@dataclass(frozen=True)
class SetpointScore:
    name: str
    source: str
    target: tuple[float, float, float, float]
    reached: bool
    settle_s: float                  # command to settled (by the vision pose)
    error_rms_m: float               # true distance to the target over the hold
    error_max_m: float
    error_end_m: float               # ... when the hold was accepted
    yaw_error_max_deg: float


@dataclass(frozen=True)
class LandingScore:
    pad: tuple[float, float]
    touchdown: tuple[float, float, float]  # true position after landing, m
    error_m: float                   # horizontal distance from the pad


@dataclass(frozen=True)
class CommandScore:
    """cmd_vel computed from a vision pose (stamped with its image's stamp): how long from
    the image's stamp to the command's arrival, the whole graph's latency."""

    commands: int                    # all cmd_vel received
    from_images: int                 # camera frames a command was computed from
    latency_median_ms: float
    latency_p95_ms: float


@dataclass(frozen=True)
class EkfScore:
    """What the autopilot's EKF said over the flight (takeoff command to landed)."""

    reports: int
    flags: tuple[int, ...]           # every flag word seen, in order of appearance
    navigating: bool                 # in every report
    velocity_ratio_max: float        # innovation test ratios (1 = the gate)
    pos_horiz_ratio_max: float
    pos_vert_ratio_max: float
    gps_fix_max: int                 # -1: no GPS_RAW_INT


@dataclass(frozen=True)
class FollowScore:
    """Following the target over the scored span (section 5)."""

    duration_s: float
    samples: int                     # onboard frames with both truths
    error_rms_m: float               # vehicle to target, horizontal, true positions
    error_max_m: float
    estimates: int                   # target/pose matched with the truth of its stamp
    estimate_rmse_m: float           # target/pose against truth/target
    heading_rmse_deg: float


@dataclass(frozen=True)
class BlindScore:
    """The ground cameras covered mid-flight, and the fused estimate meanwhile."""
    covered_s: float                 # from covering the cameras to uncovering them
    ground_gap_s: float              # stamps of the last ground pose before, first after
    fused_samples: int               # fused poses stamped in that gap
    fused_gap_s: float               # the longest time between two of them (and the ends)
    fused_max_m: float               # their largest error against the truth
    fused_rms_m: float


@dataclass(frozen=True)
class FlightReport:
    scenario: str
    sources: dict[str, SourceScore]
    commands: CommandScore
    setpoints: list[SetpointScore]
    landing: LandingScore | None
    ground_frames: int
    onboard_frames: int
    duration_s: float                # takeoff command to landed (or the end of the log)
    window: str                      # what the sources were scored over
    failure: str
    exit_codes: dict[str, int]       # of every process of the graph
    failed_logs: dict[str, str]      # the end of the log of each whose status was not 0
    ekf: EkfScore | None = None      # None without EKF_STATUS_REPORT in the window
    follow: FollowScore | None = None   # None unless the mission followed a target
    blind: BlindScore | None = None     # None unless the ground cameras were covered

    @classmethod
    def from_log(cls, log: FlightLog) -> 'FlightReport':
        windows = {name: flight_window(log, name) for name in SOURCES}
        sources = {name: score_source(getattr(log, name), log.truth, name in EXACT,
                                      *windows[name]) for name in SOURCES}
        frames = {name: int(((stamps >= windows[name][0]) & (stamps <= windows[name][1])).sum())
                  for name, stamps in (('ground', log.ground_frames),
                                       ('onboard', log.onboard_frames))}
        setpoints = [score_setpoint(event, log) for event in log.setpoints]
        landing = None
        if log.pad is not None and log.landed_ns is not None and len(log.truth):
            after = log.truth.stamps >= log.landed_ns
            p = log.truth.positions[np.flatnonzero(after)[0] if after.any() else -1]
            landing = LandingScore(log.pad, tuple(map(float, p)),
                                   float(math.hypot(p[0] - log.pad[0], p[1] - log.pad[1])))
        start = log.takeoff_ns or (int(log.truth.stamps[0]) if len(log.truth) else 0)
        end = log.landed_ns or (int(log.truth.stamps[-1]) if len(log.truth) else start)
        window = 'takeoff to LAND' if log.takeoff_ns is not None else 'the whole log'
        return cls(log.scenario, sources, score_commands(log), setpoints, landing,
                   frames['ground'], frames['onboard'], (end - start) * 1e-9, window,
                   log.failure, log.exit_codes, log.failed_logs, score_ekf(log.ekf, start, end),
                   score_follow(log), score_blind(log))

    def summary(self) -> str:
        lines = [f'scenario {self.scenario}: ' + (f'FAILED: {self.failure}' if self.failure
                                                  else f'completed in {self.duration_s:.1f} s')]
        frames = {'ground': self.ground_frames, 'onboard': self.onboard_frames}
        lines.append(f'pose sources against simulator truth ({self.window}):')
        for name, s in self.sources.items():
            if not s.samples:
                if name != 'fused':     # none without a pose filter in the graph
                    lines.append(f'  {name:8s} no samples')
                continue
            rate = f' from {frames[name]} frames' if name in frames else ''
            latency = (f', latency median {s.latency_median_ms:.1f} ms, '
                       f'p95 {s.latency_p95_ms:.1f} ms' if name in frames else '')
            lines.append(f'  {name:8s} {s.samples} poses{rate}: position RMSE '
                         f'{s.position_rmse_m * 100:.2f} cm (max {s.position_max_m * 100:.2f} cm),'
                         f' as received {s.arrival_rmse_m * 100:.2f} cm,'
                         f' yaw RMSE {s.yaw_rmse_deg:.2f} deg{latency}')
        c = self.commands
        if c.from_images:
            lines.append(f'cmd_vel: {c.commands} commands, from the vision poses of '
                         f'{c.from_images} frames; image stamp to command: median '
                         f'{c.latency_median_ms:.1f} ms, p95 {c.latency_p95_ms:.1f} ms')
        if self.setpoints:
            lines.append('setpoints (true error over the hold):')
        for s in self.setpoints:
            x, y, z, yaw = s.target
            where = f'({x:+.2f}, {y:+.2f}, {z:.2f}) m, yaw {math.degrees(yaw):.0f} deg'
            if not s.reached:
                lines.append(f'  {s.name:14s} {where} on {s.source}: NOT REACHED')
                continue
            lines.append(f'  {s.name:14s} {where} on {s.source}: settled in {s.settle_s:.1f} s;'
                         f' error {s.error_end_m * 100:.1f} cm at the end, RMS '
                         f'{s.error_rms_m * 100:.1f} cm, max {s.error_max_m * 100:.1f} cm, '
                         f'yaw max {s.yaw_error_max_deg:.1f} deg')
        if (e := self.ekf) is not None:
            said = 'navigating in every report' if e.navigating else 'NOT navigating in some'
            gps = 'no GPS fix' if e.gps_fix_max < 2 else f'GPS fix type up to {e.gps_fix_max}'
            lines.append(f'autopilot EKF over the flight: {e.reports} reports, flags '
                         f"{', '.join(f'0x{f:x}' for f in e.flags)}, {said}; largest test "
                         f'ratios velocity {e.velocity_ratio_max:.2f}, position '
                         f'{e.pos_horiz_ratio_max:.2f}, height {e.pos_vert_ratio_max:.2f} '
                         f'(gate 1); {gps}')
        if (f := self.follow) is not None:
            lines.append(f'follow: target followed for {f.duration_s:.1f} s ({f.samples} '
                         f'frames): true distance RMS {f.error_rms_m * 100:.1f} cm, max '
                         f'{f.error_max_m * 100:.1f} cm; target/pose ({f.estimates}) against '
                         f'truth: RMSE {f.estimate_rmse_m * 100:.2f} cm, heading '
                         f'{f.heading_rmse_deg:.2f} deg')
        if (b := self.blind) is not None:
            lines.append(f'ground cameras covered {b.covered_s:.1f} s (no ground pose for '
                         f'{b.ground_gap_s:.1f} s): fused {b.fused_samples} poses meanwhile '
                         f'(at most {b.fused_gap_s * 1e3:.0f} ms apart), '
                         f'error max {b.fused_max_m * 100:.1f} cm, RMS '
                         f'{b.fused_rms_m * 100:.1f} cm')
        if self.landing is not None:
            x, y, _ = self.landing.touchdown
            lines.append(f'landing: touchdown at ({x:+.3f}, {y:+.3f}) m, '
                         f'{self.landing.error_m * 100:.1f} cm from the pad at '
                         f'({self.landing.pad[0]:+.2f}, {self.landing.pad[1]:+.2f}) m')
        bad = {label: code for label, code in self.exit_codes.items() if code != 0}
        if bad:
            lines.append(f'exit status other than 0 when stopped: {bad}')
            lines.extend('  ' + line for tail in self.failed_logs.values()
                         for line in tail.splitlines())
        return '\n'.join(lines)


def score_follow(log: FlightLog) -> FollowScore | None:
    """The vehicle's true horizontal distance to the target's true centre at each onboard
    frame stamped in [follow_start_ns, follow_end_ns], and the vision estimate against
    the truth of its stamp; None if the mission did not follow a target."""
    start, end = log.follow_start_ns, log.follow_end_ns
    if start is None or end is None:
        return None
    target, truth = log.target_truth, log.truth
    keep, rows = same_stamps(target, truth, (target.stamps >= start) & (target.stamps <= end))
    error = np.linalg.norm(truth.positions[rows, :2] - target.positions[keep, :2], axis=1)
    estimated, rows = same_stamps(log.target, target, (log.target.stamps >= start)
                                  & (log.target.stamps <= end))
    miss = np.linalg.norm(log.target.positions[estimated, :2] - target.positions[rows, :2],
                          axis=1)
    heading = np.degrees(wrap_angle(log.target.yaws[estimated] - target.yaws[rows]))
    return FollowScore((end - start) * 1e-9, int(keep.sum()), rms(error),
                       float(error.max()) if len(error) else math.nan, int(estimated.sum()),
                       rms(miss), rms(heading))


def score_ekf(rows: list[list[float]], start_ns: int, end_ns: int) -> EkfScore | None:
    """The EKF reports received in [start_ns, end_ns] (FlightLog.ekf), None if none."""
    a = np.array([r for r in rows if start_ns <= r[0] <= end_ns], dtype=float).reshape(-1, 7)
    if not len(a):
        return None
    flags = tuple(dict.fromkeys(int(f) for f in a[:, 1]))
    return EkfScore(len(a), flags, bool(a[:, 5].all()), float(a[:, 2].max()),
                    float(a[:, 3].max()), float(a[:, 4].max()), int(a[:, 6].max()))


def flight_window(log: FlightLog, source: str) -> tuple[int, int]:
    """Stamps (ns) over which a pose source is scored: from the takeoff command (the
    onboard pose: from its first pose) to the LAND command (or the end of the log)."""
    track = getattr(log, source)
    start = log.takeoff_ns if log.takeoff_ns is not None else 0
    if source == 'onboard' and len(track):
        start = max(start, int(track.stamps[0]))
    end = log.land_ns if log.land_ns is not None else np.iinfo(np.int64).max
    return start, end


def score_source(track: PoseTrack, truth: PoseTrack, exact: bool, start_ns: int,
                 end_ns: int) -> SourceScore:
    """Errors against truth of `track`'s poses stamped in [start_ns, end_ns]: matched
    with the truth of the same stamp (`exact`) or interpolated."""
    keep = (track.stamps >= start_ns) & (track.stamps <= end_ns)
    if exact:
        keep, rows = same_stamps(track, truth, keep)
        true_p, true_yaw = truth.positions[rows], truth.yaws[rows]
    else:
        keep &= within(truth, track.stamps)
        true_p, true_yaw = interpolate(truth, track.stamps[keep])
    if not keep.any():
        nan = math.nan
        return SourceScore(0, nan, nan, nan, nan, nan, nan)
    dp = np.linalg.norm(track.positions[keep] - true_p, axis=1)
    dyaw = np.degrees(wrap_angle(track.yaws[keep] - true_yaw))
    latency = (track.received[keep] - track.stamps[keep]) * 1e-6
    arrived = keep & within(truth, track.received)
    then, _ = interpolate(truth, track.received[arrived])
    arrival = rms(np.linalg.norm(track.positions[arrived] - then, axis=1)) if arrived.any() \
        else math.nan
    return SourceScore(int(keep.sum()), rms(dp), float(dp.max()), rms(dyaw),
                       float(np.median(latency)), float(np.percentile(latency, 95)), arrival)


def command_latencies(log: FlightLog, source: str | None = None) -> np.ndarray:
    """Arrival minus stamp (ms) of the first command stamped with each camera frame's
    stamp: the one computed from that frame's vision pose (the controller's timer may
    send it again, with the same stamp, until the next pose). `source` 'ground' or
    'onboard' keeps the commands of that camera's frames only."""
    frames = {'ground': log.ground_frames, 'onboard': log.onboard_frames}
    c = log.commands
    from_images = np.isin(c.stamps, np.concatenate(
        [frames[source]] if source else list(frames.values())))
    stamps, index = np.unique(c.stamps[from_images], return_inverse=True)
    first = np.full(len(stamps), np.iinfo(np.int64).max)
    np.minimum.at(first, index, c.received[from_images])
    return (first - stamps) * 1e-6


def score_commands(log: FlightLog) -> CommandScore:
    latency = command_latencies(log)
    if not len(latency):
        return CommandScore(len(log.commands.stamps), 0, math.nan, math.nan)
    return CommandScore(len(log.commands.stamps), len(latency), float(np.median(latency)),
                        float(np.percentile(latency, 95)))


def score_setpoint(event: SetpointEvent, log: FlightLog) -> SetpointScore:
    """The true error over the hold window [settled, reached] of one setpoint."""
    nan = math.nan
    if event.reached_ns is None or event.settled_ns is None:
        return SetpointScore(event.name, event.source, event.target, False, nan, nan, nan, nan,
                             nan)
    t = log.truth
    window = (t.stamps >= event.settled_ns) & (t.stamps <= event.reached_ns)
    target = np.array(event.target)
    dp = np.linalg.norm(t.positions[window] - target[:3], axis=1)
    dyaw = np.degrees(np.abs(wrap_angle(t.yaws[window] - target[3])))
    settle = max(0.0, (event.settled_ns - event.start_ns) * 1e-9)
    if not len(dp):
        return SetpointScore(event.name, event.source, event.target, True, settle, nan, nan, nan,
                             nan)
    return SetpointScore(event.name, event.source, event.target, True, settle, rms(dp),
                         float(dp.max()), float(dp[-1]), float(dyaw.max()))


def same_stamps(track: PoseTrack, truth: PoseTrack, keep: np.ndarray
                ) -> tuple[np.ndarray, list[int]]:
    """`keep` narrowed to the samples of `track` whose stamp `truth` has too, and the
    rows of `truth` with those stamps, in the same order."""
    index = {int(s): i for i, s in enumerate(truth.stamps)}
    keep = keep & np.array([int(s) in index for s in track.stamps], bool)
    return keep, [index[int(s)] for s in track.stamps[keep]]


def within(track: PoseTrack, stamps: np.ndarray) -> np.ndarray:
    """Which `stamps` lie inside `track`'s span, where it can be interpolated."""
    if not len(track):
        return np.zeros(len(stamps), bool)
    return (stamps >= track.stamps[0]) & (stamps <= track.stamps[-1])


def score_blind(log: FlightLog) -> BlindScore | None:
    """The fused poses stamped between the last ground pose before the cameras were
    covered and the first after, against the truth interpolated at their stamps; None
    if the cameras were not covered or no ground pose followed."""
    start, end = log.blind_start_ns, log.blind_end_ns
    ground = log.ground.stamps
    if start is None or end is None or not (ground > end).any() or not (ground < start).any():
        return None
    last = int(ground[ground < start].max())     # the cameras were covered before `start`
    first = int(ground[ground > last].min())      # none lies in between: the covered frames
    fused = log.fused
    keep = (fused.stamps >= last) & (fused.stamps <= first) & within(log.truth, fused.stamps)
    error = np.zeros(0)
    if keep.any():
        true_p, _ = interpolate(log.truth, fused.stamps[keep])
        error = np.linalg.norm(fused.positions[keep] - true_p, axis=1)
    gap = np.diff(np.concatenate([[last], fused.stamps[keep], [first]])).max() * 1e-9
    return BlindScore((end - start) * 1e-9, (first - last) * 1e-9, int(keep.sum()),
                      float(gap), float(error.max()) if len(error) else math.nan, rms(error))


@dataclass(frozen=True)
class LinkCutScore:
    """The radio link cut mid-flight, as each side saw it."""
    cut_s: float                     # how long the link was cut
    reported_after_s: float          # the ground's link monitor said "not heard" (nan: never)
    heard_again_after_s: float       # ... and "heard" once the link was back
    command_gap_s: float             # the longest time without cmd_vel on the vehicle
    drift_m: float                   # how far the vehicle moved from the cut to the restore


def score_link_cut(log: FlightLog, vehicle_commands: CommandTrack) -> LinkCutScore | None:
    """The link cut of `log`, with the commands the vehicle received (its own recording)."""
    if log.link_cut_ns is None or log.link_restored_ns is None:
        return None
    cut, back = log.link_cut_ns, log.link_restored_ns

    def after(ns: int | None, since: int) -> float:
        return math.nan if ns is None else (ns - since) * 1e-9

    arrivals = np.sort(vehicle_commands.received)
    near = arrivals[(arrivals >= cut - 1e9) & (arrivals <= back + 1e9)]
    gap = float(np.diff(near).max()) * 1e-9 if len(near) > 1 else math.nan
    truth = log.truth
    during = (truth.stamps >= cut) & (truth.stamps <= back)
    drift = math.nan
    if during.any():
        p = truth.positions[during]
        drift = float(np.linalg.norm(p - p[0], axis=1).max())
    return LinkCutScore((back - cut) * 1e-9, after(log.link_reported_ns, cut),
                        after(log.link_heard_again_ns, back), gap, drift)


def interpolate(track: PoseTrack, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions and yaws of `track` linearly interpolated at `stamps` (yaw unwrapped)."""
    t = (track.stamps - track.stamps[0]) * 1e-9
    q = (np.asarray(stamps) - track.stamps[0]) * 1e-9
    positions = np.column_stack([np.interp(q, t, track.positions[:, k]) for k in range(3)])
    return positions, np.interp(q, t, np.unwrap(track.yaws))


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if len(a) else math.nan
