"""MAVLink 2 through pymavlink: dialect, connections and signing keys.

Importing this module selects MAVLink 2 (signing needs it) and the ardupilotmega
dialect (a superset of common, so it speaks to PX4 too) before any connection is
made; the relay session and the simulated vehicle both go through it.
"""
import hashlib
import os
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


def open_connection(device: str, baud: int = 115200, source_system: int = 255,
                    source_component: int = mavlink.MAV_COMP_ID_MISSIONPLANNER) -> mavutil.mavfile:
    """A pymavlink connection: udpin:/udpout:/udp:HOST:PORT, tcp:HOST:PORT, tcpin:, or a serial device.

    A TCP client tries once (no blocking retry loop); the caller decides when to retry.
    """
    return mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                      source_component=source_component, retries=0,
                                      autoreconnect=False)


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

