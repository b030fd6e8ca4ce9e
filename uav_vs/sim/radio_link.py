"""A radio link between two hosts, made in user space: delay, jitter, loss and cuts.

The ground station's computer and the vehicle's are two network namespaces. A kernel
with netem would impair a veth pair between them (`tc qdisc add ... netem delay 20ms
10ms loss 2%`); without it, each namespace gets a TUN device and this forwarder carries
every IP packet from one to the other, holding it for its delay or dropping it:

    ground ns  radio0 10.77.0.1  <->  forwarder (root ns)  <->  radio0 10.77.0.2  air ns

Each direction is a `Channel`: a packet is lost with probability `loss`, or held
`delay` +- `jitter`, uniformly spread as with netem's `delay D J`, and never overtakes
the packet before it (a radio's MAC delivers in order). netem draws each packet's delay
on its own and lets packets overtake; here the delay wanders in time instead (a
Gauss-Markov process of time constant `jitter_time`, mapped onto the uniform spread),
so that packets sent together, as DDS sends a message's fragments and its heartbeats,
leave together rather than all at the latest of their delays. While the link is cut
every packet is dropped. The forwarder records what it really applied, per packet, for the tests.
Both TUN devices are named `radio0`, so one Fast DDS profile (config/fastdds_radio.xml)
serves both hosts.

    python -m uav_vs.sim.radio_link --ground G --air A [--delay 0.02 --jitter 0.01
        --loss 0.02] [--stats FILE]

runs it between two existing namespaces until SIGINT or SIGTERM (then writes FILE);
SIGUSR1 cuts the link, SIGUSR2 restores it. `TwoHosts` makes the namespaces, starts
the forwarder and removes both again. It also joins them by a second, perfect wire,
`world0` (a veth pair, 10.78.0.0/24), for the simulator alone: the vehicle's true state
that the ground cameras are rendered from (light does not travel by radio). DDS never
uses it: config/fastdds_radio.xml allows the loopback and radio0 only.
"""
import argparse
import fcntl
import heapq
import itertools
import json
import math
import os
import random
import select
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from uav_vs.sim import netns
from uav_vs.vision.ground_config import default_config_path

TUNSETIFF = 0x400454CA
IFF_TUN, IFF_NO_PI = 0x0001, 0x1000
MTU = 1500
SUBNET = '10.77.0'
INTERFACE = 'radio0'
WORLD_SUBNET, WORLD_INTERFACE = '10.78.0', 'world0'


@dataclass(frozen=True)
class LinkConfig:
    """One direction's impairment; the same both ways."""

    delay: float = 0.020         # s, mean one-way delay
    jitter: float = 0.010        # s, half-width of the uniform spread around it
    loss: float = 0.02           # probability that a packet is lost
    jitter_time: float = 0.1     # s, time constant of the delay's wander

    def __post_init__(self) -> None:
        if not (self.delay >= 0 and 0 <= self.jitter <= self.delay and 0 <= self.loss < 1
                and self.jitter_time > 0):
            raise ValueError('expected 0 <= jitter <= delay, 0 <= loss < 1 and '
                             f'jitter_time > 0, got {self}')


@dataclass
class ChannelStats:
    packets: int = 0             # packets that entered the channel
    bytes: int = 0
    lost: int = 0                # dropped at random
    cut: int = 0                 # dropped while the link was cut
    delays: list[float] = field(default_factory=list)  # s, each admitted packet's delay
    held: list[float] = field(default_factory=list)    # s, each delivered packet's stay
    ports: dict[int, int] = field(default_factory=dict)  # UDP packets per destination port


class Channel:
    """One direction of the link: which packets arrive, and when."""

    def __init__(self, config: LinkConfig, rng: random.Random) -> None:
        self.config, self.rng = config, rng
        self.stats = ChannelStats()
        self._last_due = -float('inf')
        self._z, self._z_time = rng.gauss(0.0, 1.0), None      # the wander, N(0, 1)

    def admit(self, now: float, size: int, cut: bool, port: int | None = None) -> float | None:
        """The time a packet entering at `now` leaves the link; None if it is lost.
        `port` is its UDP destination port, counted to tell what crossed."""
        self.stats.packets += 1
        self.stats.bytes += size
        if port is not None:
            self.stats.ports[port] = self.stats.ports.get(port, 0) + 1
        if cut:
            self.stats.cut += 1
            return None
        if self.rng.random() < self.config.loss:
            self.stats.lost += 1
            return None
        c = self.config
        if self._z_time is not None:                 # Gauss-Markov step over the gap
            a = math.exp(-max(0.0, now - self._z_time) / c.jitter_time)
            self._z = a * self._z + math.sqrt(1.0 - a * a) * self.rng.gauss(0.0, 1.0)
        self._z_time = now
        spread = math.erf(self._z / math.sqrt(2.0))  # uniform on (-1, 1)
        due = max(now + c.delay + c.jitter * spread, self._last_due)
        self._last_due = due
        self.stats.delays.append(due - now)
        return due


def udp_port(packet: bytes) -> int | None:
    """The destination port of an IPv4 UDP packet; None for anything else."""
    if len(packet) < 24 or packet[0] >> 4 != 4 or packet[9] != socket.IPPROTO_UDP:
        return None
    header = (packet[0] & 0x0F) * 4
    return int.from_bytes(packet[header + 2:header + 4], 'big')


def open_tun(name: str) -> int:
    """A TUN device `name` (IP packets, no header) in this process's namespace."""
    fd = os.open('/dev/net/tun', os.O_RDWR | os.O_NONBLOCK)
    fcntl.ioctl(fd, TUNSETIFF, struct.pack('16sH', name.encode(), IFF_TUN | IFF_NO_PI))
    return fd


class Forwarder:
    """Carries packets between two TUN devices through a Channel each way."""

    def __init__(self, fds: tuple[int, int], config: LinkConfig, seed: int = 0) -> None:
        rng = random.Random(seed)
        self.fds = fds
        self.channels = {fds[0]: Channel(config, random.Random(rng.random())),
                         fds[1]: Channel(config, random.Random(rng.random()))}
        self.cut = False
        self.running = True
        self._queue: list[tuple[float, int, int, bytes, float, Channel]] = []
        self._order = itertools.count()

    def run(self) -> None:
        while self.running:
            timeout = 0.1
            if self._queue:
                timeout = max(0.0, self._queue[0][0] - time.monotonic())
            ready, _, _ = select.select(self.fds, [], [], timeout)
            for fd in ready:
                self._read(fd)
            self._deliver()

    def _read(self, fd: int) -> None:
        out = self.fds[1] if fd == self.fds[0] else self.fds[0]
        channel = self.channels[fd]
        while True:
            try:
                packet = os.read(fd, MTU + 64)
            except BlockingIOError:
                return
            now = time.monotonic()
            due = channel.admit(now, len(packet), self.cut, udp_port(packet))
            if due is not None:
                heapq.heappush(self._queue, (due, next(self._order), out, packet, now, channel))

    def _deliver(self) -> None:
        while self._queue and self._queue[0][0] <= time.monotonic():
            _, _, out, packet, entered, channel = heapq.heappop(self._queue)
            try:
                os.write(out, packet)
            except OSError:
                continue                 # the device went down: the packet is gone
            channel.stats.held.append(time.monotonic() - entered)


def ip(*args: str) -> None:
    subprocess.run(['ip', *args], check=True, capture_output=True, text=True)


def place(device: str, ns: str, name: str, cidr: str) -> None:
    """Move `device` into namespace `ns` as `name`, IPv4 address `cidr` only (no IPv6:
    nothing but what the hosts send crosses), and bring it up."""
    ip('link', 'set', 'dev', device, 'netns', ns)
    ip('-n', ns, 'link', 'set', 'dev', device, 'name', name)
    subprocess.run([*netns.exec_prefix(ns), 'sysctl', '-q', '-w',
                    f'net.ipv6.conf.{name}.disable_ipv6=1'], check=True)
    ip('-n', ns, 'addr', 'add', cidr, 'dev', name)
    ip('-n', ns, 'link', 'set', 'dev', name, 'up')


def address(host: int) -> str:
    """Address of host 1 (ground) or 2 (air) on the link."""
    return f'{SUBNET}.{host}'


def serve(ground: str, air: str, config: LinkConfig, seed: int, stats: Path | None) -> None:
    """Run the link between namespaces `ground` and `air` until SIGINT or SIGTERM."""
    names = (f'uvs{os.getpid()}g', f'uvs{os.getpid()}a')
    fds = (open_tun(names[0]), open_tun(names[1]))
    for host, (ns, name) in enumerate(zip((ground, air), names), start=1):
        place(name, ns, INTERFACE, f'{address(host)}/24')
    forwarder = Forwarder(fds, config, seed)

    def stop(*_) -> None:
        forwarder.running = False

    def cut(on: bool) -> None:
        forwarder.cut = on

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGUSR1, lambda *_: cut(True))
    signal.signal(signal.SIGUSR2, lambda *_: cut(False))
    print(f'link up: {ground} {address(1)} <-> {air} {address(2)}, {config}', flush=True)
    start = time.monotonic()
    forwarder.run()
    if stats is not None:
        stats.write_text(json.dumps({
            'config': asdict(config), 'seconds': time.monotonic() - start,
            'ground_to_air': asdict(forwarder.channels[fds[0]].stats),
            'air_to_ground': asdict(forwarder.channels[fds[1]].stats)}))


class TwoHosts:
    """Two network namespaces joined by the radio link, removed again on exit.

    `with TwoHosts('t1', LinkConfig()) as hosts: subprocess.run([*hosts.exec('air'), ...],
    env={**os.environ, **hosts.ros_env('air')})`
    """

    def __init__(self, tag: str, config: LinkConfig, seed: int = 0,
                 stats: Path | None = None) -> None:
        self.names = {'ground': f'uvs-{tag}-ground', 'air': f'uvs-{tag}-air'}
        self.config, self.seed, self.stats_path = config, seed, stats
        self.forwarder: subprocess.Popen | None = None

    def __enter__(self) -> 'TwoHosts':
        try:
            for ns in self.names.values():
                netns.add(ns)
            self._wire()
            argv = [sys.executable, '-m', 'uav_vs.sim.radio_link',
                    '--ground', self.names['ground'], '--air', self.names['air'],
                    '--delay', str(self.config.delay), '--jitter', str(self.config.jitter),
                    '--loss', str(self.config.loss),
                    '--jitter-time', str(self.config.jitter_time), '--seed', str(self.seed)]
            if self.stats_path is not None:
                argv += ['--stats', str(self.stats_path)]
            self.forwarder = subprocess.Popen(argv, stdin=subprocess.DEVNULL,
                                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                              text=True)
            line = self.forwarder.stdout.readline()
            if not line.startswith('link up'):
                raise RuntimeError(f'the radio link did not start: {line}'
                                   f'{self.forwarder.stdout.read()}')
        except BaseException:
            self.__exit__()
            raise
        return self

    def _wire(self) -> None:
        """The world's wire: a veth pair, one end in each namespace."""
        ends = [f'uvs{os.getpid()}w{host}' for host in (1, 2)]
        ip('link', 'add', ends[0], 'type', 'veth', 'peer', 'name', ends[1])
        for host, (ns, end) in enumerate(zip(self.names.values(), ends), start=1):
            place(end, ns, WORLD_INTERFACE, f'{WORLD_SUBNET}.{host}/24')

    def __exit__(self, *_) -> None:
        if self.forwarder is not None and self.forwarder.poll() is None:
            self.forwarder.send_signal(signal.SIGINT)
            try:
                self.forwarder.wait(10)
            except subprocess.TimeoutExpired:
                self.forwarder.kill()
                self.forwarder.wait()
        for ns in self.names.values():
            netns.delete(ns)

    def address(self, host: str) -> str:
        """`host`'s address on the radio link."""
        return address(1 if host == 'ground' else 2)

    def world_address(self, host: str) -> str:
        """`host`'s address on the world's wire (the simulator's own)."""
        return f"{WORLD_SUBNET}.{1 if host == 'ground' else 2}"

    def exec(self, host: str) -> list[str]:
        """argv prefix that runs a command on `host` ('ground' or 'air')."""
        return netns.exec_prefix(self.names[host])

    def ros_env(self, host: str) -> dict[str, str]:
        """The environment of a ROS process on `host`: config/fastdds_radio.xml, and
        discovery by unicast to the other host and to this one's loopback."""
        other = 'air' if host == 'ground' else 'ground'
        return {'FASTRTPS_DEFAULT_PROFILES_FILE': str(default_config_path('fastdds_radio.xml')),
                'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET',
                'ROS_STATIC_PEERS': f'{self.address(other)};127.0.0.1'}

    def cut(self, on: bool = True) -> None:
        """Cut the link (every packet dropped) or, with on=False, restore it."""
        self.forwarder.send_signal(signal.SIGUSR1 if on else signal.SIGUSR2)

    def stats(self) -> dict:
        """What the forwarder applied (after exit, with `stats` given)."""
        return json.loads(self.stats_path.read_text())


def summary(stats: dict) -> str:
    """What the link did, a line per direction: packets, lost, cut, delay applied."""
    c = stats['config']
    lines = [f"radio link: {c['delay'] * 1e3:.0f} +- {c['jitter'] * 1e3:.0f} ms, "
             f"{c['loss'] * 100:g} % loss, up {stats['seconds']:.0f} s"]
    for direction in ('ground_to_air', 'air_to_ground'):
        d = stats[direction]
        held = sorted(d['held']) or [math.nan]
        p50, p95 = (held[min(len(held) - 1, int(q * len(held)))] * 1e3 for q in (0.5, 0.95))
        lines.append(f"  {direction.replace('_', ' ')}: {d['packets']} packets "
                     f"({d['bytes'] / 1e6:.1f} MB, {d['bytes'] / stats['seconds'] / 1e3:.0f} "
                     f"kB/s), {d['lost']} lost, {d['cut']} cut; "
                     f'held p50 {p50:.1f} ms, p95 {p95:.1f} ms')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--ground', required=True, help='network namespace of the ground host')
    parser.add_argument('--air', required=True, help="network namespace of the vehicle's host")
    parser.add_argument('--delay', type=float, default=LinkConfig.delay, help='one-way delay, s')
    parser.add_argument('--jitter', type=float, default=LinkConfig.jitter,
                        help='uniform jitter around the delay, s')
    parser.add_argument('--loss', type=float, default=LinkConfig.loss,
                        help='probability that a packet is lost')
    parser.add_argument('--jitter-time', type=float, default=LinkConfig.jitter_time,
                        help="time constant of the delay's wander, s")
    parser.add_argument('--seed', type=int, default=0, help='seed of the delays and losses')
    parser.add_argument('--stats', type=Path, help='write what was applied here on exit')
    args = parser.parse_args(argv)
    try:
        config = LinkConfig(args.delay, args.jitter, args.loss, args.jitter_time)
    except ValueError as err:
        parser.error(str(err))
    serve(args.ground, args.air, config, args.seed, args.stats)


if __name__ == '__main__':
    main()
