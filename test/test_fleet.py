"""Two vehicles at once, `python -m uav_vs.demo --vehicles 2` (uav_vs.flight.fleet):
/uav1 and /uav2, each its own simulated autopilot (system ids 1 and 2), onboard camera,
ground station (its own landmark colours in the shared cameras' images), controller and
relay, fly their own hold and setpoint and land. Judged against each vehicle's truth (its
sim_world's, drawn by the shared ground cameras); crosstalk as the demo counted it on the
ROS graph and the relays (out/fleet.json)."""
import json
import subprocess
import sys

from conftest import REPO
from uav_vs.flight.fleet import FLEET
from uav_vs.flight.report import FlightLog, FlightReport

HOLD_RMS_M = 0.05      # each vehicle's hold by its truth (one vehicle: 1.8 cm, ideal sensors)


def test_two_vehicles_fly_their_own_setpoints_without_crosstalk(tmp_path):
    run = subprocess.run([sys.executable, '-m', 'uav_vs.demo', '--vehicles', '2', '--sensors',
                          'ideal', '--out', str(tmp_path)], capture_output=True, text=True,
                         timeout=400, cwd=REPO)
    print(run.stdout)
    assert run.returncode == 0, f'{run.stdout[-3000:]}\n{run.stderr[-3000:]}'
    crosstalk = json.loads((tmp_path / 'fleet.json').read_text())['crosstalk']
    for member in FLEET:
        log = FlightLog.load(tmp_path / member.name / 'flight.npz')
        report = FlightReport.from_log(log)
        assert log.failure == '', (member.name, log.failure)
        assert f'scenario {member.name}: completed' in run.stdout
        ns = f'/{member.name}'
        assert [e.source for e in log.setpoints] == ['ground', 'ground']
        for event in log.setpoints:       # each flew on its own ground station's pose
            assert event.controller_inputs == (f'{ns}/ground/pose', f'{ns}/setpoint'), event
        hold, setpoint = report.setpoints
        assert hold.reached and hold.error_rms_m <= HOLD_RMS_M, (member.name, hold)
        assert setpoint.reached and setpoint.error_max_m <= 0.2, (member.name, setpoint)
        ground = report.sources['ground']
        assert ground.samples > 100 and ground.position_rmse_m <= 0.05, (member.name, ground)
        assert log.landed_ns is not None
        seen = crosstalk[member.name]
        assert seen['looks'] >= 10 and seen['count'] == 0, (member.name, seen)
        assert not any(log.exit_codes.values()), (log.exit_codes, log.failed_logs)
