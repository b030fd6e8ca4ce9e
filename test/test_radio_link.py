"""uav_vs.sim.radio_link: two hosts in network namespaces joined by a delaying, lossy link.

A Channel against its model (uniform delay, in order, its share lost, nothing while
cut); then, in real namespaces, datagrams and a ROS topic across the forwarder: every
delay measured by the receiver against the sender's reading of the same clock, every
loss counted, against what the forwarder says it applied."""
import json
import math
import os
import random
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from conftest import REPO
from uav_vs.sim.radio_link import Channel, LinkConfig, TwoHosts

PROBE = [sys.executable, str(Path(__file__).with_name('radio_probe.py'))]
DEFAULT = LinkConfig()           # 20 +- 10 ms, 2 % loss


def test_a_channel_delays_uniformly_in_order_and_loses_its_share():
    channel, n, period = Channel(DEFAULT, random.Random(1)), 20000, 1.0
    dues = [channel.admit(k * period, 100, cut=False) for k in range(n)]
    kept = [(k, due) for k, due in enumerate(dues) if due is not None]
    lost = n - len(kept)
    assert abs(lost - n * DEFAULT.loss) < 4 * math.sqrt(n * DEFAULT.loss * (1 - DEFAULT.loss))
    assert channel.stats.lost == lost and channel.stats.packets == n
    # Packets ten time constants apart: independent delays, uniform over delay +- jitter.
    delays = [due - k * period for k, due in kept]
    assert stats.kstest(delays, stats.uniform(0.010, 0.020).cdf).pvalue > 1e-3
    # 1 ms apart they leave in order, none early or late, and together: the delay
    # wanders, so a burst is not held back to the latest delay drawn in it.
    burst = Channel(LinkConfig(loss=0.0), random.Random(2))
    dues = [burst.admit(k * 0.001, 100, cut=False) for k in range(100000)]
    assert dues == sorted(dues)
    delays = np.array(dues) - 0.001 * np.arange(len(dues))
    assert delays.min() >= 0.010 and delays.max() <= 0.030
    assert abs(delays.mean() - DEFAULT.delay) < 0.001, delays.mean()
    assert burst.admit(200.0, 100, cut=True) is None and burst.stats.cut == 1


@pytest.fixture
def two_hosts(tmp_path):
    """TwoHosts(config) with its stats file; skips (fails under CI) where network
    namespaces or TUN devices cannot be made."""
    reason = None
    if os.geteuid() != 0 or shutil.which('ip') is None or not Path('/dev/net/tun').exists():
        reason = ('network namespaces and TUN devices need root, iproute2 and /dev/net/tun: '
                  'run the tests as root, or in a container with CAP_NET_ADMIN and '
                  'CAP_SYS_ADMIN and /dev/net/tun')
    if reason:
        if os.environ.get('CI'):
            pytest.fail(reason)
        pytest.skip(reason)

    def make(config: LinkConfig, seed: int = 0) -> TwoHosts:
        return TwoHosts(f'{os.getpid()}', config, seed, stats=tmp_path / 'link.json')
    return make


def _receive(hosts: TwoHosts, seconds: float) -> subprocess.Popen:
    rx = subprocess.Popen([*hosts.exec('air'), *PROBE, 'udp-receive', '9000', str(seconds)],
                          stdout=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)
    assert rx.stdout.readline().strip() == 'ready'
    return rx


def _send(hosts: TwoHosts, n: int, rate: float) -> None:
    subprocess.run([*hosts.exec('ground'), *PROBE, 'udp-send', hosts.address('air'), '9000',
                    str(n), str(rate)], check=True, timeout=60, stdin=subprocess.DEVNULL)


def test_datagrams_cross_with_the_delay_and_loss_the_link_applied(two_hosts):
    with two_hosts(DEFAULT, seed=3) as hosts:
        rx = _receive(hosts, 2.0)
        _send(hosts, 1000, 500.0)
        measured = {int(k): v for k, v in json.loads(rx.communicate(timeout=60)[0]).items()}
    applied = hosts.stats()['ground_to_air']
    assert applied['packets'] == 1000 and applied['cut'] == 0
    assert len(measured) == 1000 - applied['lost']
    assert abs(applied['lost'] - 20) < 4 * math.sqrt(20 * 0.98)
    delays = np.array(applied['delays'])
    assert len(delays) == len(measured)
    assert delays.min() >= DEFAULT.delay - DEFAULT.jitter
    assert delays.max() <= DEFAULT.delay + DEFAULT.jitter
    # Each datagram spent at least its own delay between the two clock readings.
    assert np.all(np.sort(list(measured.values())) >= np.sort(delays))


def test_a_cut_link_drops_everything_until_it_is_restored(two_hosts):
    with two_hosts(DEFAULT, seed=4) as hosts:
        rx = _receive(hosts, 2.0)
        cutter = threading.Thread(target=lambda: (time.sleep(1.0), hosts.cut(True),
                                                  time.sleep(1.0), hosts.cut(False)))
        cutter.start()
        _send(hosts, 300, 100.0)                     # 3 s or more
        cutter.join()
        got = {int(k) for k in json.loads(rx.communicate(timeout=60)[0])}
    applied = hosts.stats()['ground_to_air']
    missing = sorted(set(range(300)) - got)
    assert applied['cut'] > 0 and len(missing) == applied['cut'] + applied['lost']
    runs = np.split(np.array(missing), np.flatnonzero(np.diff(missing) != 1) + 1)
    cut = max(runs, key=len)                     # runs of consecutive missing datagrams
    assert len(cut) >= applied['cut']            # the cut is one stretch ...
    assert max(got) > cut[-1]                    # ... and the link came back after it

def test_a_ros_topic_crosses_by_static_peers_once_with_the_links_delay(two_hosts):
    with two_hosts(DEFAULT, seed=5) as hosts:
        rx = subprocess.Popen([*hosts.exec('air'), *PROBE, 'ros-listen', '150', '15'],
                              stdout=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
                              env={**os.environ, **hosts.ros_env('air')})
        subprocess.run([*hosts.exec('ground'), *PROBE, 'ros-talk', '150'], check=True,
                       timeout=60, stdin=subprocess.DEVNULL,
                       env={**os.environ, **hosts.ros_env('ground')})
        delays = {int(k): v for k, v in json.loads(rx.communicate(timeout=60)[0]).items()}
    applied = hosts.stats()['ground_to_air']
    assert len(delays) > 50, delays
    # Every message crossed the link (nothing took another way round it) ...
    assert min(delays.values()) >= DEFAULT.delay - DEFAULT.jitter
    # ... once: the listener's data port got a packet per message, and a few of the
    # graph's own (ros_discovery_info), so a packet the link drops is a message lost ...
    assert max(applied['ports'].values()) <= 150 * 1.2, applied['ports']
    # ... and best effort lost no more than the link dropped, once discovery was done.
    missing = set(range(min(delays), 150)) - set(delays)
    assert len(missing) <= applied['lost']
