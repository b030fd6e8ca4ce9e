"""MAVLink relay node benchmarks: a cmd_vel message until its MAVLink datagram is on the wire.

The relay runs as its own process (console script + config/mavlink_relay.yaml), connected
over loopback UDP to a bare endpoint here that sends ArduPilot heartbeats. Arrival times
are the kernel's receive timestamps of the SET_POSITION_TARGET_LOCAL_NED datagrams
(SO_TIMESTAMPNS), on the same clock as the publish times (time.time()), so a busy
publishing thread in this process does not delay them. Each cmd_vel carries its
sequence number in the velocity, so a datagram is matched to the message it came from
(the relay's 10 Hz re-sends of the same setpoint are not counted twice).

`mavlink/cmd_vel_latency`: publish (test-side node, Fast DDS shared memory) -> relay
callback -> Session.send_velocity -> datagram read here; median and p95. Reference:
the core's Session.send_velocity called directly in this process.
`mavlink/cmd_vel_rate`: cmd_vel published at 50 Hz and back to back; the figure is the
interval between delivered setpoints at the wire, with the fraction delivered (the relay
queues the last 10 cmd_vel, and writes at most `max_send_rate` setpoints a second, 50 Hz:
back to back, older ones are dropped or coalesced).
Target: p95 <= 2 ms, 50 Hz sustained with nothing lost.
"""
import math
import os
import socket
import struct
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import TwistStamped

from bench.common import report
from bench.mavlink import SET_POSITION_TARGET, Vehicle
from uav_vs import graph
from uav_vs.autopilot.link import mavlink
from uav_vs.autopilot.session import Limits, Session, SessionConfig

SUITE = 'mavlink'
CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'mavlink_relay.yaml'
SO_TIMESTAMPNS = 35  # Linux; not exported by the socket module
STEP = 0.001  # m/s per sequence number, carried in the ENU y (NED x) velocity (< 30 m/s)


class Recorder(Vehicle):
    """The bare endpoint, recording the arrival time of each sequence number's first setpoint."""

    def __init__(self):
        super().__init__()
        self.arrivals: dict[int, float] = {}
        self.parser = mavlink.MAVLink(None)
        self.reader = threading.Thread(target=self._read, daemon=True)

    def _read(self):
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.sock.settimeout(0.2)
        while not self.stop.is_set():
            try:
                data, ancillary, _, peer = self.sock.recvmsg(512, socket.CMSG_SPACE(16))
            except (TimeoutError, OSError):
                continue
            sec, nsec = struct.unpack('qq', ancillary[0][2])
            t = sec + nsec * 1e-9
            self.peer = peer
            if data[0] != 0xFD or int.from_bytes(data[7:10], 'little') != SET_POSITION_TARGET:
                continue
            msg = self.parser.parse_char(data)
            seq = round(msg.vx / STEP)
            if seq > 0:
                self.arrivals.setdefault(seq, t)

    def start(self):
        self.thread.start()
        self.reader.start()
        return self

    def close(self):
        self.stop.set()
        self.reader.join(timeout=1.0)
        self.sock.close()


def _ros_domain() -> None:
    """A domain of our own unless one is set (tests use 1..200)."""
    os.environ.setdefault('ROS_DOMAIN_ID', str(201 + os.getpid() % 30))


def _publish_series(pub, first: int, count: int, period: float | None,
                    sent: dict[int, float]) -> None:
    """Publish `count` world cmd_vel numbered from `first`, every `period` s (None: at once)."""
    msg = TwistStamped()
    msg.header.frame_id = 'world'
    next_t = time.perf_counter()
    for seq in range(first, first + count):
        msg.twist.linear.y = seq * STEP
        if period is not None:
            next_t += period
        sent[seq] = time.time()
        pub.publish(msg)
        if period is not None:
            time.sleep(max(0.0, next_t - time.perf_counter()))


def _latencies(sent: dict[int, float], arrivals: dict[int, float], seqs) -> np.ndarray:
    return np.array([(arrivals[s] - sent[s]) * 1e3 for s in seqs if s in arrivals])


def relay_cases(latency_n: int = 500, rate_seconds: float = 4.0) -> None:
    """Both cases against one relay process; the reference in this process."""
    _ros_domain()
    endpoint = Recorder().start()
    conn = f'udpout:127.0.0.1:{endpoint.port}'
    # the reference first, alone on the endpoint: the core called directly
    ref_sent: dict[int, float] = {}
    base = 10
    with Session(SessionConfig(connection=conn, rates={}, command_timeout=2.5,
                               limits=Limits(max_speed=30.0),
                               max_send_rate=math.inf)) as session:   # every call sent
        session.wait_connected(10.0)
        for seq in range(base, base + latency_n):
            ref_sent[seq] = time.time()
            session.send_velocity([0.0, seq * STEP, 0.0])
            time.sleep(0.002)
        time.sleep(0.2)
    ref = _latencies(ref_sent, endpoint.arrivals, range(base, base + latency_n))
    base += latency_n

    log_dir = Path(tempfile.mkdtemp(prefix='bench_relay_'))
    relay = graph.start('mavlink_relay_node', [
        '--params-file', str(CONFIG), '-p', f'connection:={conn}', '-p', 'limits.max_speed:=30.0',
        '-p', 'command_timeout:=2.5'], log_dir, 'relay')
    rclpy.init()
    node = rclpy.create_node('bench_cmd_vel')
    try:
        pub = node.create_publisher(TwistStamped, 'cmd_vel', 10)
        deadline = time.monotonic() + 30.0
        while pub.get_subscription_count() == 0 or 1 not in endpoint.arrivals:
            if time.monotonic() > deadline or relay.poll() is not None:
                raise RuntimeError(f'relay not ready; see {log_dir}/relay.log')
            _publish_series(pub, 1, 1, None, {})   # until one gets through: link up, subscribed
            time.sleep(0.1)

        sent: dict[int, float] = {}
        _publish_series(pub, base, latency_n, 0.02, sent)   # 50 Hz, one at a time on the wire
        time.sleep(0.2)
        ours = _latencies(sent, endpoint.arrivals, range(base, base + latency_n))
        report(SUITE, 'mavlink/cmd_vel_latency', ours, 'Session.send_velocity in-process', ref,
               delivered=f'{len(ours)}/{latency_n}', target_p95_ms=2.0)

        base += latency_n
        for label, period in (('50 Hz', 0.02), ('max', None)):
            count = int(rate_seconds * 50) if period else 15000  # ids stay below 30 m/s
            sent = {}
            t0 = time.perf_counter()
            if period:
                _publish_series(pub, base, count, period, sent)
            else:
                while time.perf_counter() - t0 < rate_seconds and len(sent) < count:
                    _publish_series(pub, base + len(sent), 100, None, sent)
            elapsed = time.perf_counter() - t0
            time.sleep(0.3)
            got = sorted(endpoint.arrivals[s] for s in sent if s in endpoint.arrivals)
            report(SUITE, 'mavlink/cmd_vel_rate', np.diff(got) * 1e3, publish=label,
                   published_hz=round(len(sent) / elapsed, 1), delivered=f'{len(got)}/{len(sent)}',
                   delivered_hz=round(len(got) / elapsed, 1))
            base += len(sent)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        graph.stop([relay])
        endpoint.close()


def main() -> None:
    relay_cases()


if __name__ == '__main__':
    main()
