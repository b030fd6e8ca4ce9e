"""Probes run on either side of uav_vs.sim.radio_link (test_radio_link.py).

    radio_probe.py udp-send HOST PORT N RATE     N datagrams (sequence, send time)
    radio_probe.py udp-receive PORT SECONDS      prints 'ready', then {sequence: delay}
                                                 once SECONDS pass without one
    radio_probe.py ros-talk N                    N PoseStamped on /ground/pose at 30 Hz
    radio_probe.py ros-listen N SECONDS          prints {sequence: stamp -> receipt} once
                                                 message N - 1 came, or SECONDS passed

Both namespaces share the machine's monotonic and system clocks, so a delay is a
difference of two readings.
"""
import json
import socket
import struct
import sys
import time


def udp_send(host: str, port: int, n: int, rate: float) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for i in range(n):
        sock.sendto(struct.pack('!Id', i, time.monotonic()), (host, port))
        time.sleep(1.0 / rate)


def udp_receive(port: int, seconds: float) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(('0.0.0.0', port))
    sock.settimeout(seconds)
    print('ready', flush=True)
    delays = {}
    try:
        while True:
            data = sock.recv(64)
            i, sent = struct.unpack('!Id', data)
            delays[i] = time.monotonic() - sent
    except socket.timeout:
        pass
    print(json.dumps(delays))


def ros(mode: str, n: int, seconds: float = 0.0) -> None:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node(f'radio_probe_{mode}')
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    if mode == 'talk':
        pub = node.create_publisher(PoseStamped, '/ground/pose', qos)
        for i in range(n):
            msg = PoseStamped()
            msg.header.stamp = node.get_clock().now().to_msg()
            msg.header.frame_id = str(i)
            pub.publish(msg)
            time.sleep(1 / 30)
        return
    delays = {}

    def received(msg: PoseStamped) -> None:
        now = node.get_clock().now().nanoseconds
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        delays[int(msg.header.frame_id)] = (now - stamp) * 1e-9

    node.create_subscription(PoseStamped, '/ground/pose', received, qos)
    end = time.monotonic() + seconds
    while time.monotonic() < end and n - 1 not in delays:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps(delays))


if __name__ == '__main__':
    command, args = sys.argv[1], sys.argv[2:]
    if command == 'udp-send':
        udp_send(args[0], int(args[1]), int(args[2]), float(args[3]))
    elif command == 'udp-receive':
        udp_receive(int(args[0]), float(args[1]))
    else:
        ros(command.removeprefix('ros-'), int(args[0]), *map(float, args[1:]))
