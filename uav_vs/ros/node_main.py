"""Start-up and shutdown shared by every node, and its diagnostics helper."""
import ctypes
import sys
import time
from typing import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher

from uav_vs.ros.params_file import check_params_files

# For create_publisher(event_callbacks=...): no event handlers. rclpy's two default ones
# (they log an incompatible QoS or type) are polled on every executor wake, ~10 us each;
# the subscribing side reports the same mismatches.
NO_PUBLISHER_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_HEAP_KEEP_BYTES = 32 << 20


def keep_freed_memory() -> None:
    """Let glibc's malloc reuse freed image-sized buffers instead of returning them to the OS.

    Every message taken allocates and frees a few buffers of the image's size; by
    default glibc unmaps or trims them on free, so the next frame page-faults them
    back (~640 faults, ~2 ms per 640x480 bgr8 image on 2 cores). Buffers up to 32 MiB
    now stay in the heap. A no-op where the C library has no mallopt.
    """
    mallopt = getattr(ctypes.CDLL(None), 'mallopt', None)
    if mallopt is not None:
        mallopt(_M_MMAP_THRESHOLD, _HEAP_KEEP_BYTES)
        mallopt(_M_TRIM_THRESHOLD, _HEAP_KEEP_BYTES)


def run(factory: Callable[[], Node], name: str, args: list[str] | None = None) -> None:
    """Keep freed memory, rclpy.init, build the node, spin until SIGINT/SIGTERM, shut down.

    A configuration error (a `--params-file` that rcl would refuse: missing, not
    YAML, a list of mixed types; or a ValueError raised while the node is being
    built) is logged as one FATAL line naming the parameter and exits with status 2.
    """
    keep_freed_memory()
    problem = check_params_files(sys.argv if args is None else args)
    if problem is not None:
        rclpy.logging.get_logger(name).fatal(problem)
        sys.exit(2)
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
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class QuietPublisherNode(Node):
    """A Node whose publishers, /parameter_events included, default to NO_PUBLISHER_EVENTS."""

    def create_publisher(self, *args, **kwargs) -> Publisher:
        kwargs.setdefault('event_callbacks', NO_PUBLISHER_EVENTS)
        return super().create_publisher(*args, **kwargs)


class Diagnostics:
    """Publishes one DiagnosticStatus for a node on /diagnostics."""

    def __init__(self, node: Node, hardware_id: str = '') -> None:
        self._node = node
        self._pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10,
                                          event_callbacks=NO_PUBLISHER_EVENTS)
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
