"""link_monitor_node: whether the other host is heard, on /diagnostics.

With the ground station and the vehicle on two hosts, the ground side must say when the
radio link is gone, not only the vehicle (whose relay stops it when commands stop). This
node subscribes `link_monitor.topic` (nav_msgs/Odometry; by default autopilot/odom,
which the vehicle's relay publishes at its `odom_rate`) and publishes, every
`link_monitor.diagnostics_period`, OK "heard" while messages come, ERROR "not heard for
X s" once none has come for `link_monitor.timeout` (timed on the steady clock,
uav_vs.ros.liveness), WARN "never heard" before the first; with the counts `messages`,
`outages` (OK to ERROR), `silent` (s since the last message) and `longest_silence`.
Every parameter is read-only.
"""
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

from uav_vs.ros.liveness import Silence
from uav_vs.ros.node_main import ERROR, OK, WARN, Diagnostics, run
from uav_vs.ros.params import Param, T, declare

PARAMS = [
    Param('link_monitor.topic', T.STRING, 'autopilot/odom',
          'what the other host publishes steadily (nav_msgs/Odometry)'),
    Param('link_monitor.timeout', T.DOUBLE, 0.5,
          'the other host is not heard after this long without a message, s', 0.01, 60.0),
    Param('link_monitor.diagnostics_period', T.DOUBLE, 0.2, 'diagnostics period, s',
          0.05, 60.0),
]


class LinkMonitorNode(Node):
    def __init__(self) -> None:
        super().__init__('link_monitor_node')
        p = declare(self, PARAMS)
        self.topic = self.resolve_topic_name(p['link_monitor.topic'])
        self.silence = Silence(p['link_monitor.timeout'], p['link_monitor.timeout'])
        self.counts = dict(messages=0, outages=0)
        self.longest, self.level = 0.0, OK
        self.create_subscription(Odometry, p['link_monitor.topic'], self.on_message,
                                 qos_profile_sensor_data)
        self.diag = Diagnostics(self)
        self.create_timer(p['link_monitor.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(f"watching {self.topic}: not heard after "
                               f"{p['link_monitor.timeout']:g} s")

    def on_message(self, _: Odometry) -> None:
        self.longest = max(self.longest, self.silence.silent_s() or 0.0)
        self.silence.heard()
        self.counts['messages'] += 1

    def publish_diagnostics(self) -> None:
        silent = self.silence.silent_s()
        if silent is None:
            level, message = WARN, f'never heard on {self.topic}'
        elif (level := self.silence.level()) == OK:
            message = f'heard on {self.topic}'
        else:
            message = f'not heard on {self.topic} for {silent:.1f} s'
        if level == ERROR and self.level != ERROR:
            self.counts['outages'] += 1
            self.get_logger().error(message)
        elif level == OK and self.level == ERROR:
            self.get_logger().info(f'{message} again')
        self.level = level
        self.diag.publish(level, message, {
            **self.counts, 'silent': 'none' if silent is None else f'{silent:.2f}',
            'longest_silence': f'{max(self.longest, silent or 0.0):.2f}'})


def main(args: list[str] | None = None) -> None:
    run(LinkMonitorNode, 'link_monitor_node', args)


if __name__ == '__main__':
    main()
