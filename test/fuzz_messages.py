"""Hypothesis strategies of the messages test_fuzz_nodes.py sends the nodes.

Each strategy draws `Fuzzed` items: the topic, the message (or the bytes of a
serialized one), whether the node must refuse it (`bad`: True, counted as malformed;
False, taken; None, either is right) and how to stamp it when it is sent. The verdicts
come from the messages' documented contract (docs/ros.md, "Nodes" and "Topics"), worked
out here field by field, never by the code under test.
"""
import math
import struct
from dataclasses import dataclass

import cv2
import numpy as np
from geometry_msgs.msg import Point32, Polygon, PolygonStamped, PoseStamped, TwistStamped
from hypothesis import strategies as st
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

INT32_MIN, INT32_MAX, UINT32_MAX = -2**31, 2**31 - 1, 2**32 - 1
MAX_BYTES = 3 << 20                   # the largest message drawn, bytes
CHANNELS = {'bgr8': 3, 'rgb8': 3, 'bgra8': 4, 'rgba8': 4, 'mono8': 1}
WRONG_ENCODINGS = ['', '32FC1', '16UC1', 'bayer_rggb8', 'yuv422', 'BGR8', 'mono16', 'x' * 4096]


@dataclass(frozen=True)
class Stamp:
    """A header stamp: `now` plus `offset` s (the time it is sent), or the fixed
    (sec, nanosec) when `fixed`; `now` stamps of one storm increase strictly."""

    offset: float = 0.0
    fixed: tuple[int, int] | None = None


NOW = Stamp()


@dataclass(frozen=True)
class Fuzzed:
    topic: str                     # relative to the node's namespace
    payload: object                # a message, or bytes sent as a serialized one
    bad: bool | None               # must be refused / must be taken / either
    stamp: Stamp | None = NOW      # None: the payload's own (serialized bytes)


# ------------------------------------------------------------------ fields

EDGE_DOUBLES = [0.0, -0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 1e308, -1e308,
                5e-324, -5e-324, 2.2250738585072014e-308, 3.4028235e38, 3.5e38, 1e-300, 1e30]
EDGE_FLOAT32 = [0.0, -0.0, 1.0, math.nan, math.inf, -math.inf, 3.4028234663852886e38,
                -3.4028234663852886e38, 1.401298464324817e-45, 1e-38]


def doubles() -> st.SearchStrategy[float]:
    """Any float64, its edges often."""
    return st.one_of(st.sampled_from(EDGE_DOUBLES), st.floats(), st.floats(-10.0, 10.0))


def float32s() -> st.SearchStrategy[float]:
    return st.one_of(st.sampled_from(EDGE_FLOAT32), st.floats(width=32),
                     st.floats(-1000.0, 1000.0, width=32))


def strings(expected: str) -> st.SearchStrategy[str]:
    """A frame_id or format: the expected one, empty, huge, unicode, anything short."""
    return st.one_of(st.just(expected), st.sampled_from(['', 'x' * 100_000, '🛸 ünïcode', 'map']),
                     st.text(max_size=16))


EDGE_STAMPS = [Stamp(fixed=s) for s in ((0, 0), (0, 1), (1, 0), (INT32_MAX, 999_999_999),
                                        (INT32_MIN, 0), (-1, UINT32_MAX))]
EDGE_STAMPS += [Stamp(offset=s) for s in (-10.0, -1.0, -0.5, 0.0, 0.05, 1.0, 3600.0)]


def stamps() -> st.SearchStrategy[Stamp]:
    """Stamps at their edges: 0, int32/uint32 extremes, 2038, 10 s old, ahead; or now."""
    return st.one_of(st.sampled_from(EDGE_STAMPS), st.just(NOW),
                     st.builds(Stamp, fixed=st.tuples(st.integers(INT32_MIN, INT32_MAX),
                                                      st.integers(0, UINT32_MAX))))


def header(frame_id: str = '') -> Header:
    return Header(frame_id=frame_id)


# ------------------------------------------------------------------ images

def pattern(n: int, kind: str, frame: bytes = b'') -> bytes:
    """n bytes of pixels: black, white, a ramp, or the given frame repeated."""
    if kind == 'black':
        return bytes(n)
    if kind == 'white':
        return b'\xff' * n
    if kind == 'frame' and frame:
        return (frame * (n // len(frame) + 1))[:n]
    return (np.arange(n) % 251).astype(np.uint8).tobytes()


def image_verdict(encoding: str, width: int, height: int, step: int, size: int,
                  expected: tuple[int, int] | None) -> bool:
    """Must a node refuse this Image? Unsupported encoding, another size than the node's,
    an empty image, a row longer than step, or fewer bytes than step * height."""
    channels = CHANNELS.get(encoding)
    return (channels is None or (expected is not None and (width, height) != expected)
            or width == 0 or height == 0 or step < width * channels or size < step * height)


def raw_images(expected: tuple[int, int] | None, frame: np.ndarray,
               topic: str) -> st.SearchStrategy[Fuzzed]:
    """sensor_msgs/Image with every field at its edges; data of any length up to MAX_BYTES."""
    w, h = expected or (frame.shape[1], frame.shape[0])
    small = st.integers(0, 64) if expected is None else st.integers(0, 4096)
    encodings = st.one_of(st.sampled_from(list(CHANNELS)), st.sampled_from(WRONG_ENCODINGS),
                          st.text(max_size=8))
    widths = st.one_of(st.sampled_from([0, 1, w, w - 1, w + 1, UINT32_MAX, 2**31]), small)
    heights = st.one_of(st.sampled_from([0, 1, h, h - 1, h + 1, UINT32_MAX]), small)
    steps = st.one_of(st.sampled_from([0, -1, 1, 64, UINT32_MAX]), st.integers(0, 8192))
    lengths = st.one_of(st.sampled_from([0, -1, 1, 'exact', 'exact']), st.integers(0, 4096))
    contents = st.sampled_from(['black', 'white', 'ramp', 'frame'])
    frame_ids, endians = strings('camera_optical'), st.sampled_from([0, 1, 255])
    pixels = frame.tobytes()

    @st.composite
    def draw_image(draw) -> Fuzzed:
        encoding, width, height = draw(encodings), draw(widths), draw(heights)
        row = width * CHANNELS.get(encoding, 3)
        step = draw(steps)             # 0, -1, 1, 64: none, one short, one over, padded rows
        step = step if step in (0, UINT32_MAX) or step > 64 else max(row + step, 0)
        exact = step * height
        length = draw(lengths)         # 0, -1, 1: none, one short, one over
        length = exact if length == 'exact' else (max(exact + length, 0) if length in (-1, 1)
                                                   else length)
        length = min(length, MAX_BYTES)
        msg = Image(header=header(draw(frame_ids)), height=height, width=width,
                    encoding=encoding, is_bigendian=draw(endians), step=min(step, UINT32_MAX))
        msg.data = pattern(length, draw(contents), pixels)
        return Fuzzed(topic, msg, image_verdict(encoding, width, height, msg.step, length,
                                                expected))
    def valid(encoding: str, content: str) -> Fuzzed:
        msg = Image(height=h, width=w, encoding=encoding, step=w * CHANNELS[encoding])
        msg.data = pattern(msg.step * h, content, pixels)
        return Fuzzed(topic, msg, False)
    edges = draw_image()
    return st.one_of(edges, edges, edges, edges,          # one in five valid
                     st.builds(valid, st.sampled_from(list(CHANNELS)), contents))


def serialized(msg) -> bytes:
    return bytes(serialize_message(msg))


def serialized_images(valid: Image, topic: str) -> st.SearchStrategy[Fuzzed]:
    """Bytes sent as a serialized Image: random, a valid one truncated, or one with a
    length or count overwritten (then it may still be valid: either verdict). Never
    empty: an empty serialized sample stalls the probe's reliable writer in Fast DDS, so
    the node would see nothing more (a property of the transport, not of the node)."""
    cdr = serialized(valid)
    heads = st.sampled_from([b'\x00\x01\x00\x00', b'\x00\x00\x00\x00'])
    junk = st.builds(lambda b, k: b * k, st.binary(min_size=1, max_size=64),
                     st.sampled_from([1, 5, 64]))

    def truncated(cut: int) -> Fuzzed:   # DDS pads a payload to 4 bytes: a cut there is none
        return Fuzzed(topic, cdr[:cut], True if -(-cut // 4) * 4 < len(cdr) else None, None)

    def overwritten(at: int, value: int) -> Fuzzed:
        return Fuzzed(topic, cdr[:at] + struct.pack('<I', value) + cdr[at + 4:], None, None)
    return st.one_of(
        st.builds(lambda b: Fuzzed(topic, b, True, None), junk),
        st.builds(lambda h, b: Fuzzed(topic, h + b, True, None), heads, junk),
        st.builds(truncated, st.integers(1, len(cdr) - 1)),
        st.builds(overwritten, st.integers(4, min(len(cdr), 200) - 4),
                  st.sampled_from([0, 1, UINT32_MAX, INT32_MAX, 0x8000_0000])))


def encode(img: np.ndarray, ext: str) -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def with_jpeg_size(jpeg: bytes, width: int, height: int) -> bytes:
    """The JPEG with the size in its baseline start-of-frame (FFC0) replaced."""
    at = jpeg.index(b'\xff\xc0')
    return jpeg[:at + 5] + struct.pack('>HH', height, width) + jpeg[at + 9:]


def compressed_images(expected: tuple[int, int] | None, frame: np.ndarray,
                      topic: str) -> st.SearchStrategy[Fuzzed]:
    """sensor_msgs/CompressedImage: empty, random, truncated, corrupted or resized JPEG
    and PNG, valid ones of the node's size and of others, any format string."""
    jpeg, png = encode(frame, '.jpg'), encode(frame, '.png')
    sized = expected is not None
    wholes = st.sampled_from([jpeg, png])
    lying = [(0, 0), (1, 1), (frame.shape[1] + 1, frame.shape[0]),
             (frame.shape[1], frame.shape[0] + 7)]

    def random(data: bytes) -> tuple[bytes, bool | None]:
        return data, None if data[:2] == b'\xff\xd8' or data[:4] == b'\x89PNG' else True

    def corrupted(whole: bytes, changes: list[tuple[int, int]]) -> tuple[bytes, None]:
        data = bytearray(whole)
        for at, value in changes:
            data[at % len(data)] = value
        return bytes(data), None
    datas = st.one_of(
        st.just((b'', True)),
        st.builds(random, st.builds(lambda b, k: b * k, st.binary(min_size=1, max_size=64),
                                    st.sampled_from([1, 16, 128]))),
        st.builds(lambda m, b: (m + b, None),     # a JPEG or PNG signature, then garbage
                  st.sampled_from([b'\xff\xd8', b'\xff\xd8\xff\xe0', b'\x89PNG\r\n\x1a\n']),
                  st.binary(max_size=64)),
        st.builds(lambda w, f: (w[:int(f * (len(w) - 1))], None), wholes,   # truncated
                  st.floats(0.0, 1.0)),
        st.builds(corrupted, wholes, st.lists(st.tuples(st.integers(0, 1 << 20),
                                                        st.integers(0, 255)),
                                              min_size=1, max_size=16)),
        st.builds(lambda wh: (with_jpeg_size(jpeg, *wh), True if sized else None),
                  st.sampled_from(lying)),         # the header lies about the size
        st.builds(lambda d: (d, False), wholes),
        st.just((encode(frame[:frame.shape[0] // 2, :frame.shape[1] // 2], '.jpg'), sized)),
        st.just((encode(frame.astype(np.uint16) * 257, '.png'), None)))   # 16-bit PNG

    def message(data: tuple[bytes, bool | None], frame_id: str, fmt: str) -> Fuzzed:
        msg = CompressedImage(header=header(frame_id), format=fmt)
        msg.data = data[0]
        return Fuzzed(topic, msg, data[1])
    return st.builds(message, datas, strings('camera_optical'), strings('jpeg'))


def stamped_frames(valid: list[tuple[str, object]]) -> st.SearchStrategy[Fuzzed]:
    """Valid frames (topic, message) with stamps at their edges: refused or taken, the node
    must see the next frame stamped now."""
    return st.builds(lambda pick, stamp: Fuzzed(pick[0], pick[1], None, stamp),
                     st.sampled_from(valid), stamps())


# ------------------------------------------------------------------ poses and commands

UNIT_QUATERNIONS = [(0.0, 0.0, 0.0, 1.0), (0.0, 0.0, math.sin(0.4), math.cos(0.4)),
                    (0.1, -0.2, 0.3, math.sqrt(1 - 0.14))]
BAD_QUATERNIONS = [(0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), (0.0, 0.0, math.inf, 1.0),
                   (1e308, 1e308, 0.0, 0.0), (1e-300, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1e-4)]


def quaternion_verdict(q: tuple[float, ...]) -> bool | None:
    """A quaternion names a rotation when unit; zero, non-finite, or 1000 times too short
    or too long names none; one of another length may be normalised or refused."""
    n2 = sum(c * c for c in q)
    if not math.isfinite(n2) or not 1e-6 <= n2 <= 1e6:
        return True
    return False if abs(n2 - 1.0) < 1e-6 else None


def either(*verdicts: bool | None) -> bool | None:
    """Refused if any field must be refused; taken only if every one must be taken."""
    if True in verdicts:
        return True
    return None if None in verdicts else False


def quaternions() -> st.SearchStrategy[tuple[float, ...]]:
    unit = st.sampled_from(UNIT_QUATERNIONS)
    return st.one_of(unit, st.sampled_from(BAD_QUATERNIONS),
                     st.builds(lambda q, k: tuple(k * c for c in q), unit,
                               st.sampled_from([2.0, 0.5, -1.0, 1.001, 100.0])),
                     st.tuples(doubles(), doubles(), doubles(), doubles()))


@st.composite
def poses(draw, topic: str, frame: str = 'world', sane: bool = False) -> Fuzzed:
    """PoseStamped with edge positions, quaternions and frame_ids, stamped now. A huge but
    finite position is a pose nobody flies: either verdict (`sane`: none drawn)."""
    coordinate = (st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324]),
                            st.floats(-1e6, 1e6)) if sane else doubles())
    position = draw(st.tuples(coordinate, coordinate, coordinate))
    q = draw(quaternions())
    frame_id = draw(strings(frame))
    msg = PoseStamped(header=header(frame_id))
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = position
    o.x, o.y, o.z, o.w = q
    finite = all(map(math.isfinite, position))
    sane = all(abs(c) < 1e6 for c in position) if finite else False
    return Fuzzed(topic, msg, either(frame_id != frame, not finite, quaternion_verdict(q),
                                     None if finite and not sane else False))


@st.composite
def twists(draw, topic: str, frames: tuple[str, str] = ('world', 'base_link')) -> Fuzzed:
    """TwistStamped with edge components; only linear x, y, z and angular z are used."""
    linear = draw(st.tuples(doubles(), doubles(), doubles()))
    angular = draw(st.tuples(doubles(), doubles(), doubles()))
    frame_id = draw(st.one_of(st.sampled_from(frames), strings(frames[0])))
    msg = TwistStamped(header=header(frame_id))
    v, w = msg.twist.linear, msg.twist.angular
    v.x, v.y, v.z = linear
    w.x, w.y, w.z = angular
    used = (*linear, angular[2])
    return Fuzzed(topic, msg, frame_id not in frames or not all(map(math.isfinite, used)))


@st.composite
def polygons(draw, topics: list[str], n_points: int) -> Fuzzed:
    """PolygonStamped landmarks: any number of points (n_points are expected), any floats
    (NaN is 'not found', so only the count is checked)."""
    count = draw(st.one_of(st.sampled_from([0, 1, n_points - 1, n_points, n_points + 1, 5000]),
                           st.integers(0, 32)))
    if count > 64:
        value = draw(float32s())
        points = [Point32(x=value, y=value, z=value)] * count
    else:
        points = [Point32(x=draw(float32s()), y=draw(float32s()), z=draw(float32s()))
                  for _ in range(count)]
    msg = PolygonStamped(header=header(draw(strings('cam_optical'))),
                         polygon=Polygon(points=points))
    return Fuzzed(draw(st.sampled_from(topics)), msg, count != n_points)
