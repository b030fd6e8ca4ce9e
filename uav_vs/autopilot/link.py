"""MAVLink 2 through pymavlink: dialect, connections, signing keys and signature checks.

Importing this module selects MAVLink 2 (signing needs it) and the ardupilotmega
dialect (a superset of common, so it speaks to PX4 too) before any connection is
made; the relay session and the simulated vehicle both go through it.
"""
import hashlib
import hmac
import os
import socket
import stat
import types
from pathlib import Path

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402  (must follow MAVLINK20)

mavutil.set_dialect('ardupilotmega')
mavlink = mavutil.mavlink

# SET_POSITION_TARGET_LOCAL_NED type_mask: use vx, vy, vz and yaw_rate, ignore the rest.
VELOCITY_YAW_RATE_MASK = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE)  # 0x05C7
POSITION_IGNORE = (mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
                   | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE)
VELOCITY_IGNORE = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
                   | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE)

FORCE_DISARM = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that overrides the in-flight check

# A new signed stream may start at most this far behind our own signing timestamp
# (10 us units: one minute), as the MAVLink signing specification says.
NEW_STREAM_WINDOW = 6_000_000
# Why pymavlink dropped a frame as 'Invalid signature' (see rejection_cause).
UNSIGNED, BAD_SIGNATURE, OLD_TIMESTAMP = 'unsigned', 'bad_signature', 'old_timestamp'


NETWORK_PREFIXES = ('udp:', 'udpin:', 'udpout:', 'udpbcast:', 'tcp:', 'tcpin:')
SERIAL_PREFIXES = ('/dev/', 'COM')


def connection_problem(device: str) -> str | None:
    """Why `device` cannot be a connection string, None when it can. Only the form is
    judged: whether its host resolves or its port listens is found when it is opened
    (and may change: a radio or VPN link can come up later)."""
    if device.startswith(SERIAL_PREFIXES):
        return None
    prefix = next((p for p in NETWORK_PREFIXES if device.startswith(p)), None)
    if prefix is None:
        return (f"expected {', '.join(NETWORK_PREFIXES)} followed by HOST:PORT, or a serial "
                f"device (/dev/..., COM...), got {device!r}")
    host, colon, port = device.removeprefix(prefix).rpartition(':')
    if not (colon and host and port.isdigit() and int(port) <= 65535):
        return f'expected {prefix}HOST:PORT with a port in 0..65535, got {device!r}'
    return None


def open_connection(device: str, baud: int = 115200, source_system: int = 255,
                    source_component: int = mavlink.MAV_COMP_ID_MISSIONPLANNER) -> mavutil.mavfile:
    """A pymavlink connection: udpin:/udpout:/udp:HOST:PORT, tcp:HOST:PORT, tcpin:, or a serial device.

    A TCP client tries once (no blocking retry loop); the caller decides when to retry.
    A host name that does not resolve raises socket.gaierror, for udpout: too (pymavlink
    would open it and then drop every datagram without a word).
    """
    if device.startswith('udpout:'):
        host, _, port = device.removeprefix('udpout:').rpartition(':')
        socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    return verify_signatures_first(mavutil.mavlink_connection(
        device, baud=baud, source_system=source_system, source_component=source_component,
        retries=0, autoreconnect=False))


def verify_signatures_first(conn: mavutil.mavfile) -> mavutil.mavfile:
    """Make `conn` verify a signed frame's signature before it changes any signing state.

    pymavlink's MAVLink.check_signature records a frame's timestamp as the newest of its
    (link id, system, component) stream before it compares the signature. One forged
    frame carrying a peer's ids and a future timestamp, made without the key, then makes
    every genuine frame of that peer look like a replay for as long as the connection
    lives. MAVLink.decode() calls check_signature through the instance, so this
    connection's parser gets `_check_signature` instead; the library stays as it is for
    everyone else. Returns `conn`.
    """
    conn.mav.check_signature = types.MethodType(_check_signature, conn.mav)
    return conn


def _check_signature(mav, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
    """The MAVLink signing rules, in an order a forged frame cannot exploit.

    The signature first (a frame that fails changes nothing); then the frame must be
    newer than the last one accepted from its (link id, system, component) stream, or,
    first of its stream, at most NEW_STREAM_WINDOW behind our own timestamp. Only then
    is its timestamp recorded, and ours raised to it.
    """
    signing = mav.signing
    if not signature_matches(signing.secret_key, msgbuf):
        return False
    timestamp = int.from_bytes(msgbuf[-12:-6], 'little')
    stream = (msgbuf[-13], src_system, src_component)
    last = signing.stream_timestamps.get(stream)
    if last is not None and timestamp <= last:
        return False   # not newer than its stream: a replay
    if last is None and timestamp + NEW_STREAM_WINDOW < signing.timestamp:
        return False   # a new stream, but over a minute old
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True


def is_signed(frame: bytes) -> bool:
    """Whether a raw frame is MAVLink 2 with a signature block (header incompat flag)."""
    return (len(frame) > 2 and frame[0] == mavlink.PROTOCOL_MARKER_V2
            and bool(frame[2] & mavlink.MAVLINK_IFLAG_SIGNED))


def signature_matches(key: bytes, frame: bytes) -> bool:
    """Whether a signed raw frame's 48-bit signature is the one `key` makes."""
    expected = hashlib.sha256(key + bytes(frame[:-6])).digest()[:6]
    return hmac.compare_digest(expected, bytes(frame[-6:]))


def rejection_cause(key: bytes, frame: bytes) -> str:
    """Why pymavlink dropped a raw frame as 'Invalid signature' on a link signed with `key`:
    UNSIGNED (no signature where one is required), BAD_SIGNATURE (made with another key,
    or forged) or OLD_TIMESTAMP (our key, but not newer than its stream: a replay)."""
    if not is_signed(frame):
        return UNSIGNED
    return OLD_TIMESTAMP if signature_matches(key, frame) else BAD_SIGNATURE


def load_signing_key(path: str | Path) -> bytes:
    """The 32-byte MAVLink 2 signing key stored in a file.

    The file holds 64 hex digits, 32 raw bytes, or a passphrase that is hashed with
    SHA-256 (as MAVProxy's `signing setup PASSPHRASE` does). The key itself never
    appears in an error message.
    """
    data = Path(path).read_bytes()
    try:
        text = data.decode().strip()
    except UnicodeDecodeError:
        if len(data) == 32:
            return data
        raise ValueError(f'signing key file {path}: binary, but not 32 bytes') from None
    if len(text) == 64 and all(c in '0123456789abcdefABCDEF' for c in text):
        return bytes.fromhex(text)
    if not text:
        raise ValueError(f'signing key file {path} is empty')
    return hashlib.sha256(text.encode()).digest()


def key_file_exposure(path: str | Path) -> str | None:
    """What is wrong with a key file that group or others may read or write (as ssh checks
    its private keys), or None. Anyone who can read the key can command the vehicle."""
    mode = stat.S_IMODE(Path(path).stat().st_mode)
    who = [name for name, bits in (('group', 0o070), ('others', 0o007)) if mode & bits]
    if not who:
        return None
    return (f'signing key file {path} is accessible by {" and ".join(who)} (mode {mode:04o}); '
            f'anyone who can read it can command the vehicle: chmod 600 {path}')
