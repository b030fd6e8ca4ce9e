"""ImageInput: every image goes through one guarded path and its stamp is judged against
the node's clock, so neither a malformed image, a failing frame nor a clock glitch
stops or blinds a vision node.

The images are published to an ImageInput on the test's own spinning node; truth is
what was published (each frame's pixels and stamp).
"""
import struct

import cv2
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from conftest import wait_for
from uav_vs.ros import convert as cv
from uav_vs.ros.image_input import ImageInput, InputLimits
from uav_vs.ros.node_main import ERROR, OK, WARN

RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
S = 1_000_000_000
RNG = np.random.default_rng(3)
FRAME = cv2.GaussianBlur(RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8), (0, 0), 2)


def compressed(data: bytes, fmt: str = 'jpeg') -> CompressedImage:
    msg = CompressedImage(format=fmt)
    msg.data = data
    return msg


def raw(width: int, height: int, step: int, n_bytes: int, encoding: str = 'bgr8') -> Image:
    msg = Image(width=width, height=height, step=step, encoding=encoding)
    msg.data = bytes(n_bytes)
    return msg


PNG = cv2.imencode('.png', FRAME)[1].tobytes()
JPEG = cv2.imencode('.jpg', FRAME)[1].tobytes()
# A PNG whose header claims 100000 x 100000 pixels (a decompression bomb's header).
HUGE_PNG = PNG[:16] + struct.pack('>II', 100000, 100000) + PNG[24:]
MALFORMED = {
    'empty compressed': compressed(b''),
    'garbage jpeg': compressed(b'\xff\xd8 not a jpeg at all'),
    'png header truncated': compressed(PNG[:12], 'png'),
    'jpeg truncated after its header': compressed(JPEG[:len(JPEG) // 3]),
    'absurd png size': compressed(HUGE_PNG, 'png'),
    'not jpeg or png': compressed(b'GIF89a' + bytes(40), 'gif'),
    'bgr8 0x0': raw(0, 0, 0, 0),
    'bgr8 640x0': raw(640, 0, 1920, 0),
    'bgr8 0x480': raw(0, 480, 0, 0),
    'step shorter than a row': raw(64, 48, 100, 48 * 192),
    'data shorter than step x height': raw(64, 48, 192, 47 * 192),
    'mono8 640x0': raw(640, 0, 640, 0, 'mono8'),
}


@pytest.mark.parametrize('grey', [False, True])
def test_every_malformed_image_raises_message_error(grey):
    """The converters refuse each defect with a MessageError: an empty CompressedImage
    used to escape as cv2.error, a 0x0 or 640x0 bgr8 Image to pass as an empty array."""
    accepted = []
    for name, msg in MALFORMED.items():
        if isinstance(msg, CompressedImage):
            convert = cv.compressed_to_gray if grey else cv.compressed_to_bgr
        else:
            convert = cv.image_to_gray if grey else cv.image_to_bgr
        try:
            convert(msg)
            accepted.append(name)
        except cv.MessageError:
            pass
    assert accepted == []


def test_compressed_size_is_read_from_the_header_without_decoding():
    assert cv.compressed_size(compressed(JPEG)) == (64, 48)
    assert cv.compressed_size(compressed(PNG, 'png')) == (64, 48)
    with pytest.raises(cv.MessageError, match=r'image size 100000x100000 refused'):
        cv.compressed_to_gray(compressed(HUGE_PNG, 'png'))


class Harness:
    """An ImageInput on the test node, the frames it hands over and a publisher per topic."""

    def __init__(self, ros_node, topic: str, fail_on: set[int] = frozenset(), **kwargs) -> None:
        self.node, self.fail_on = ros_node, fail_on
        self.frames: list[tuple[int, np.ndarray]] = []
        self.restarts = 0
        self.input = ImageInput(ros_node, topic, 'reliable', self.on_frame, colour=True,
                                on_restart=self.on_restart, **kwargs)
        self.raw = ros_node.create_publisher(Image, topic, RELIABLE)
        self.compressed = ros_node.create_publisher(CompressedImage, topic + '/compressed',
                                                    RELIABLE)
        assert wait_for(lambda: self.raw.get_subscription_count() > 0
                        and self.compressed.get_subscription_count() > 0, 10)

    def on_frame(self, bgr: np.ndarray, header: Header) -> None:
        stamp = cv.stamp_to_ns(header.stamp)
        if stamp in self.fail_on:
            raise ZeroDivisionError('division by zero')
        self.frames.append((stamp, bgr.copy()))

    def on_restart(self) -> None:
        self.restarts += 1

    def now(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def handled(self) -> int:
        counts = self.input.counts
        return (len(self.frames) + counts['malformed'] + counts['stale'] + counts['future']
                + counts['errors'])

    def send(self, msg: Image | CompressedImage, stamp_ns: int) -> None:
        """Publish one image and wait until the input has dealt with it."""
        before = self.handled()
        msg.header = Header(stamp=cv.ns_to_stamp(stamp_ns), frame_id='cam_optical')
        (self.compressed if isinstance(msg, CompressedImage) else self.raw).publish(msg)
        assert wait_for(lambda: self.handled() > before, 10), self.input.counts

    def stamps(self) -> list[int]:
        return [stamp for stamp, _ in self.frames]


def test_malformed_images_are_counted_and_the_next_frame_is_handed_over(ros_node):
    """On the raw and the compressed topic alike; an empty CompressedImage used to
    escape as cv2.error and a 0x0 bgr8 Image to reach the node."""
    h = Harness(ros_node, '/guard/image_raw')
    t = h.now() - 10 * S
    for k, msg in enumerate(MALFORMED.values()):
        h.send(msg, t + k)
    assert h.input.counts['malformed'] == len(MALFORMED) and h.frames == []
    assert h.input.diagnose(OK, 'ok')[0] == WARN            # nothing got through
    h.send(cv.bgr_to_image(FRAME, Header()), t + 100)
    h.send(compressed(PNG, 'png'), t + 200)
    assert h.stamps() == [t + 100, t + 200]
    assert all(np.array_equal(frame, FRAME) for _, frame in h.frames)
    assert h.input.diagnose(OK, 'ok') == (OK, 'ok')


def test_a_future_stamp_is_dropped_and_moves_nothing_on(ros_node):
    """One frame stamped in 2038 (a camera clock glitch) used to make every later frame
    stale until restart."""
    h = Harness(ros_node, '/future/image_raw', limits=InputLimits(future_tolerance_s=1.0))
    now = h.now()
    h.send(cv.bgr_to_image(FRAME, Header()), now - S)
    h.send(cv.bgr_to_image(FRAME, Header()), 2_145_000_000 * S)     # year 2037
    h.send(cv.bgr_to_image(FRAME, Header()), now + S // 2)        # within the tolerance
    h.send(cv.bgr_to_image(FRAME, Header()), h.now() + S // 2)
    assert h.stamps()[:2] == [now - S, now + S // 2] and len(h.frames) == 3
    counts = h.input.counts
    assert counts['future'] == 1 and counts['stale'] == 0 and counts['restarts'] == 0
    level, message = h.input.diagnose(OK, 'ok')
    assert level == WARN and '1 images stamped in the future dropped' in message


def test_time_going_back_restarts_the_order_once(ros_node):
    """A bag loop: frames stamped 20 s earlier are processed again, the node told once;
    a small step back is still a stale frame."""
    h = Harness(ros_node, '/loop/image_raw', limits=InputLimits(restart_after_s=1.0))
    t0 = h.now() - 100 * S
    replay = [t0 + k * S // 10 for k in range(5)]
    for stamp in replay:
        h.send(compressed(JPEG), stamp + 20 * S)        # the first pass, 20 s later
    h.send(compressed(JPEG), replay[-1] + 20 * S - S // 2)          # 0.5 s back: stale
    for stamp in replay:
        h.send(compressed(JPEG), stamp)                 # the bag again, from its start
    assert h.stamps() == [s + 20 * S for s in replay] + replay
    assert h.input.counts['restarts'] == 1 and h.restarts == 1
    assert h.input.counts['stale'] == 1


def test_a_frame_whose_processing_raises_is_counted_and_the_next_one_goes_through(ros_node):
    """A failing frame used to end the node; now it is counted (errors), shown in the
    diagnostics with what raised where, and the next frame is processed."""
    t = ros_node.get_clock().now().nanoseconds - 10 * S
    h = Harness(ros_node, '/fail/image_raw', fail_on={t + 1})
    for k in range(3):
        h.send(cv.bgr_to_image(FRAME, Header()), t + k)
    assert h.stamps() == [t, t + 2]
    assert h.input.counts['errors'] == 1
    level, message = h.input.diagnose(OK, 'ok')
    assert level == WARN and 'ZeroDivisionError: division by zero' in message
    assert 'test_image_input.py' in message


def test_stamps_are_judged_against_ros_time_with_use_sim_time(ros_node):
    """With use_sim_time the clock is /clock's: a frame 50 s past a replay's clock is
    in the future although it is decades behind the wall clock."""
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock
    ros_node.set_parameters([Parameter('use_sim_time', value=True)])
    clock = ros_node.create_publisher(Clock, '/clock', RELIABLE)
    h = Harness(ros_node, '/sim/image_raw', limits=InputLimits(future_tolerance_s=1.0))
    h.send(compressed(JPEG), 10**18)               # ROS time still 0: nothing is ahead
    assert wait_for(lambda: clock.get_subscription_count() > 0, 10)
    clock.publish(Clock(clock=cv.ns_to_stamp(100 * S)))
    assert wait_for(lambda: h.now() == 100 * S, 10)
    h.send(compressed(JPEG), 150 * S)
    h.send(compressed(JPEG), 30 * S)               # back from 10**18: a restart
    h.send(compressed(JPEG), 100 * S + S // 2)
    assert h.stamps() == [10**18, 30 * S, 100 * S + S // 2]
    assert h.input.counts['future'] == 1


def test_a_silent_input_makes_the_diagnostics_warn_then_error(ros_node):
    t = ros_node.get_clock().now().nanoseconds - 10 * S
    h = Harness(ros_node, '/quiet/image_raw',
                limits=InputLimits(warn_after_s=0.2, error_after_s=0.6))
    assert h.input.diagnose(WARN, 'no image yet') == (WARN, 'no image yet')
    h.send(cv.bgr_to_image(FRAME, Header()), t)
    assert h.input.diagnose(OK, 'ok') == (OK, 'ok')
    assert wait_for(lambda: h.input.diagnose(OK, 'ok')[0] == WARN, 5)
    assert h.input.diagnose(OK, 'ok')[1].startswith('no image for ')
    assert wait_for(lambda: h.input.diagnose(OK, 'ok')[0] == ERROR, 5)
    h.send(cv.bgr_to_image(FRAME, Header()), t + 1)
    assert h.input.diagnose(OK, 'ok') == (OK, 'ok')
