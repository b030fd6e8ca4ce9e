"""Start-up and shutdown shared by every node, and its diagnostics helper."""
import sys
import time
from typing import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node


def run(factory: Callable[[], Node], name: str, args: list[str] | None = None,
        threads: int = 1) -> None:
    """rclpy.init, build the node, spin until SIGINT/SIGTERM, shut down.

    A configuration error (ValueError) raised while the node is being built is
    logged as one FATAL line naming the parameter and exits with status 2.
    `threads` > 1 spins a MultiThreadedExecutor, for nodes whose callback groups
    let slow callbacks run beside fast ones.
    """
    rclpy.init(args=args)
    try:
        node = factory()
    except ValueError as err:
        rclpy.logging.get_logger(name).fatal(str(err))
        rclpy.try_shutdown()
        sys.exit(2)
    except (KeyboardInterrupt, ExternalShutdownException):
        rclpy.try_shutdown()
        return
    try:
        rclpy.spin(node, MultiThreadedExecutor(threads) if threads > 1 else None)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class Diagnostics:
    """Publishes one DiagnosticStatus for a node on /diagnostics."""

    def __init__(self, node: Node, hardware_id: str = '') -> None:
        self._node = node
        self._pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._name = node.get_fully_qualified_name()
        self._hardware_id = hardware_id

    def publish(self, level: int, message: str, values: dict[str, object]) -> None:
        status = DiagnosticStatus(level=bytes([level]), name=self._name, message=message,
                                  hardware_id=self._hardware_id,
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)


OK, WARN, ERROR = (int.from_bytes(x, 'little') for x in
                   (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR))


class ThrottledWarnings:
    """At most one warning per kind of defect every `period_s` (rclpy throttles per call
    site, which would let one kind of bad input hide another)."""

    def __init__(self, node: Node, period_s: float = 5.0) -> None:
        self._node, self._period = node, period_s
        self._next: dict[str, float] = {}

    def warn(self, kind: str, text: str) -> None:
        now = time.monotonic()
        if now >= self._next.get(kind, 0.0):
            self._next[kind] = now + self._period
            self._node.get_logger().warn(text)
