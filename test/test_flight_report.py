"""FlightReport scores a flight log exactly: pose errors by stamp, interpolated odometry,
command latencies from the image stamps they carry, setpoint holds; the log survives
save/load. Truth is the synthetic log built here."""
import math

import numpy as np
import pytest

from uav_vs import graph
from uav_vs.flight.report import (CommandTrack, FlightLog, FlightReport, PoseTrack,
                                  SetpointEvent, command_latencies)

MS = 1_000_000
T0 = 1_700_000_000 * 10**9


def track(stamps, positions, yaws, latency_ms=0.0) -> PoseTrack:
    stamps = np.asarray(stamps, np.int64)
    return PoseTrack(stamps, stamps + int(latency_ms * MS), np.asarray(positions, float),
                     np.asarray(yaws, float))


def make_log() -> FlightLog:
    frames = T0 + np.arange(50, dtype=np.int64) * 100 * MS          # 10 Hz, 5 s
    t = (frames - T0) * 1e-9
    truth_p = np.column_stack([t, 0.5 * t, np.full_like(t, 1.5)])
    truth = track(frames, truth_p, 0.1 * t)
    ground = track(frames, truth_p + [0.03, 0.0, 0.04], 0.1 * t + math.radians(2.0), 20.0)
    odom_stamps = frames[:-1] + 50 * MS                               # between the frames
    odom_t = (odom_stamps - T0) * 1e-9
    odom = track(odom_stamps, np.column_stack([odom_t, 0.5 * odom_t, np.full_like(odom_t, 1.5)]),
                 0.1 * odom_t)
    # Commands: one per frame (latency 30 + k ms), the timer's re-send of it (same stamp,
    # later) and timer ones stamped in between.
    k = np.arange(len(frames))
    stamps = np.concatenate([frames, frames, frames + 7 * MS])
    received = np.concatenate([frames + (30 + k) * MS, frames + (90 + k) * MS, frames + 8 * MS])
    commands = CommandTrack(stamps, received, np.zeros((len(stamps), 3)), np.zeros(len(stamps)))
    hold = SetpointEvent('hold', 'ground', (2.0, 1.0, 1.5, 0.2), int(frames[10]),
                         settled_ns=int(frames[20]), reached_ns=int(frames[30]))
    return FlightLog('synthetic', truth, ground, PoseTrack(), odom, commands, frames,
                     np.zeros(0, np.int64), [hold], pad=None, takeoff_ns=int(frames[0]))


def test_sources_commands_and_setpoints_are_scored_exactly():
    log = make_log()
    report = FlightReport.from_log(log)
    ground = report.sources['ground']
    assert ground.samples == 50
    assert ground.position_rmse_m == pytest.approx(0.05, abs=1e-12)      # |(0.03, 0, 0.04)|
    assert ground.yaw_rmse_deg == pytest.approx(2.0, abs=1e-9)
    assert ground.latency_median_ms == pytest.approx(20.0)
    odom = report.sources['odom']          # on the truth's straight line: interpolation exact
    assert odom.samples == 49 and odom.position_rmse_m < 1e-9 and odom.yaw_rmse_deg < 1e-9
    assert report.sources['onboard'].samples == 0
    # As received: the vehicle moved on at (1, 0.5, 0) m/s during the ground pose's 20 ms;
    # the odometry arrived as stamped (the last one, past the truth, is left out).
    moved = np.array([0.03, 0.0, 0.04]) - 0.020 * np.array([1.0, 0.5, 0.0])
    assert ground.arrival_rmse_m == pytest.approx(np.linalg.norm(moved), abs=1e-9)
    assert odom.arrival_rmse_m < 1e-9
    log.fused = track(log.odom.stamps, log.odom.positions + [0.0, 0.0, 0.02], log.odom.yaws)
    fused = FlightReport.from_log(log).sources['fused']
    assert fused.samples == 49 and fused.position_rmse_m == pytest.approx(0.02, abs=1e-9)

    latency = command_latencies(log)      # the first command that carries each frame's stamp
    np.testing.assert_allclose(latency, 30.0 + np.arange(50))
    np.testing.assert_allclose(command_latencies(log, 'ground'), latency)
    assert len(command_latencies(log, 'onboard')) == 0      # no onboard frame in this log
    assert report.commands.commands == 150 and report.commands.from_images == 50
    assert report.commands.latency_median_ms == pytest.approx(54.5)
    assert report.commands.latency_p95_ms == pytest.approx(np.percentile(30.0 + np.arange(50), 95))

    (hold,) = report.setpoints
    t = np.arange(20, 31) * 0.1          # truth over the hold, against (2, 1, 1.5)
    dist = np.hypot(t - 2.0, 0.5 * t - 1.0)
    assert hold.reached and hold.settle_s == pytest.approx(1.0)
    assert hold.error_max_m == pytest.approx(dist.max()) and hold.error_end_m == pytest.approx(dist[-1])
    assert 'image stamp to command: median 54.5 ms' in report.summary()


def test_save_and_load_keep_everything(tmp_path):
    log = make_log()
    log.save(tmp_path / 'flight.npz')
    back = FlightLog.load(tmp_path / 'flight.npz')
    for name in ('truth', 'ground', 'onboard', 'odom', 'commands'):
        a, b = getattr(log, name), getattr(back, name)
        for field in vars(a):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=name)
    assert back.setpoints == log.setpoints and back.takeoff_ns == log.takeoff_ns
    assert FlightReport.from_log(back) == FlightReport.from_log(log)


def test_the_ekf_reports_of_the_flight_are_summed_up_and_kept(tmp_path):
    """Only the reports from the takeoff command to landed count; one without an absolute
    horizontal position is a fallback."""
    log = make_log()
    start, end = log.takeoff_ns, log.takeoff_ns + 5 * 10**9
    log.landed_ns = end
    row = lambda t, flags, posh, nav: [t, flags, 0.1, posh, 0.05, nav, 0]   # noqa: E731
    log.ekf = [row(start - 10**9, 0xa5, 0.0, 0),                  # before takeoff: ignored
               row(start + 10**9, 0x33f, 0.2, 1), row(start + 3 * 10**9, 0x33f, 0.4, 1),
               row(end + 10**9, 0xa5, 5.0, 0)]                   # after landing: ignored
    ekf = FlightReport.from_log(log).ekf
    assert (ekf.reports, ekf.flags, ekf.navigating) == (2, (0x33f,), True)
    assert (ekf.velocity_ratio_max, ekf.pos_horiz_ratio_max, ekf.gps_fix_max) == (0.1, 0.4, 0)
    assert ('autopilot EKF over the flight: 2 reports, flags 0x33f, navigating in every '
            'report; largest test ratios velocity 0.10, position 0.40, height 0.05 (gate 1); '
            'no GPS fix') in FlightReport.from_log(log).summary()
    log.ekf.insert(2, row(start + 2 * 10**9, 0xa7, 0.3, 0))       # constant position mode
    ekf = FlightReport.from_log(log).ekf
    assert ekf.flags == (0x33f, 0xa7) and not ekf.navigating
    log.save(tmp_path / 'flight.npz')
    assert FlightLog.load(tmp_path / 'flight.npz').ekf == log.ekf
    assert FlightReport.from_log(make_log()).ekf is None             # PX4: no reports


def test_a_process_that_failed_is_reported_with_the_end_of_its_log(tmp_path):
    procs = {'ok': graph.start('python', [], tmp_path, 'ok', args=['-c', 'print("fine")']),
             'bad': graph.start('python', [], tmp_path, 'bad', args=[
                 '-c', 'print("\\n".join(map(str, range(40)))); raise SystemExit("why: 39")'])}
    for proc in procs.values():
        proc.wait(30)
    log = make_log()
    log.exit_codes = dict(zip(procs, graph.stop(list(procs.values()))))
    log.failed_logs = graph.failed_logs(procs, lines=3)
    summary = FlightReport.from_log(log).summary().splitlines()
    assert log.exit_codes == {'ok': 0, 'bad': 1}
    assert summary[-5:] == ["exit status other than 0 when stopped: {'bad': 1}",
                            f'  {tmp_path / "bad.log"}:', '  38', '  39', '  why: 39']


def test_following_is_scored_on_both_truths_and_kept(tmp_path):
    """The vehicle 3 cm east and 4 cm north of the target (5 cm) over the scored frames,
    the estimate 1 cm off and 2 degrees; frames outside the span are not scored."""
    log = make_log()
    frames = log.truth.stamps
    t = (frames - T0) * 1e-9
    target_p = log.truth.positions - [0.03, 0.04, 1.5]
    target_p[:5] += 10.0                      # before the span: far away, not scored
    log.target_truth = track(frames, target_p, 0.3 * t)
    log.target = track(frames[::2], target_p[::2] + [0.0, 0.01, 0.0],
                       0.3 * t[::2] + math.radians(2.0))
    log.follow_start_ns, log.follow_end_ns = int(frames[5]), int(frames[45])
    log.follow_inputs = {'target_follower_node': ['/ground/pose', '/onboard/target']}
    follow = FlightReport.from_log(log).follow
    assert follow.duration_s == pytest.approx(4.0) and follow.samples == 41
    assert follow.error_rms_m == pytest.approx(0.05) and follow.error_max_m == pytest.approx(0.05)
    assert follow.estimates == 20 and follow.estimate_rmse_m == pytest.approx(0.01)
    assert follow.heading_rmse_deg == pytest.approx(2.0)
    assert 'true distance RMS 5.0 cm' in FlightReport.from_log(log).summary()
    log.save(tmp_path / 'flight.npz')
    loaded = FlightLog.load(tmp_path / 'flight.npz')
    assert FlightReport.from_log(loaded).follow == follow
    assert loaded.follow_inputs == log.follow_inputs
    assert FlightReport.from_log(make_log()).follow is None


def test_the_fused_estimate_is_scored_while_the_ground_cameras_are_covered(tmp_path):
    """Ground poses every 0.1 s but while the cameras were covered, the first after them
    before the mission knew they were uncovered; the fused estimate every 20 ms, 2 cm off
    the truth but for one pose 6 cm off inside the gap and one 50 cm off outside it."""
    log = make_log()
    frames = log.truth.stamps
    seen = (frames <= frames[15]) | (frames >= frames[31])
    stamps = np.append(frames[seen], frames[30] + 60 * MS)           # 1.56 s without a pose
    order = np.argsort(stamps)
    log.ground = track(stamps[order], np.zeros((len(stamps), 3)), np.zeros(len(stamps)))
    log.blind_start_ns, log.blind_end_ns = int(frames[15] + 10 * MS), int(frames[30] + 80 * MS)
    stamps = T0 + np.arange(0, 4900, 20, dtype=np.int64) * MS
    t = (stamps - T0) * 1e-9
    positions = np.column_stack([t, 0.5 * t + 0.02, np.full_like(t, 1.5)])
    positions[np.searchsorted(stamps, frames[20])] += [0.0, 0.04, 0.0]     # 6 cm
    positions[np.searchsorted(stamps, frames[40])] += [0.5, 0.0, 0.0]     # after: not scored
    log.fused = track(stamps, positions, 0.1 * t)
    blind = FlightReport.from_log(log).blind
    assert blind.covered_s == pytest.approx(1.57)
    assert blind.ground_gap_s == pytest.approx(1.56)
    assert blind.fused_samples == 79 and blind.fused_gap_s == pytest.approx(0.02)
    assert blind.fused_max_m == pytest.approx(0.06)
    assert blind.fused_rms_m == pytest.approx(math.sqrt((78 * 0.02**2 + 0.06**2) / 79))
    assert 'no ground pose for 1.6 s' in FlightReport.from_log(log).summary()
    log.save(tmp_path / 'flight.npz')
    assert FlightReport.from_log(FlightLog.load(tmp_path / 'flight.npz')).blind == blind
    assert FlightReport.from_log(make_log()).blind is None
