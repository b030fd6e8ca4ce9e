"""foxglove_node: the running graph in Foxglove or Lichtblick, over the Foxglove WebSocket
protocol, as the C++ foxglove_bridge serves it on a full ROS install.

A WebSocket server (foxglove-sdk) on `foxglove.host`:`foxglove.port` (127.0.0.1:8765 by
default: this host only; docs/safety.md says what opening it exposes). Every
`foxglove.discovery_period` the node looks at the graph and advertises each topic that
`foxglove.topics` lets through (regular expressions on the full name; hidden topics,
`/_...`, never) as a channel: message encoding `cdr`, schema `ros2msg` (the installed
.msg files, uav_vs.bag.schemas), a channel closed when its topic goes. A topic is
subscribed only while an app subscribes to its channel, with its publishers' reliability
and durability (so /tf_static's latched transforms come too), and every message goes
out as the serialized bytes it came in, stamped with the time it was received.

For a slow link, `foxglove.max_rates` (`TOPIC=HZ`) forwards at most HZ messages a second
on a topic, the first of each period, and `foxglove.jpeg_topics` serves an image topic
(raw or compressed) also as `<topic>/jpeg`, each frame re-encoded as a JPEG CompressedImage
(`foxglove.jpeg_quality`), `foxglove.jpeg_scale` times its size; `foxglove.jpeg_markers`
serves an image annotation (visualization_msgs/ImageMarker) also as `<topic>/jpeg`, its
pixel coordinates scaled alike. A frame or marker that cannot be converted is counted and
skipped.

With `foxglove.allow_services` the graph's services that `foxglove.services` lets
through (`arm`, `land`, `controller/enable`, ...) are advertised too, and a call from
the app is made on the ROS service and answered with its response (CDR both ways),
within `foxglove.service_timeout`. Off (the default), the server does not offer services
at all: a call is refused.

Diagnostics every `foxglove.diagnostics_period`: the port, channels, the topics the
clients subscribe to, messages forwarded and held back by a rate limit, the services
offered, frames or markers that could not be converted and malformed calls (skipped),
and topics without a schema. Every parameter is read-only.
"""
import re
import threading
from collections import deque
from dataclasses import dataclass, field
from functools import partial
from typing import Callable

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message

from uav_vs.bag.schemas import SchemaError, message_schema, service_schemas
from uav_vs.ros.convert import MessageError, image_cdr_to_jpeg_cdr, marker_cdr_scaled
from uav_vs.ros.node_main import OK, WARN, Diagnostics, ThrottledWarnings, run
from uav_vs.ros.params import Param, ParameterError, T, declare
from uav_vs.ros.replay import message_class

try:        # no rosdep key: a ROS install from apt has it only once pip has installed it
    import foxglove
    from foxglove import Schema
    from foxglove.websocket import Capability, ChannelView, Client
except ImportError:
    foxglove = None
NEEDS_SDK = 'foxglove_node needs the foxglove-sdk Python package: pip install foxglove-sdk==0.30.3'

PARAMS = [
    Param('foxglove.host', T.STRING, '127.0.0.1',
          'address the WebSocket server binds (0.0.0.0: every interface, see docs/safety.md)'),
    Param('foxglove.port', T.INTEGER, 8765, 'TCP port of the WebSocket server (0: any free one)',
          0, 65535),
    Param('foxglove.topics', T.STRING_ARRAY, ['.*'],
          'regular expressions: a topic whose full name one of them matches is advertised'),
    Param('foxglove.allow_services', T.BOOL, False,
          'offer the graph\'s services to the app (arm, land, ...): anyone who can connect '
          'can then fly the vehicle'),
    Param('foxglove.services', T.STRING_ARRAY, ['.*'],
          'regular expressions: with allow_services, the services advertised'),
    Param('foxglove.service_timeout', T.DOUBLE, 5.0,
          'a service call from the app fails after this long without a response, s', 0.1, 120.0),
    Param('foxglove.max_rates', T.STRING_ARRAY, [],
          'TOPIC=HZ entries (TOPIC a regular expression): at most HZ messages a second are '
          'forwarded on a topic it matches, the first of each period (a slow link)'),
    Param('foxglove.jpeg_topics', T.STRING_ARRAY, [],
          'regular expressions: a sensor_msgs/Image or CompressedImage topic one matches is '
          'also served as <topic>/jpeg, each frame re-encoded as a JPEG CompressedImage (a '
          'slow link)'),
    Param('foxglove.jpeg_quality', T.INTEGER, 80, 'quality of the re-encoded JPEG frames',
          1, 100),
    Param('foxglove.jpeg_scale', T.DOUBLE, 1.0,
          'width and height of the re-encoded JPEG frames, times the image\'s', 0.1, 1.0),
    Param('foxglove.jpeg_markers', T.STRING_ARRAY, [],
          'regular expressions: a visualization_msgs/ImageMarker topic one matches is also '
          'served as <topic>/jpeg, its pixel coordinates times foxglove.jpeg_scale (the '
          'annotation of the re-encoded frames)'),
    Param('foxglove.discovery_period', T.DOUBLE, 1.0,
          'period of the look at the graph for new or gone topics and services, s', 0.1, 60.0),
    Param('foxglove.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.1, 60.0),
]


IMAGE, COMPRESSED = 'sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage'
MARKER = 'visualization_msgs/msg/ImageMarker'
JPEG_SUFFIX = '/jpeg'


@dataclass
class Forwarded:
    """One advertised channel: the ROS topic it serves (of type `msgtype`), as it comes
    or converted (JPEG frames, scaled markers), at most one message every `period_ns`;
    its ROS subscription while an app listens."""

    source: str
    msgtype: str
    channel: object             # foxglove.Channel
    convert: Callable[[bytes], bytes] | None = None
    period_ns: int = 0
    clients: set[int] = field(default_factory=set)
    subscription: object | None = None
    last_ns: int | None = None
    messages: int = 0
    throttled: int = 0


class Listener:
    """The server's callbacks (on its own thread): queued for the node's executor."""

    def __init__(self, wake) -> None:
        self.requests: deque[tuple[str, int, int]] = deque()
        self._wake = wake

    def on_subscribe(self, client: 'Client', channel: 'ChannelView') -> None:
        self.requests.append(('subscribe', client.id, channel.id))
        self._wake()

    def on_unsubscribe(self, client: 'Client', channel: 'ChannelView') -> None:
        self.requests.append(('unsubscribe', client.id, channel.id))
        self._wake()


class FoxgloveNode(Node):
    def __init__(self) -> None:
        super().__init__('foxglove_node')
        if foxglove is None:
            raise ValueError(NEEDS_SDK)
        p = declare(self, PARAMS)
        self.topic_patterns = _patterns(p, 'foxglove.topics')
        self.service_patterns = _patterns(p, 'foxglove.services')
        self.jpeg_patterns = _patterns(p, 'foxglove.jpeg_topics')
        self.marker_patterns = _patterns(p, 'foxglove.jpeg_markers')
        self.jpeg_quality = p['foxglove.jpeg_quality']
        self.jpeg_scale = p['foxglove.jpeg_scale']
        self.max_rates = _rates(p['foxglove.max_rates'])
        self.allow_services = p['foxglove.allow_services']
        self.service_timeout = p['foxglove.service_timeout']
        self.forwarded: dict[str, Forwarded] = {}          # by topic
        self.by_channel: dict[int, str] = {}
        self.advertised_services: dict[str, object] = {}   # name -> ROS client
        self.failed: set[str] = set()                      # types without a schema, warned once
        self.malformed_calls = self.unconverted = 0
        self.warnings = ThrottledWarnings(self)
        self.wake = self.create_guard_condition(self.serve_requests)
        self.listener = Listener(self.wake.trigger)
        self.fox_context = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name='uav_vs', host=p['foxglove.host'], port=p['foxglove.port'],
                capabilities=[Capability.Services] if self.allow_services else [],
                supported_encodings=['cdr'], server_listener=self.listener,
                context=self.fox_context)
        except Exception as err:     # the SDK raises its own error types: bind, address
            raise ParameterError(f"foxglove.host, foxglove.port: cannot serve on "
                                 f"{p['foxglove.host']}:{p['foxglove.port']} ({err})") from err
        self.diag = Diagnostics(self)
        self.create_timer(p['foxglove.discovery_period'], self.discover)
        self.create_timer(p['foxglove.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(
            f"serving ws://{p['foxglove.host']}:{self.server.port} (services "
            f"{'offered' if self.allow_services else 'not offered'})")
        self.discover()

    # ------------------------------------------------------------ topics

    def discover(self) -> None:
        """Advertise the new topics, close the channels of the gone ones; the same for
        the services when they are offered."""
        present = {}
        for topic, types in self.get_topic_names_and_types():
            if '/_' not in topic and _matches(self.topic_patterns, topic):
                present[topic] = types[0]
        for name in [n for n, f in self.forwarded.items() if present.get(f.source) != f.msgtype]:
            self.close(name)
        for topic, msgtype in present.items():
            if topic not in self.forwarded:
                self.advertise(topic, topic, msgtype)
            jpeg = topic + JPEG_SUFFIX
            patterns = {IMAGE: self.jpeg_patterns, COMPRESSED: self.jpeg_patterns,
                        MARKER: self.marker_patterns}.get(msgtype)
            if (patterns and _matches(patterns, topic)
                    and jpeg not in present and jpeg not in self.forwarded):
                self.advertise(jpeg, topic, msgtype)
        if self.allow_services:
            self.discover_services()

    def advertise(self, name: str, source: str, msgtype: str) -> None:
        """Channel `name` serving topic `source`: the same messages, or (another name) its
        frames as JPEG, its markers scaled to them."""
        convert, served = None, msgtype
        if name != source and msgtype == MARKER:
            convert = partial(marker_cdr_scaled, scale=self.jpeg_scale)
        elif name != source:
            convert = partial(image_cdr_to_jpeg_cdr, quality=self.jpeg_quality,
                              scale=self.jpeg_scale, compressed=msgtype == COMPRESSED)
            served = COMPRESSED
        try:
            schema = message_schema(served)
        except SchemaError as err:
            if served not in self.failed:
                self.failed.add(served)
                self.get_logger().warn(f'{name} not advertised: {err}')
            return
        channel = foxglove.Channel(
            name, message_encoding='cdr', context=self.fox_context,
            schema=Schema(name=served, encoding='ros2msg', data=schema.encode()))
        rate = next((hz for pattern, hz in self.max_rates if pattern.fullmatch(name)), None)
        self.forwarded[name] = Forwarded(source, msgtype, channel, convert,
                                         period_ns=round(1e9 / rate) if rate else 0)
        self.by_channel[channel.id()] = name
        self.get_logger().info(f'advertising {name} ({served}) on channel {channel.id()}')

    def close(self, name: str) -> None:
        f = self.forwarded.pop(name)
        self.get_logger().info(f'{name} is gone: channel {f.channel.id()} closed')
        self.by_channel.pop(f.channel.id(), None)
        if f.subscription is not None:
            self.destroy_subscription(f.subscription)
        f.channel.close()

    def serve_requests(self) -> None:
        """The apps' subscriptions, taken on the executor's thread."""
        while self.listener.requests:
            what, client, channel = self.listener.requests.popleft()
            name = self.by_channel.get(channel)
            if name is None:
                continue
            f = self.forwarded[name]
            if what == 'subscribe':
                f.clients.add(client)
                if f.subscription is None:
                    f.subscription = self.create_subscription(
                        message_class(f.msgtype), f.source, self.forwarder(f),
                        self.publishers_qos(f.source), raw=True)
            else:
                f.clients.discard(client)
                if not f.clients and f.subscription is not None:
                    self.destroy_subscription(f.subscription)
                    f.subscription = None

    def forwarder(self, f: Forwarded):
        def forward(data: bytes) -> None:
            received = self.get_clock().now().nanoseconds
            if f.period_ns:     # judged on the stamp the app sees; a clock gone back restarts
                if f.last_ns is not None and 0 <= received - f.last_ns < f.period_ns:
                    f.throttled += 1
                    return
                f.last_ns = received
            if f.convert is not None:
                try:
                    data = f.convert(data)
                except MessageError as err:
                    self.unconverted += 1
                    self.warnings.skipped(f'{f.source}: {err}')
                    return
            f.messages += 1
            f.channel.log(data, log_time=received)
        return forward

    def publishers_qos(self, topic: str) -> QoSProfile:
        """Reliable if every publisher is, transient local if every publisher is: what
        matches them all (as foxglove_bridge and ros2 topic echo choose)."""
        offers = [info.qos_profile for info in self.get_publishers_info_by_topic(topic)]
        reliable = bool(offers) and all(
            q.reliability == ReliabilityPolicy.RELIABLE for q in offers)
        latched = bool(offers) and all(
            q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offers)
        return QoSProfile(
            depth=max(10, len(offers)),
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

    # ------------------------------------------------------------ services

    def discover_services(self) -> None:
        present = {name: types[0] for name, types in self.get_service_names_and_types()
                   if '/_' not in name and _matches(self.service_patterns, name)
                   and not name.startswith(self.get_fully_qualified_name() + '/')}
        gone = [name for name in self.advertised_services if name not in present]
        if gone:
            self.server.remove_services(gone)
            for name in gone:
                self.destroy_client(self.advertised_services.pop(name))
        for name, srvtype in present.items():
            if name not in self.advertised_services:
                self.offer(name, srvtype)

    def offer(self, name: str, srvtype: str) -> None:
        try:
            request, response = service_schemas(srvtype)
        except SchemaError as err:
            if srvtype not in self.failed:
                self.failed.add(srvtype)
                self.get_logger().warn(f'service {name} not offered: {err}')
            return
        cls = message_class(srvtype)
        client = self.create_client(cls, name)
        schema = foxglove.ServiceSchema(
            srvtype,
            request=foxglove.MessageSchema(encoding='cdr', schema=Schema(
                name=f'{srvtype}_Request', encoding='ros2msg', data=request.encode())),
            response=foxglove.MessageSchema(encoding='cdr', schema=Schema(
                name=f'{srvtype}_Response', encoding='ros2msg', data=response.encode())))
        self.server.add_services([foxglove.Service(
            name, schema=schema, handler=self.caller(name, cls, client))])
        self.advertised_services[name] = client

    def caller(self, name: str, cls, client):
        def call(request) -> bytes:
            """On the server's thread: the ROS call, awaited; raising fails the app's call."""
            try:
                ros_request = deserialize_message(request.payload, cls.Request)
            except Exception as err:        # rclpy raises its C++ errors as they come
                self.malformed_calls += 1
                self.warnings.skipped(f'malformed call of {name} from the app ({err})')
                raise ValueError(f'{name}: the request is no {cls.__name__} in CDR') from err
            future = client.call_async(ros_request)
            done = threading.Event()
            future.add_done_callback(lambda _: done.set())
            if not done.wait(self.service_timeout):
                future.cancel()
                raise TimeoutError(f'{name}: no response in {self.service_timeout:g} s')
            self.get_logger().info(f'service {name} called from the app')
            return serialize_message(future.result())
        return call

    # ------------------------------------------------------------ diagnostics

    def publish_diagnostics(self) -> None:
        subscribed = [t for t, f in self.forwarded.items() if f.subscription is not None]
        level = OK if self.forwarded else WARN
        self.diag.publish(level, f'{len(subscribed)} of {len(self.forwarded)} topics '
                                 f'forwarded', {
            'port': self.server.port, 'channels': len(self.forwarded),
            'subscribed': ' '.join(sorted(subscribed)),
            'messages': sum(f.messages for f in self.forwarded.values()),
            'services': ' '.join(sorted(self.advertised_services)),
            'throttled': sum(f.throttled for f in self.forwarded.values()),
            'unconverted': self.unconverted,
            'malformed_calls': self.malformed_calls,
            'without_schema': ' '.join(sorted(self.failed))})

    def destroy_node(self) -> None:
        self.server.stop()
        super().destroy_node()


def _patterns(p: dict, name: str) -> list[re.Pattern]:
    try:
        return [re.compile(expr) for expr in p[name]]
    except re.error as err:
        raise ParameterError(f'{name}: expected regular expressions, got {err.pattern!r} '
                             f'({err})') from err


def _rates(entries: list[str]) -> list[tuple[re.Pattern, float]]:
    """'TOPIC=HZ' entries: (the topic's pattern, its rate)."""
    rates = []
    for entry in entries:
        expr, _, hz = entry.rpartition('=')
        try:
            rate = float(hz)
            pattern = re.compile(expr)
        except (ValueError, re.error):
            rate = 0.0
        if not expr or not 0.0 < rate < float('inf'):
            raise ParameterError(f'foxglove.max_rates: expected TOPIC=HZ entries (a regular '
                                 f'expression and a positive rate), got {entry!r}')
        rates.append((pattern, rate))
    return rates


def _matches(patterns: list[re.Pattern], name: str) -> bool:
    return any(pattern.fullmatch(name) for pattern in patterns)


def main(args: list[str] | None = None) -> None:
    # SingleThreadedExecutor: the server's thread wakes the node with a guard condition,
    # which EventsExecutor (rclpy 7.1.6) does not support.
    run(FoxgloveNode, 'foxglove_node', args, executor='single')


if __name__ == '__main__':
    main()
