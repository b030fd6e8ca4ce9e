"""config/fastdds_shm.xml keeps the graph off the network: DDS receives on loopback only."""
import os
from pathlib import Path

from conftest import REPO, wait_for

PROFILE = REPO / 'config' / 'fastdds_shm.xml'


def udp_sockets(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every IPv4 UDP socket the process holds, from /proc."""
    inodes = set()
    for fd in Path(f'/proc/{pid}/fd').iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith('socket:['):
            inodes.add(target[8:-1])
    sockets = []
    for line in Path('/proc/net/udp').read_text().splitlines()[1:]:
        fields = line.split()
        if fields[9] in inodes:
            host, port = fields[1].split(':')
            address = '.'.join(str(int(host[i:i + 2], 16)) for i in (6, 4, 2, 0))
            sockets.append((address, int(port, 16)))
    return sockets


def ephemeral_ports() -> range:
    low, high = map(int, Path('/proc/sys/net/ipv4/ip_local_port_range').read_text().split())
    return range(low, high + 1)


def domain_ports(domain: int) -> range:
    """The RTPS well-known ports of a domain: 7400 + 250 d + (0..249) (RTPS 2.2, 9.6.1.1)."""
    return range(7400 + 250 * domain, 7400 + 250 * (domain + 1))


def test_nodes_receive_dds_traffic_on_loopback_only(ros_node, processes):
    """Every port a participant announces (the domain's well-known ports) and every other
    fixed port is bound to 127.0.0.1; only Fast DDS's send sockets, on kernel-chosen
    ports, are not. The node is still found on this host."""
    assert os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(PROFILE)
    proc = processes('fuzzy_controller_node', ['--params-file',
                                               str(REPO / 'config' / 'fuzzy_controller.yaml')])
    assert wait_for(lambda: 'fuzzy_controller_node' in ros_node.get_node_names(), 20.0)
    sockets = udp_sockets(proc.pid)
    domain = domain_ports(int(os.environ['ROS_DOMAIN_ID']))
    assert any(port in domain for _, port in sockets), sockets
    fixed = [(a, p) for a, p in sockets if p in domain or p not in ephemeral_ports()]
    assert all(address == '127.0.0.1' for address, _ in fixed), sockets
