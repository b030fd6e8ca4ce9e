"""The relay's Session flying the real ArduCopter SITL: nothing unsafe reaches the autopilot.

Truth is the simulator's own state (SIM_STATE, on a second serial port the relay does
not use) and the bytes on the relay's link (a TCP tap between the Session and SITL's
SERIAL0 decodes every SET_POSITION_TARGET_LOCAL_NED, and can cut the link in flight).
The flight runs inside SITL's network namespace (`python test/test_sitl_relay.py SERIAL0
SERIAL1` there) and prints its measurements as JSON; the tests below judge them. SITL runs at SPEEDUP times real
time: speeds are in the autopilot's time, and the relay's rates in wall time.
"""
import contextlib
import json
import math
import socket
import sys
import threading
import time
from pathlib import Path

import pytest

from sitl import Sitl
from uav_vs.autopilot.session import SEND_BURST

NAMESPACE, INSTANCE, SPEEDUP = 'uavvs_relay_sitl', 4, 8
MAX_SPEED, MAX_CLIMB, MAX_DESCENT, MAX_YAW_RATE = 1.5, 0.5, 0.5, 0.5
SEND_RATE = 50.0
# Each phase starts from a hover. Measured on this SITL with commands at the limits: the
# copter's own loops overshoot a step by up to 2 % (speed), 12 % (climb) and 23 % (yaw
# rate) and settle on the target within about 2 s of its time.
PEAK, SETTLED = 1.3, 1.05
SETTLE_TIME = 2.5 / SPEEDUP   # [s] wall
LINK_TIMEOUT = 3.0            # SessionConfig.link_timeout [s] wall
# ArduPilot's GUID_TIMEOUT (3 s) and its stop from 1 m/s, in its time, as wall seconds
STOPPED_AFTER = (3.0 + 2.0) / SPEEDUP
HUGE = 1.7976931348623157e308
PHASES = {   # name: (ENU/FLU command, yaw rate, body frame, wall seconds)
    'huge_up': ((1e308, 1e308, 1e308), 1e308, False, 1.0),        # north-east, climbing
    'huge_down': ((-HUGE, -5e-324, -HUGE), -HUGE, False, 0.7),    # west, descending
    'huge_body': ((1e308, -1e308, 0.0), 1e308, True, 1.0),        # forward-right
    'over_limit': ((10.0, -10.0, 3.0), -4.0, False, 1.0),
}


@pytest.fixture(scope='module')
def flight(tmp_path_factory) -> dict:
    with Sitl(NAMESPACE, tmp_path_factory.mktemp('sitl'), INSTANCE, SPEEDUP) as sim:
        serial0, serial1, _ = sim.ports
        return sim.run_python(Path(__file__), str(serial0), str(serial1), timeout=110.0)


LIMITS = {'speed': MAX_SPEED, 'climb': MAX_CLIMB, 'descent': MAX_DESCENT,
          'yaw_rate': MAX_YAW_RATE}


@pytest.mark.parametrize('phase', PHASES)
def test_huge_and_over_limit_commands_fly_within_the_limits(flight, phase):
    peak, settled = flight['phases'][phase]['peak'], flight['phases'][phase]['settled']
    for key, limit in LIMITS.items():
        assert peak[key] <= limit * PEAK and settled[key] <= limit * SETTLED, (key, peak, settled)
    assert settled['speed'] >= 0.9 * MAX_SPEED and settled['yaw_rate'] >= 0.9 * MAX_YAW_RATE
    vertical = {'huge_up': 'climb', 'huge_down': 'descent', 'over_limit': 'climb'}.get(phase)
    if vertical:   # flown at the limit, not dropped
        assert settled[vertical] >= 0.9 * LIMITS[vertical], settled


def test_every_setpoint_on_the_wire_is_finite_and_within_the_limits(flight):
    wire = flight['wire']
    assert wire['count'] > 50 and wire['non_finite'] == 0
    # float32 on the wire: 1e-6 relative
    assert wire['speed'] <= MAX_SPEED * (1 + 1e-6) and wire['climb'] <= MAX_CLIMB * (1 + 1e-6)
    assert wire['descent'] <= MAX_DESCENT * (1 + 1e-6)
    assert wire['yaw_rate'] <= MAX_YAW_RATE * (1 + 1e-6)
    assert flight['refused_non_finite'] == 3   # inf, -inf, nan: ValueError, nothing sent


def test_a_lost_link_is_noticed_the_autopilot_stops_and_the_relay_flies_on_after_it(flight):
    loss = flight['link_loss']
    assert loss['speed_before'] >= 0.9, loss
    # SessionConfig.link_timeout after the last HEARTBEAT (wall time), and reported at once
    assert loss['noticed_after'] <= LINK_TIMEOUT + 1.0, loss
    # meanwhile ArduPilot's GUID_TIMEOUT stopped the vehicle: nothing reached it
    assert loss['speed_while_lost'] <= 0.15, loss
    assert loss['reconnects'] == 1 and loss['stale_setpoints'] == 0, loss
    assert loss['resumed_setpoints'] > 10, loss
    assert math.isclose(loss['velocity_after'][0], 0.5, abs_tol=0.1), loss   # north
    assert abs(loss['velocity_after'][1]) < 0.1, loss


def test_a_burst_is_rate_limited_on_the_wire_and_its_newest_command_is_flown(flight):
    burst = flight['burst']
    allowed = SEND_RATE * burst['seconds'] + SEND_BURST
    # a burst well beyond the limit (how many a 1 ms loop makes depends on the machine's load)
    assert burst['commands'] > 3 * allowed, burst
    assert burst['setpoints'] <= allowed, burst
    assert burst['last'] == [0.5, 0.0, 0.0]                  # NED north 0.5: the newest
    assert math.isclose(burst['velocity'][0], 0.5, abs_tol=0.1), burst   # and the copter flies it
    assert abs(burst['velocity'][1]) < 0.1, burst


# ---------------------------------------------------------------- inside the namespace
class WireTap:
    """A TCP relay from a local port to SITL, decoding what the client sends. While
    `dropping` is set it forwards nothing either way (a radio out of range); a client
    that reconnects gets a new connection to SITL."""

    def __init__(self, port: int):
        from uav_vs.autopilot.link import mavlink
        self.parser = mavlink.MAVLink(None)
        self.server = socket.create_server(('127.0.0.1', 0))
        self.port = self.server.getsockname()[1]
        self.setpoints: list = []   # (time.monotonic(), SET_POSITION_TARGET_LOCAL_NED)
        self.dropping = False
        threading.Thread(target=self._serve, args=(port,), daemon=True).start()

    def _serve(self, port: int) -> None:
        while True:
            client, _ = self.server.accept()
            upstream = socket.create_connection(('127.0.0.1', port))
            threading.Thread(target=self._pipe, args=(upstream, client, False),
                             daemon=True).start()
            threading.Thread(target=self._pipe, args=(client, upstream, True),
                             daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, decode: bool) -> None:
        with contextlib.suppress(OSError):   # either side closed: this connection ends
            while data := src.recv(65536):
                if self.dropping:
                    continue
                dst.sendall(data)
                for msg in (self.parser.parse_buffer(data) or []) if decode else []:
                    if msg.get_type() == 'SET_POSITION_TARGET_LOCAL_NED':
                        self.setpoints.append((time.monotonic(), msg))
        for end in (src, dst):
            end.close()


class Truth:
    """SIM_STATE from a second serial port: the simulator's own velocity and turn rate."""

    def __init__(self, port: int):
        from uav_vs.autopilot.link import open_connection
        self.conn = open_connection(f'tcp:127.0.0.1:{port}', source_system=254)
        self.samples: list = []   # (time.monotonic(), vn, ve, vd, zgyro)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        from uav_vs.autopilot.link import mavlink
        asked = 0.0
        while True:
            if time.monotonic() - asked > 1.0:
                self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                mavlink.MAVLINK_MSG_ID_SIM_STATE, 20000, 0, 0, 0,
                                                0, 0)
                asked = time.monotonic()
            msg = self.conn.recv_match(type='SIM_STATE', blocking=True, timeout=0.2)
            if msg is not None:
                self.samples.append((time.monotonic(), msg.vn, msg.ve, msg.vd, msg.zgyro))

    def between(self, start: float, end: float) -> dict:
        rows = [s for s in self.samples if start <= s[0] <= end]
        return {'samples': len(rows),
                'speed': max(math.hypot(vn, ve) for _, vn, ve, _, _ in rows),
                'climb': max(-vd for *_, vd, _ in rows),
                'descent': max(vd for *_, vd, _ in rows),
                'yaw_rate': max(abs(r) for *_, r in rows)}


def hold(session, v, yaw_rate: float, body: bool, seconds: float, rate: float = 20.0) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        assert session.send_velocity(v, yaw_rate, body)
        time.sleep(1.0 / rate)


def fly(serial0: int, serial1: int) -> dict:
    from uav_vs.autopilot.session import Limits, Session, SessionConfig
    tap, truth = WireTap(serial0), Truth(serial1)
    limits = Limits(max_speed=MAX_SPEED, max_climb=MAX_CLIMB, max_descent=MAX_DESCENT,
                    max_yaw_rate=MAX_YAW_RATE)
    config = SessionConfig(connection=f'tcp:127.0.0.1:{tap.port}', allow_arming=True,
                           limits=limits, max_send_rate=SEND_RATE, command_timeout=1.0)
    result = {}
    with Session(config) as session:
        session.wait_connected(20.0)
        end = time.monotonic() + 60.0
        while not session.status().prearm_ok:
            assert time.monotonic() < end, session.status().prearm_reasons
            time.sleep(0.2)
        session.set_guided()
        session.arm()
        session.takeoff(3.0)
        hold(session, (0.0, 0.0, 0.0), 0.0, False, 0.6)   # the takeoff's own climb ends

        windows = {}
        for name, (v, yaw_rate, body, seconds) in PHASES.items():
            start = time.monotonic()
            hold(session, v, yaw_rate, body, seconds)
            windows[name] = (start, time.monotonic())
            hold(session, (0.0, 0.0, 0.0), 0.0, False, 0.4)   # back to a hover

        refused = 0
        for bad in ((math.inf, 0.0, 0.0), (0.0, -math.inf, 0.0), (0.0, 0.0, math.nan)):
            try:
                session.send_velocity(bad)
            except ValueError:
                refused += 1
        result['refused_non_finite'] = refused

        t0, n = time.monotonic(), 0
        while time.monotonic() < t0 + 0.5:   # ~1 kHz: east 0..1 m/s
            session.send_velocity((min(n / 500, 1.0), 0.0, 0.0))
            n += 1
            time.sleep(0.001)
        session.send_velocity((0.0, 0.5, 0.0))   # the newest: north 0.5
        newest = (0.5, 0.0, 0.0)
        end = time.monotonic() + 1.0
        while not any(_ned(m) == newest for t, m in tap.setpoints if t >= t0):
            assert time.monotonic() < end, 'the newest command never reached the wire'
            time.sleep(0.005)
        seen = time.monotonic()
        burst = [m for t, m in tap.setpoints if t0 <= t <= seen]
        time.sleep(0.8)   # 6.4 s of autopilot time on the newest command
        late = [s for s in truth.samples if s[0] >= time.monotonic() - 0.1]
        result['burst'] = {'commands': n + 1, 'setpoints': len(burst), 'seconds': seen - t0,
                           'last': list(_ned(burst[-1])),
                           'velocity': [sum(s[k] for s in late) / len(late) for k in (1, 2)]}
        result['link_loss'] = lose_the_link(session, tap, truth)
        session.land()
    result['phases'] = {name: {'peak': truth.between(start, end + 0.3),   # and the stop
                               'settled': truth.between(start + SETTLE_TIME, end)}
                        for name, (start, end) in windows.items()}
    result['wire'] = _wire(m for _, m in tap.setpoints)
    return result


def lose_the_link(session, tap: WireTap, truth: Truth) -> dict:
    """Fly north at 1 m/s, then drop every byte both ways until the Session calls the link
    lost, and let it reconnect; the controller (this loop) keeps commanding meanwhile."""
    from uav_vs.autopilot.session import LinkState
    hold(session, (0.0, 1.0, 0.0), 0.0, False, 1.0)
    cut = time.monotonic()
    tap.dropping = True
    while session.send_velocity((0.0, 1.0, 0.0)):
        assert time.monotonic() < cut + 10.0, 'the lost link was never noticed'
        time.sleep(0.05)
    lost = time.monotonic()
    tap.dropping = False
    while session.status().link is not LinkState.CONNECTED:
        assert time.monotonic() < lost + 20.0, session.status()
        time.sleep(0.05)
    back = time.monotonic()
    time.sleep(0.5)                  # nothing is sent until the controller commands again
    stale = sum(t >= back for t, _ in tap.setpoints)
    resumed = time.monotonic()
    hold(session, (0.0, 0.5, 0.0), 0.0, False, 1.0)
    late = [s for s in truth.samples if s[0] >= time.monotonic() - 0.3]
    return {'speed_before': truth.between(cut - 0.3, cut)['speed'],
            'speed_while_lost': truth.between(cut + STOPPED_AFTER, lost)['speed'],
            'noticed_after': lost - cut, 'reconnects': session.status().reconnects,
            'stale_setpoints': stale,
            'resumed_setpoints': sum(t >= resumed for t, _ in tap.setpoints),
            'velocity_after': [sum(s[k] for s in late) / len(late) for k in (1, 2)]}


def _ned(msg) -> tuple[float, float, float]:
    return (msg.vx, msg.vy, msg.vz)


def _wire(setpoints) -> dict:
    rows = [(m.vx, m.vy, m.vz, m.yaw_rate) for m in setpoints]
    return {'count': len(rows),
            'non_finite': sum(not all(map(math.isfinite, r)) for r in rows),
            'speed': max(math.hypot(vx, vy) for vx, vy, _, _ in rows),
            'climb': max(-vz for _, _, vz, _ in rows),
            'descent': max(vz for _, _, vz, _ in rows),
            'yaw_rate': max(abs(r) for *_, r in rows)}


if __name__ == '__main__':
    print(json.dumps(fly(int(sys.argv[1]), int(sys.argv[2]))))
