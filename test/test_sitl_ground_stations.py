"""The relay's Session on the real ArduCopter SITL beside another ground station.

A MAVProxy shares the relay's link to the autopilot and sends as system 255 too: every
COMMAND_ACK the autopilot gives it reaches the relay. Here a router between the Session
and SITL's SERIAL0 does what MAVProxy does (everything from the autopilot passed to
the relay, the relay's messages passed on) and sends commands of its own as system 255,
component OTHER_COMPONENT (MAVProxy's). Its refusals must not be taken for the relay's.
The router also records what the autopilot says on that link (its time since boot,
STATUSTEXT, the first LOCAL_POSITION_NED): when `autopilot/odom` can start.
The run happens inside SITL's network namespace (`python test/test_sitl_ground_stations.py
SERIAL0` there) and prints its measurements as JSON; the tests below judge them.
"""
import contextlib
import json
import logging
import socket
import sys
import threading
import time
from pathlib import Path

import pytest

from sitl import Sitl

NAMESPACE, INSTANCE, SPEEDUP = 'uavvs_gcs_sitl', 5, 8
OTHER_COMPONENT = 230          # MAVProxy's source component (same system, 255)
UNKNOWN_MODE = 99              # no ArduCopter mode: DO_SET_MODE to it is refused
ACCEPTED = 0                   # MAV_RESULT_ACCEPTED


@pytest.fixture(scope='module')
def run(tmp_path_factory) -> dict:
    with Sitl(NAMESPACE, tmp_path_factory.mktemp('sitl'), INSTANCE, SPEEDUP) as sim:
        return sim.run_python(Path(__file__), str(sim.ports[0]), timeout=110.0)


def test_another_ground_stations_refusal_is_not_logged_as_the_relays(run):
    other = run['other_refusal']
    assert other['ack'][:2] == [255, OTHER_COMPONENT] and other['ack'][3] != ACCEPTED, other
    assert other['relay_warnings'] == [], other


def test_a_command_waiting_for_its_ack_ignores_another_ground_stations_refusal(run):
    guided = run['guided']
    # the other station's refusal reached the relay while its own DO_SET_MODE was held back
    assert guided['other_ack'][:2] == [255, OTHER_COMPONENT], guided
    assert guided['other_ack'][3] != ACCEPTED, guided
    assert guided['error'] is None and guided['mode'] == 'GUIDED', guided


def test_the_relays_own_refusal_is_still_its_own(run):
    own = run['own_refusal']   # a takeoff while disarmed
    assert own['ack'][:2] == [255, 190] and own['ack'][3] != ACCEPTED, own
    assert own['error'] is not None and 'refused' in own['error'], own


def test_local_position_starts_when_the_ekf_uses_gps_not_at_its_origin(run):
    """What docs/relay.md says of when `autopilot/odom` starts on ArduPilot."""
    t = run['boot_ms']
    assert t['origin_set'] is not None and t['using_gps'] is not None, run['texts']
    assert t['first_local_position'] >= t['using_gps'], t
    assert t['using_gps'] - t['origin_set'] > 5000, t   # the origin alone starts nothing


# ---------------------------------------------------------------- inside the namespace
class Router:
    """A MAVProxy-like router: SITL on one side, the relay on the other, and a ground
    station of its own (system 255, OTHER_COMPONENT) on the autopilot's link."""

    def __init__(self, port: int):
        from uav_vs.autopilot.link import mavlink
        self.mavlink = mavlink
        self.server = socket.create_server(('127.0.0.1', 0))
        self.port = self.server.getsockname()[1]
        self.upstream = socket.create_connection(('127.0.0.1', port))
        self.client: socket.socket | None = None
        self.write_lock = threading.Lock()
        self.own = mavlink.MAVLink(self, srcSystem=255, srcComponent=OTHER_COMPONENT)
        self.cond = threading.Condition()
        self.hold_command: int | None = None   # the relay's COMMAND_LONG of this is held back
        self.held: list[bytes] = []
        self.acks: list[tuple] = []   # (target_system, target_component, command, result)
        self.boot_ms = 0
        self.texts: list[tuple[int, str]] = []
        self.first_local_position: int | None = None
        threading.Thread(target=self._from_autopilot, daemon=True).start()
        threading.Thread(target=self._serve, daemon=True).start()

    def write(self, data: bytes) -> None:
        """Upstream, to the autopilot (the own ground station's encoder writes here)."""
        with self.write_lock:
            self.upstream.sendall(data)

    def _serve(self) -> None:
        self.client, _ = self.server.accept()
        parser = self.mavlink.MAVLink(None)
        parser.robust_parsing = True    # a stray byte is BAD_DATA, not an exception
        with contextlib.suppress(OSError):
            while data := self.client.recv(65536):
                for msg in parser.parse_buffer(data) or []:
                    with self.cond:
                        if msg.get_type() == 'COMMAND_LONG' and msg.command == self.hold_command:
                            self.held.append(bytes(msg.get_msgbuf()))
                            self.cond.notify_all()
                            continue
                    self.write(bytes(msg.get_msgbuf()))

    def _from_autopilot(self) -> None:
        parser = self.mavlink.MAVLink(None)
        parser.robust_parsing = True    # a stray byte is BAD_DATA, not an exception
        with contextlib.suppress(OSError):
            while data := self.upstream.recv(65536):
                if self.client is not None:
                    self.client.sendall(data)   # first to the relay, then noted
                with self.cond:
                    for msg in parser.parse_buffer(data) or []:
                        self._note(msg)
                    self.cond.notify_all()

    def _note(self, msg) -> None:
        kind = msg.get_type()
        if hasattr(msg, 'time_boot_ms'):
            self.boot_ms = msg.time_boot_ms
        if kind == 'COMMAND_ACK':
            self.acks.append((msg.target_system, msg.target_component, msg.command, msg.result))
        elif kind == 'STATUSTEXT':
            self.texts.append((self.boot_ms, msg.text))
        elif kind == 'LOCAL_POSITION_NED' and self.first_local_position is None:
            self.first_local_position = msg.time_boot_ms

    def refuse_from_the_other_station(self, timeout: float = 5.0) -> tuple:
        """DO_SET_MODE to an unknown mode from the own station; its ACK, once passed on."""
        mav = self.mavlink
        with self.cond:
            start = len(self.acks)
            self.own.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0,
                                       mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, UNKNOWN_MODE,
                                       0, 0, 0, 0, 0)
            mine = lambda: [a for a in self.acks[start:]  # noqa: E731
                            if a[1] == OTHER_COMPONENT and a[2] == mav.MAV_CMD_DO_SET_MODE]
            assert self.cond.wait_for(mine, timeout), 'no COMMAND_ACK for the other station'
            return mine()[0]

    def ack_to(self, component: int, command: int, since: int = 0) -> tuple | None:
        with self.cond:
            return next((a for a in self.acks[since:] if a[1] == component and a[2] == command),
                        None)

    def text_at(self, words: str) -> int | None:
        with self.cond:
            return next((ms for ms, text in self.texts if words in text), None)


def run_beside_another_station(serial0: int) -> dict:
    from uav_vs.autopilot.link import mavlink
    from uav_vs.autopilot.session import AutopilotError, Session, SessionConfig
    router = Router(serial0)
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = records.append
    core = logging.getLogger('uav_vs.autopilot')
    core.addHandler(handler)
    core.setLevel(logging.INFO)
    config = SessionConfig(connection=f'tcp:127.0.0.1:{router.port}', ack_timeout=3.0,
                           command_retries=0)
    result = {}
    with Session(config) as session:
        session.wait_connected(20.0)
        time.sleep(0.5)   # the stream requests are answered

        # the relay waits for nothing: the other station's refusal is not the relay's
        before = len(records)
        ack = router.refuse_from_the_other_station()
        time.sleep(0.5)
        result['other_refusal'] = {'ack': ack, 'relay_warnings': [
            r.getMessage() for r in records[before:] if r.levelno >= logging.WARNING
            and 'refused' in r.getMessage()]}

        # the relay's own refusal: ArduCopter takes off only when armed
        start = len(router.acks)
        try:
            session.takeoff(3.0)
            error = None
        except AutopilotError as err:
            error = str(err)
        result['own_refusal'] = {'error': error, 'ack': router.ack_to(
            190, mavlink.MAV_CMD_NAV_TAKEOFF, start)}

        end = time.monotonic() + 60.0
        while not session.status().prearm_ok:
            assert time.monotonic() < end, session.status().prearm_reasons
            time.sleep(0.1)

        # GUIDED, its DO_SET_MODE held back until the other station's refusal has passed
        with router.cond:
            router.hold_command = mavlink.MAV_CMD_DO_SET_MODE
        outcome = {}

        def set_guided() -> None:
            try:
                session.set_guided()
                outcome['error'] = None
            except AutopilotError as err:
                outcome['error'] = str(err)
        worker = threading.Thread(target=set_guided)
        worker.start()
        with router.cond:
            assert router.cond.wait_for(lambda: router.held, 5.0), 'set_guided sent nothing'
        other = router.refuse_from_the_other_station()
        time.sleep(0.3)   # the relay has read it
        with router.cond:
            router.hold_command = None
            held, router.held = router.held, []
        for frame in held:
            router.write(frame)
        worker.join(10.0)
        result['guided'] = {'other_ack': other, **outcome, 'mode': session.status().mode}
    core.removeHandler(handler)
    result['boot_ms'] = {'origin_set': router.text_at('origin set'),
                         'using_gps': router.text_at('is using GPS'),
                         'first_local_position': router.first_local_position}
    result['texts'] = router.texts
    return result


if __name__ == '__main__':
    print(json.dumps(run_beside_another_station(int(sys.argv[1]))))
