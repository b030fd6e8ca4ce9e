"""MAVLink relay benchmarks: a velocity command call until its datagram is on a loopback socket.

`mavlink/command_latency`: Session.send_velocity (validation, limits, frame conversion,
packing, send) until the SET_POSITION_TARGET_LOCAL_NED datagram is read at the vehicle's
socket; reference: pymavlink's raw set_position_target_local_ned_send on the same socket.
`mavlink/command_rate`: back-to-back calls, all counted at the receiver.
"""
import math
import socket
import threading
import time

import numpy as np

from bench.common import report
from uav_vs.autopilot.link import mavlink, open_connection
from uav_vs.autopilot.session import Session, SessionConfig

SUITE = 'mavlink'
SET_POSITION_TARGET = mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED


class Vehicle:
    """A bare UDP endpoint that sends ArduPilot heartbeats and counts setpoint datagrams."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.peer = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._heartbeats, daemon=True)

    def _heartbeats(self):
        hb = self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                       mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, mavlink.MAV_STATE_ACTIVE)
        while not self.stop.wait(0.2):
            if self.peer is not None:
                self.sock.sendto(hb.pack(self.mav), self.peer)

    def next_setpoint(self) -> None:
        """Block until the next SET_POSITION_TARGET_LOCAL_NED datagram."""
        while True:
            data = self.sock.recv(512)
            if data[0] == 0xFD and int.from_bytes(data[7:10], 'little') == SET_POSITION_TARGET:
                return

    def drain(self) -> None:
        self.sock.setblocking(False)
        try:
            while True:
                self.sock.recv(512)
        except BlockingIOError:
            pass
        self.sock.setblocking(True)


def latency(send, vehicle: Vehicle, repeat: int = 2000) -> np.ndarray:
    out = np.empty(repeat)
    for k in range(repeat):
        vehicle.drain()
        t0 = time.perf_counter()
        send()
        vehicle.next_setpoint()
        out[k] = (time.perf_counter() - t0) * 1e3
    return out


def main() -> None:
    vehicle = Vehicle()
    vehicle.thread.start()
    vehicle.sock.settimeout(5.0)
    session = Session(SessionConfig(connection=f'udpout:127.0.0.1:{vehicle.port}', rates={},
                                    max_send_rate=math.inf)).start()   # every call sent
    raw = open_connection(f'udpout:127.0.0.1:{vehicle.port}')
    try:
        _, vehicle.peer = vehicle.sock.recvfrom(512)   # the session's heartbeat: where it is
        session.wait_connected(5.0)
        cmd = np.array([0.5, -0.2, 0.1])
        for body in (False, True):
            session.send_velocity(cmd, 0.1, body)
            vehicle.next_setpoint()
        ours = latency(lambda: session.send_velocity(cmd, 0.1), vehicle)
        ref = latency(lambda: raw.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0x05C7, 0, 0, 0, -0.2, 0.5, -0.1, 0, 0, 0, 0, -0.1), vehicle)
        report(SUITE, 'mavlink/command_latency', ours, 'pymavlink raw send', ref)

        n = 5000
        received = [0]

        def count():
            while received[0] < n:
                try:
                    vehicle.next_setpoint()
                except TimeoutError:
                    return
                received[0] += 1
        counter = threading.Thread(target=count)
        vehicle.drain()
        counter.start()
        per_call = np.empty(n)
        for k in range(n):
            t0 = time.perf_counter()
            session.send_velocity(cmd, 0.1)
            per_call[k] = (time.perf_counter() - t0) * 1e3
        counter.join(timeout=10.0)
        report(SUITE, 'mavlink/command_rate', per_call, delivered=f'{received[0]}/{n}')
    finally:
        session.close()
        raw.close()
        vehicle.stop.set()
        vehicle.sock.close()


if __name__ == '__main__':
    main()
