"""Start-up and shutdown shared by every node, and its diagnostics helper.

Every node process spins its node (or nodes, for a process holding several) in one
executor chosen by the environment variable UAV_VS_EXECUTOR:

- `events` (the default): rclpy.experimental.EventsExecutor, event-driven in C++; a
  message costs one callback, with no wait set rebuilt in Python on every wake.
- `single`: rclpy's SingleThreadedExecutor, the wait-set loop `rclpy.spin` runs.

A node that needs one of them passes it to run() and ignores the variable: the
mavlink_relay_node's services await worker threads through `node.executor`, which
EventsExecutor (rclpy 7.1.6) neither sets nor resumes.
"""
import ctypes
import faulthandler
import os
import re
import signal
import sys
import threading
import time
from typing import Callable, NoReturn, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher

from uav_vs import dds_shm
from uav_vs.ros.params_file import check_args

# For create_publisher(event_callbacks=...): no event handlers. rclpy's two default ones
# (they log an incompatible QoS or type) are polled on every executor wake, ~10 us each;
# the subscribing side reports the same mismatches.
NO_PUBLISHER_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)

# A stopping node that has not finished tearing down (rclpy, the DDS participant) after
# this long exits anyway (status 1, its threads' stacks printed): a node asked to stop
# always stops. Destroying the DDS participant was seen to take over 4 s on a loaded
# machine; `ros2 launch` sends SIGTERM after 5 s (which does not cut this short) and
# SIGKILL after 10 s, so the grace ends before that.
SHUTDOWN_GRACE_S = 8.0

EXECUTOR_ENV = 'UAV_VS_EXECUTOR'
EXECUTORS: dict[str, Callable[[], Executor]] = {'events': EventsExecutor,
                                                'single': SingleThreadedExecutor}
DEFAULT_EXECUTOR = 'events'
# Executors spin one callback at a time, and at least this often see whether the context
# is still up: EventsExecutor.spin() (rclpy 7.1.6) never returns once a signal has shut
# the context down.
SPIN_CHECK_S = 0.5

# Set by the first SIGINT: an exception that comes out of rclpy after it is the interrupt.
_INTERRUPTED = threading.Event()

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


def executor_choice(fixed: str | None = None) -> tuple[str, str | None]:
    """`fixed`, else the executor UAV_VS_EXECUTOR names (DEFAULT_EXECUTOR when unset or
    empty), and a one-line problem when it names none of EXECUTORS."""
    choice = fixed or os.environ.get(EXECUTOR_ENV) or DEFAULT_EXECUTOR
    if choice in EXECUTORS:
        return choice, None
    return choice, f'{EXECUTOR_ENV}={choice!r}: expected one of {", ".join(EXECUTORS)}'


def run(factory: Callable[[], Node | Sequence[Node]], name: str,
        args: list[str] | None = None, executor: str | None = None) -> NoReturn:
    """Keep freed memory, rclpy.init, build the node(s), spin them in one executor
    (`executor`, else see executor_choice) until SIGINT/SIGTERM, shut down and
    exit 0 (see _exit_after_shutdown).

    A configuration error (an unknown UAV_VS_EXECUTOR; a `--params-file` or `-p` rule
    that rcl would refuse or silently misread, see params_file; or a ValueError raised
    while a node is being built) is logged as one FATAL line naming the variable, file,
    rule or parameter, and exits with status 2.
    """
    keep_freed_memory()
    faulthandler.enable()   # a crash in native code prints every thread's Python stack
    choice, problem = executor_choice(executor)
    problem = problem or check_args(sys.argv if args is None else args)
    if problem is None:
        # rclpy's SIGINT handler chains to this one: the first Ctrl-C interrupts, later
        # ones (under `ros2 launch` a node gets two) cannot cut the shutdown short.
        signal.signal(signal.SIGINT, _interrupt_once)
        try:
            rclpy.init(args=args)
        except RuntimeError as err:     # rcl refused an argument the checks let through
            problem = _rcl_refusal(str(err))
    if problem is not None:
        rclpy.logging.get_logger(name).fatal(problem)
        sys.exit(2)
    try:
        built = factory()
    except ValueError as err:
        rclpy.logging.get_logger(name).fatal(str(err))
        rclpy.try_shutdown()
        sys.exit(2)
    except (KeyboardInterrupt, ExternalShutdownException, RuntimeError) as err:
        # A SIGINT while the node is being built shuts the context down under it.
        if isinstance(err, RuntimeError) and not _INTERRUPTED.is_set():
            raise
        rclpy.try_shutdown()
        _exit_after_shutdown()
    nodes = [built] if isinstance(built, Node) else list(built)
    spinner = EXECUTORS[choice]()
    try:
        for node in nodes:
            spinner.add_node(node)
        while rclpy.ok():
            spinner.spin_once(timeout_sec=SPIN_CHECK_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # A SIGINT while rclpy's C++ converts a message taken comes out as RuntimeError
        # ("Unable to convert call argument"), as does a take from a context shut down.
        if rclpy.ok() and not _INTERRUPTED.is_set():
            raise
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        # faulthandler's timer is a C thread: it needs no GIL, which a teardown hung in
        # rclpy's C++ (seen destroying the DDS participant) holds. It prints every thread's
        # stack and exits 1; a shutdown that finishes exits 0 first.
        faulthandler.dump_traceback_later(SHUTDOWN_GRACE_S, exit=True)
        for node in nodes:
            spinner.remove_node(node)
        _release_handles(spinner)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    _exit_after_shutdown()


def _release_handles(spinner: Executor) -> None:
    """Make the executor let go of the nodes' handles before the nodes are destroyed.

    Until nothing holds the handles, the DDS participant outlives the context, and its
    shared-memory segments (64 MiB each with config/fastdds_shm.xml) stay in /dev/shm,
    which is memory, after the process has gone. EventsExecutor holds them until its
    shutdown(), which also unregisters its middleware callbacks and its signal callback;
    run before destroy_node(), it only releases them, and the handles are then finalised
    by destroy_node() as with any executor. (Run after it, the executor itself finalised
    the deferred QoS event handles, and once hung there, in rcl_event_fini, while a peer
    left the graph.) SingleThreadedExecutor holds none once its nodes are removed, and its
    shutdown() is skipped: it frees its SIGINT guard condition, which rclpy's signal
    thread may be triggering at that moment (a segfault, seen under load).
    """
    if not isinstance(spinner, SingleThreadedExecutor):
        spinner.shutdown()


def _exit_after_shutdown() -> NoReturn:
    """Exit 0 once the nodes and rclpy are shut down, without the interpreter's teardown.

    The nodes have left the graph by then (destroy_node), and their log is flushed
    (try_shutdown). What the interpreter would still do, finalising modules and the
    native libraries' state, was seen to take longer than launch waits on a loaded machine
    (past SIGINT's 5 s and SIGTERM's 10 s), so that `ros2 launch` killed a node that had
    stopped cleanly. The DDS participant is destroyed with the last node's handle; once in
    a suite's run it was seen to outlive a clean stop, which left its shared memory in
    /dev/shm: whatever of it the process still holds is removed (dds_shm.remove_own).
    """
    dds_shm.remove_own()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _interrupt_once(signum: int, frame) -> None:
    """KeyboardInterrupt for the first SIGINT; every later one is ignored."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _INTERRUPTED.set()
    raise KeyboardInterrupt


def _rcl_refusal(message: str) -> str:
    """rcl's "Couldn't parse ... '<argument>'. Error: <why>, at <file:line>..." as one line."""
    match = re.search(r"Couldn't parse [\w ]+: '(.*)'\. Error: (.*?)(, at [^,]*)*$", message,
                      re.DOTALL)
    text = f'{match[1]}: {match[2]}' if match else message
    return ' '.join(text.split())


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

    def skipped(self, text: str) -> None:
        """'<text>; skipped' for a bad message, its kind named by the first two words."""
        self.warn(' '.join(text.split()[:2]), f'{text}; skipped')
