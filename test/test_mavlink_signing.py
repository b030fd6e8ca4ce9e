"""MAVLink 2 signing: the signing rules as checked on our links, a forged frame that must
not lock a party out, and misconfigurations that must be said in plain words.

The signing rules are checked on frames made here by pymavlink's own signer; the link
tests run the session (and the relay node) against the simulated vehicle over loopback,
and the session against the real ArduCopter SITL where ../shared/sitl has it.
A forged frame is what anyone on the network can send without the key: a peer's system
and component ids, every link id, a timestamp an hour ahead and a signature made with a
random key.
"""
import contextlib
import ctypes
import os
import re
import socket
import subprocess
import threading
import time
import types

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from conftest import REPO, wait_for
from test_mavlink_relay_node import Probe, start_relay, vehicle_and_connection
from uav_vs.autopilot.link import (BAD_SIGNATURE, NEW_STREAM_WINDOW, OLD_TIMESTAMP, UNSIGNED,
                                   key_file_exposure, mavlink, open_connection, rejection_cause,
                                   verify_signatures_first)
from uav_vs.autopilot.session import (AutopilotError, CommandError, LinkState, Session,
                                      SessionConfig)
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
HOUR = 360_000_000   # signing timestamp units (10 us)
NO_KEY = 'vehicle signs its messages, we have no key (set signing_key_file)'
WRONG_KEY = 'frames rejected: bad signature (wrong key?)'


# ---------------------------------------------------------------- the signing rules
def _signer(key: bytes, system: int = 1, link_id: int = 0) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=1)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, link_id
    return mav


def _frame(signer: mavlink.MAVLink, timestamp: int) -> bytes:
    """A signed HEARTBEAT with this signing timestamp."""
    signer.signing.timestamp = timestamp
    return bytes(signer.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, 3, 0, 0, 0).pack(signer))


def _receiver(timestamp: int) -> mavlink.MAVLink:
    """A parser holding KEY whose own signing timestamp is `timestamp`, as a link has it."""
    link = verify_signatures_first(types.SimpleNamespace(mav=_signer(KEY, system=255)))
    link.mav.signing.timestamp = timestamp
    link.mav.robust_parsing = True   # as mavutil's connections parse
    return link.mav


def _accepted(receiver: mavlink.MAVLink, frame: bytes) -> bool:
    msg = receiver.parse_char(frame)
    assert msg is not None
    return msg.get_type() == 'HEARTBEAT'


def test_a_forged_frame_changes_nothing_and_genuine_frames_are_accepted_after_it():
    now = 10 * HOUR
    rx, genuine = _receiver(now), _signer(KEY)
    assert _accepted(rx, _frame(genuine, now))
    forged = [_frame(_signer(os.urandom(32), link_id=link), now + HOUR) for link in range(256)]
    assert not any(_accepted(rx, frame) for frame in forged)
    assert rx.signing.stream_timestamps == {(0, 1, 1): now} and rx.signing.timestamp == now
    assert _accepted(rx, _frame(genuine, now + 1))
    assert {rejection_cause(KEY, frame) for frame in forged} == {BAD_SIGNATURE}


def test_replays_and_stale_streams_are_rejected_as_the_specification_says():
    now = 10 * HOUR
    rx, genuine = _receiver(now), _signer(KEY)
    first = _frame(genuine, now + 100)
    assert _accepted(rx, first)
    assert rx.signing.timestamp == now + 100                # ours follows the newest accepted
    assert not _accepted(rx, first)                          # the same frame again: a replay
    assert not _accepted(rx, _frame(genuine, now + 99))     # older than its stream
    assert rejection_cause(KEY, first) == OLD_TIMESTAMP
    assert _accepted(rx, _frame(genuine, now + 101))
    # a new stream (another link id) may start at most one minute behind our timestamp
    ours = rx.signing.timestamp
    assert not _accepted(rx, _frame(_signer(KEY, link_id=7), ours - NEW_STREAM_WINDOW - 1))
    assert _accepted(rx, _frame(_signer(KEY, link_id=8), ours - NEW_STREAM_WINDOW))
    # unsigned: dropped, and said to be
    plain = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    unsigned = bytes(plain.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, 3, 0, 0, 0).pack(plain))
    assert not _accepted(rx, unsigned) and rejection_cause(KEY, unsigned) == UNSIGNED


# ---------------------------------------------------------------- forged frames on a link
def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def _forged(system: int, component: int) -> list[bytes]:
    """Forged HEARTBEATs claiming (system, component) on every link id, an hour ahead."""
    timestamp = int((time.time() - 1420070400) * 1e5) + HOUR
    frames = []
    for link in range(256):
        forger = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
        forger.signing.secret_key, forger.signing.sign_outgoing = os.urandom(32), True
        forger.signing.link_id, forger.signing.timestamp = link, timestamp
        frames.append(bytes(forger.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0).pack(forger)))
    return frames


def _inject_forged(port: int, system: int, component: int, counted=None) -> None:
    """Send the forged frames as UDP datagrams; with `counted` (the receiver's count of
    rejected frames), each one only once the one before it was counted: a burst of 256
    overflows a busy receiver's socket buffer and the kernel drops datagrams."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for n, frame in enumerate(_forged(system, component), start=1):
            s.sendto(frame, ('127.0.0.1', port))
            if counted is not None:
                assert wait_for(lambda: counted() >= n, 5.0, period=0.002), f'frame {n} not seen'


class ForgingTap:
    """A TCP relay between a client and a server that can slip frames into either
    direction between the ones it forwards (someone on the path, with no key)."""

    def __init__(self, server_port: int):
        self.server = socket.create_server(('127.0.0.1', 0))
        self.port = self.server.getsockname()[1]
        self.lock = threading.Lock()
        self.ends: dict[str, socket.socket] = {}
        self.ready = threading.Event()
        threading.Thread(target=self._serve, args=(server_port,), daemon=True).start()

    def _serve(self, server_port: int) -> None:
        client, _ = self.server.accept()
        upstream = socket.create_connection(('127.0.0.1', server_port))
        self.ends = {'client': client, 'server': upstream}
        self.ready.set()
        threading.Thread(target=self._pipe, args=(upstream, client), daemon=True).start()
        self._pipe(client, upstream)

    def _pipe(self, src: socket.socket, dst: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                with self.lock:
                    dst.sendall(data)

    def inject(self, towards: str, frames: list[bytes]) -> None:
        assert self.ready.wait(5.0)
        with self.lock:
            for frame in frames:
                self.ends[towards].sendall(frame)


@contextlib.contextmanager
def signed_pair(vehicle_key=KEY, session_key=KEY, session_serves=False, tmp_path=None,
                **session_kw):
    """The simulated vehicle (UDP) and a session, each with its key or None.

    session_serves: the session listens (udpin) on a known port and the vehicle sends to
    it, so that frames can be injected towards the session."""
    if session_serves:
        port = _free_udp_port()
        server, client = f'udpout:127.0.0.1:{port}', f'udpin:127.0.0.1:{port}'
    else:
        server = 'udpin:127.0.0.1:0'
    key_file = None
    if session_key is not None:
        key_file = tmp_path / 'signing.key'
        key_file.write_text(session_key.hex())
        key_file.chmod(0o600)
    cfg = VehicleConfig(connection=server, ready_delay=0.2, signing_key=vehicle_key)
    with MavlinkVehicle(cfg) as vehicle:
        if not session_serves:
            client = f'udpout:127.0.0.1:{vehicle.address[1]}'
        with Session(SessionConfig(connection=client, signing_key_file=key_file and str(key_file),
                                   ack_timeout=0.5, **session_kw)) as session:
            yield vehicle, session


def test_a_forged_frame_does_not_lock_the_relay_out_of_the_vehicle(tmp_path):
    with signed_pair(tmp_path=tmp_path) as (vehicle, session):
        session.wait_connected(5.0)
        session.set_mode('GUIDED')
        _inject_forged(vehicle.address[1], 255, mavlink.MAV_COMP_ID_MISSIONPLANNER)
        session.set_mode('STABILIZE')      # the vehicle still takes our signed commands
        assert vehicle.truth().mode == 'STABILIZE'


def test_a_forged_frame_does_not_lock_the_vehicle_out_of_the_relay(tmp_path):
    with signed_pair(tmp_path=tmp_path, session_serves=True) as (vehicle, session):
        session.wait_connected(5.0)
        port = session.config.connection.rsplit(':', 1)[1]
        _inject_forged(int(port), 1, 1, counted=lambda: session.status().rejected_bad_signature)
        injected = time.monotonic()
        # the vehicle's next HEARTBEAT (1 Hz) is still accepted: no link loss, no reconnect
        assert wait_for(lambda: time.monotonic() - session.status().heartbeat_age > injected, 2.5)
        status = session.status()
        assert status.link is LinkState.CONNECTED and status.reconnects == 0
        assert status.rejected_bad_signature == 256 and status.rejected_old_timestamp == 0
        assert status.signing_problem is None


def test_a_forged_frame_in_a_tcp_stream_locks_neither_party_out(tmp_path):
    key_file = tmp_path / 'signing.key'
    key_file.write_text(KEY.hex())
    key_file.chmod(0o600)
    vehicle_cfg = VehicleConfig(connection='tcpin:127.0.0.1:0', ready_delay=0.2, signing_key=KEY)
    with MavlinkVehicle(vehicle_cfg) as vehicle:
        tap = ForgingTap(vehicle.address[1])
        config = SessionConfig(connection=f'tcp:127.0.0.1:{tap.port}', ack_timeout=0.5,
                               signing_key_file=str(key_file))
        with Session(config) as session:
            session.wait_connected(5.0)
            session.set_mode('GUIDED')
            # towards the vehicle, as the session: its signed commands still count
            tap.inject('server', _forged(255, mavlink.MAV_COMP_ID_MISSIONPLANNER))
            session.set_mode('STABILIZE')
            assert vehicle.truth().mode == 'STABILIZE'
            # towards the session, as the vehicle: its next HEARTBEAT is still taken
            injected = time.monotonic()
            tap.inject('client', _forged(1, 1))
            assert wait_for(lambda: time.monotonic() - session.status().heartbeat_age > injected,
                            2.5)
            status = session.status()
            assert status.link is LinkState.CONNECTED and status.reconnects == 0
            assert status.rejected_bad_signature == 256 and status.rejected_old_timestamp == 0
            assert status.signing_problem is None


# ---------------------------------------------------------------- misconfigurations, said
def test_no_key_for_a_signing_vehicle_is_said(tmp_path):
    with signed_pair(session_key=None, command_retries=0) as (vehicle, session):
        status = session.wait_connected(5.0)
        assert status.vehicle_signs and not status.signing
        assert status.signing_problem == NO_KEY
        with pytest.raises(CommandError, match=re.escape(f'no COMMAND_ACK: {NO_KEY}')):
            session.set_mode('GUIDED')
        assert vehicle.truth().mode == 'STABILIZE'   # it dropped our unsigned command


def test_wrong_key_is_said_apart_from_unsigned_frames(tmp_path):
    with signed_pair(session_key=OTHER_KEY, tmp_path=tmp_path) as (vehicle, session):
        assert wait_for(lambda: session.status().rejected_bad_signature >= 2, 5.0)
        status = session.status()
        assert status.link is LinkState.CONNECTING and status.rejected_unsigned == 0
        assert status.signing_problem == WRONG_KEY
        with pytest.raises(AutopilotError, match=re.escape(
                f'no link to the autopilot (connecting): {WRONG_KEY}')):
            session.set_mode('GUIDED')
    # a vehicle that does not sign, for a session that requires signing: another cause
    with signed_pair(vehicle_key=None, tmp_path=tmp_path) as (vehicle, session):
        assert wait_for(lambda: session.status().rejected_unsigned >= 2, 5.0)
        status = session.status()
        assert status.rejected_bad_signature == 0
        assert status.signing_problem.startswith('frames rejected: unsigned (the vehicle does not sign')
    # not requiring signatures, pymavlink lets a badly signed frame through as unsigned
    with signed_pair(session_key=OTHER_KEY, tmp_path=tmp_path,
                     signing_required=False) as (vehicle, session):
        status = session.wait_connected(5.0)
        assert status.vehicle_signs
        assert status.signing_problem == 'vehicle signs with another key (wrong key?)'


# ---------------------------------------------------------------- the relay node says it
class DiagProbe(Probe):
    """A Probe that also keeps the relay's diagnostics level and message."""

    def _on_diag(self, msg) -> None:
        super()._on_diag(msg)
        for status in msg.status:
            if status.name == self.name:
                self.level, self.message = status.level, status.message


def _diag_says(probe: DiagProbe, text: str, timeout: float = 20.0) -> None:
    ok = wait_for(lambda: text in getattr(probe, 'message', ''), timeout)
    assert ok, f'diagnostics never said {text!r}: {getattr(probe, "message", None)}'


def test_relay_says_no_key_wrong_key_and_an_open_key_file(ros_node, processes, tmp_path):
    open_key = tmp_path / 'open.key'
    open_key.write_text(OTHER_KEY.hex())
    open_key.chmod(0o644)
    heard_without_key, conn1 = vehicle_and_connection('udp', signing_key=KEY)
    heard_with_wrong_key, conn2 = vehicle_and_connection('udp', signing_key=KEY)
    try:
        start_relay(processes, conn1, ns='/nokey', label='nokey')
        start_relay(processes, conn2, f'signing_key_file:={open_key}', ns='/wrong', label='wrong')
        nokey, wrong = DiagProbe(ros_node, '/nokey'), DiagProbe(ros_node, '/wrong')

        diag = nokey.wait_diag(link='connected', vehicle_signs='True', signing='False')
        _diag_says(nokey, NO_KEY)
        assert nokey.level == DiagnosticStatus.WARN
        response = nokey.call('set_guided')
        assert not response.success and NO_KEY in response.message

        _diag_says(wrong, WRONG_KEY)
        diag = wrong.diag()
        assert diag['link'] == 'connecting' and wrong.level == DiagnosticStatus.ERROR
        assert int(diag['rejected_bad_signature']) > 0 and diag['rejected_unsigned'] == '0'

        assert wait_for(lambda: NO_KEY in processes.log('nokey'), 10)
        assert wait_for(lambda: WRONG_KEY in processes.log('wrong'), 10)
        log = processes.log('wrong')
        assert (f'[wrong.mavlink_relay_node]: signing key file {open_key} is accessible by group '
                'and others (mode 0644)') in log    # the node's own logger: its name, /rosout
        assert OTHER_KEY.hex() not in log
    finally:
        heard_without_key.stop()
        heard_with_wrong_key.stop()


@pytest.mark.parametrize('mode, who', [(0o600, None), (0o400, None), (0o640, 'group'),
                                       (0o604, 'others'), (0o666, 'group and others')])
def test_a_key_file_open_to_others_is_named_with_its_mode(tmp_path, mode, who):
    key_file = tmp_path / 'signing.key'
    key_file.write_text(KEY.hex())
    key_file.chmod(mode)
    said = key_file_exposure(key_file)
    if who is None:
        assert said is None
    else:
        assert said.startswith(f'signing key file {key_file} is accessible by {who} '
                               f'(mode {mode:04o})')
        assert said.endswith(f'chmod 600 {key_file}') and KEY.hex() not in said


# ---------------------------------------------------------------- the real ArduCopter
SITL = REPO.parent / 'shared' / 'sitl'
SITL_NS, SITL_INSTANCE = 'uavvs_sign', 3
SERIAL0, SIGNED_PORT = 5760 + 10 * SITL_INSTANCE, 5762 + 10 * SITL_INSTANCE  # 5762 enforces
CLONE_NEWNET = 0x40000000


@pytest.fixture
def sitl(tmp_path):
    """ArduCopter SITL (instance 3) in its loopback-only network namespace."""
    if not (SITL / 'run_arducopter.sh').is_file():
        why = (f'no ArduCopter SITL at {SITL}: build ArduPilot (ardupilot.org, "Setting up '
               f'SITL on Linux") and put it there with run_arducopter.sh')
        if os.environ.get('CI'):
            pytest.fail(why)
        pytest.skip(why)
    script = str(SITL / 'run_arducopter.sh')
    pid = subprocess.run([script, 'up', SITL_NS, str(tmp_path / 'sitl'), str(SITL_INSTANCE), '1'],
                         capture_output=True, text=True, check=True).stdout.strip()
    yield SITL_NS
    subprocess.run([script, 'down', SITL_NS, pid], check=False)


def in_namespace(ns: str, work) -> None:
    """Run work() on a thread inside network namespace `ns` (threads it starts are in it
    too: the session's); its exception is raised here."""
    failure = []

    def target():
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            fd = os.open(f'/var/run/netns/{ns}', os.O_RDONLY)
            try:
                if libc.setns(fd, CLONE_NEWNET) != 0:
                    raise OSError(ctypes.get_errno(), f'setns {ns}')
            finally:
                os.close(fd)
            work()
        except BaseException as err:   # noqa: B036 (re-raised on the caller's thread)
            failure.append(err)
    thread = threading.Thread(target=target, name=f'in {ns}')
    thread.start()
    thread.join()
    if failure:
        raise failure[0]


def _connect(device: str, timeout: float):
    """A TCP connection to SITL, retried while it starts listening."""
    end = time.monotonic() + timeout
    while True:
        try:
            return open_connection(device)
        except ConnectionRefusedError:
            if time.monotonic() > end:
                raise
            time.sleep(0.2)


def test_arducopter_signing_no_key_and_wrong_key_are_said(sitl, tmp_path):
    right, wrong = tmp_path / 'right.key', tmp_path / 'wrong.key'
    right.write_text(KEY.hex())
    wrong.write_text(OTHER_KEY.hex())
    for key_file in (right, wrong):
        key_file.chmod(0o600)

    def work():
        # the key goes in over SERIAL0, which always takes unsigned messages
        with contextlib.closing(_connect(f'tcp:127.0.0.1:{SERIAL0}', 20.0)) as serial0:
            assert serial0.wait_heartbeat(timeout=20) is not None, 'no HEARTBEAT from SITL'
            now = int((time.time() - 1420070400) * 1e5)
            serial0.mav.setup_signing_send(1, 1, list(KEY), now)
            time.sleep(0.5)
        config = dict(connection=f'tcp:127.0.0.1:{SIGNED_PORT}', command_retries=0)
        with Session(SessionConfig(**config)) as session:
            session.wait_connected(10.0)
            assert wait_for(lambda: session.status().vehicle_signs, 5.0)
            assert session.status().signing_problem == NO_KEY
            with pytest.raises(CommandError, match=re.escape(f'no COMMAND_ACK: {NO_KEY}')):
                session.set_mode('STABILIZE')
        with Session(SessionConfig(**config, signing_key_file=str(wrong))) as session:
            assert wait_for(lambda: session.status().rejected_bad_signature >= 2, 10.0)
            status = session.status()
            assert status.link is LinkState.CONNECTING and status.rejected_unsigned == 0
            assert status.signing_problem == WRONG_KEY
        with Session(SessionConfig(**config, signing_key_file=str(right))) as session:
            session.wait_connected(10.0)
            session.set_mode('STABILIZE')   # the same command, signed: acknowledged
            assert session.status().signing_problem is None
    in_namespace(sitl, work)
