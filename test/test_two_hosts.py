"""The closed loop on two hosts over a radio link (uav_vs.sim.radio_link), as the chapter's
ground station and vehicle: `python -m uav_vs.demo --hosts 2`.

The ground cameras, station, controller (on the ground pose) and the mission on one
network namespace; the vehicle, its onboard camera and nodes, the controller (on the
onboard pose) and the relay on another; between them a link of
20 +- 10 ms and 2 % loss made in user space, and DDS discovery by static peers; once
the vehicle holds, the link is cut for 3 s. Judged on the simulator's truth (the hold,
the vehicle still while cut off), on what the link's forwarder says it carried (only
poses, commands and diagnostics: no image crossed), on the commands the vehicle
recorded itself and on the poses' own stamps.
"""
import json
import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import REPO
from uav_vs.flight.replay import commands_from_bag, stamps_from_bag
from uav_vs.bag.reader import Bag
from uav_vs.demo import ground_commands
from uav_vs.flight.report import FlightLog, FlightReport, score_link_cut
from uav_vs.flight.scenario import vehicle_bag

CUT = 3.0        # s the radio link is cut once the vehicle holds


@pytest.fixture(scope='module')
def flight(tmp_path_factory) -> SimpleNamespace:
    """The flight's log, what the link applied (link.json), the commands the vehicle
    recorded, the demo's output and its folder."""
    if os.geteuid() != 0:
        reason = 'two hosts are two network namespaces, which need root'
        if os.environ.get('CI'):
            pytest.fail(reason)
        pytest.skip(reason)
    out = tmp_path_factory.mktemp('two_hosts')
    run = subprocess.run([sys.executable, '-m', 'uav_vs.demo', '--hosts', '2',
                          '--scenario', 'land_on_pad', '--sensors', 'ideal',
                          '--cut-link', str(CUT), '--out', str(out)],
                         capture_output=True, text=True, timeout=300, cwd=REPO,
                         stdin=subprocess.DEVNULL)
    print(run.stdout)
    assert (out / 'flight.npz').exists(), f'{run.stdout[-3000:]}\n{run.stderr[-3000:]}'
    return SimpleNamespace(log=FlightLog.load(out / 'flight.npz'),
                           link=json.loads((out / 'link.json').read_text()),
                           received=commands_from_bag(vehicle_bag(out)), stdout=run.stdout,
                           out=out)


def test_the_mission_flies_across_the_radio_link(flight):
    """The same figures as test_closed_loop asks on one host: within 0.2 m of the setpoint
    over the hold, touchdown within 0.3 m of the pad; every node ended cleanly."""
    log, link, stdout = flight.log, flight.link, flight.stdout
    report = FlightReport.from_log(log)
    assert log.failure == '', log.failure
    assert [e.source for e in log.setpoints] == ['ground', 'onboard', 'onboard']
    assert all(s.reached and s.error_max_m <= 0.2 for s in report.setpoints), report.setpoints
    assert report.landing is not None and report.landing.error_m <= 0.3, report.landing
    assert not any(log.exit_codes.values()), (log.exit_codes, log.failed_logs)
    assert 'radio link: 20 +- 10 ms, 2 % loss' in stdout
    assert 'cmd_vel on the vehicle from ground frames (controller across the link)' in stdout


def test_every_command_and_pose_lost_was_lost_by_the_link(flight):
    """The commands the controller sent from the ground (of the ground frames; its
    recorder, same host) once the vehicle's recorder had its first that never reached it:
    no more than the packets the link dropped or cut that way, and the link did drop some
    (2 % loss, a 3 s cut). The same bound for the onboard poses the other way, taken best
    effort as a controller on the ground would take them; that some were lost is not
    asked: the homography node may start after the cut, and at 2 % a hundred poses all
    cross one time in ten (test_radio_link shows a message crosses once)."""
    sent, arrived = ground_commands(flight.log), flight.received.stamps
    lost = len(np.setdiff1d(sent[sent >= arrived.min()], arrived))
    up = flight.link['ground_to_air']
    assert 0 < lost <= up['lost'] + up['cut'], (lost, up['lost'], up['cut'])
    sent = stamps_from_bag(vehicle_bag(flight.out), '/onboard/pose')
    arrived = flight.log.onboard.stamps
    lost = len(np.setdiff1d(sent[sent >= arrived.min()], arrived))
    down = flight.link['air_to_ground']
    assert lost <= down['lost'] + down['cut'], (lost, down['lost'], down['cut'])
    assert 'across the link: cmd_vel' in flight.stdout


def first_receipts(track, stamps: np.ndarray) -> np.ndarray:
    """When `track` first received a command of each of `stamps` (all in it)."""
    order = np.lexsort((track.received, track.stamps))
    return track.received[order][np.searchsorted(track.stamps[order], stamps)]


def test_the_controller_runs_where_the_pose_it_flies_on_is_made(flight):
    """On the ground pose its commands reach the ground's recorder a link's delay before
    the vehicle's; on the onboard pose it runs on the vehicle, and the other way round."""
    log, received, config = flight.log, flight.received, flight.link['config']
    least_ns = (config['delay'] - config['jitter']) * 1e9
    for frames, sign in ((log.ground_frames, 1), (log.onboard_frames, -1)):
        stamps = np.intersect1d(log.commands.stamps[np.isin(log.commands.stamps, frames)],
                                received.stamps)
        assert len(stamps) > 20, len(stamps)
        ahead = first_receipts(received, stamps) - first_receipts(log.commands, stamps)
        assert sign * np.median(ahead) >= least_ns, (sign, np.median(ahead))


def test_only_poses_commands_and_diagnostics_crossed(flight):
    log, link = flight.log, flight.link
    up, down = link['ground_to_air'], link['air_to_ground']
    assert up['packets'] > 100 and down['packets'] > 100
    # One 640x480 frame is 0.9 MB: a raw camera stream across would be ~10 MB a second ...
    assert (up['bytes'] + down['bytes']) / link['seconds'] < 1e6, (up, down, link['seconds'])
    # ... and neither host's recorder took the other's images (JPEG would be smaller).
    with Bag(flight.out / 'bag') as ground, Bag(vehicle_bag(flight.out)) as vehicle:
        assert not [t for t in ground.topics if t.startswith('/onboard/image')], ground.topics
        assert set(vehicle.topics) == {'/cmd_vel', '/onboard/pose'}
    # The onboard pose crossed the link: each arrived at least the link's least delay late.
    onboard = log.onboard
    latency = (onboard.received - onboard.stamps) * 1e-9
    least = link['config']['delay'] - link['config']['jitter']
    assert len(latency) > 50 and np.min(latency) >= least, np.min(latency)


def test_a_cut_link_stops_the_commands_the_vehicle_holds_and_both_sides_resume(flight):
    """While cut off the vehicle gets no command (the relay stops it after its stale-command
    timeout) and stays put; the ground's link monitor says so, and hears it again after."""
    log, link, stdout = flight.log, flight.link, flight.stdout
    cut = score_link_cut(log, flight.received)
    assert cut is not None and abs(cut.cut_s - CUT) < 0.5, cut
    assert link['ground_to_air']['cut'] > 0 and link['air_to_ground']['cut'] > 0
    assert cut.command_gap_s >= CUT - 0.1, cut                # nothing came through
    assert 0.0 < cut.reported_after_s < CUT, cut               # said while it lasted ...
    assert 0.0 < cut.heard_again_after_s < 10.0, cut           # ... and heard again after
    assert cut.drift_m < 0.1, cut                               # hovering, not flying off
    assert 'link cut for' in stdout
