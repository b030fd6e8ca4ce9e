"""A camera input for vision nodes: raw and compressed images in, numpy frames out.

`ImageInput` subscribes `<topic>` (sensor_msgs/Image) and `<topic>/compressed`
(sensor_msgs/CompressedImage) and hands each new frame to the node as an 8-bit grey
(or, with `colour=True`, BGR) array with its header. Every image goes through one
guarded path:

- its stamp is judged first (uav_vs.vision.frame_sync.StampOrder, against the node's
  clock, so use_sim_time is honoured): a frame stamped more than `future_tolerance`
  ahead of the clock is dropped (`future`) and moves nothing on; one not newer than
  the last frame handed over is skipped before decoding (`stale`: a camera driver may
  publish both topics, so each frame is decoded and processed once and never out of
  order); one older than that by more than `restart_after` means time went back (a
  bag loop, a new replay, a reset /clock): it is processed, the order restarts
  (`restarts`, logged once each) and the node's `on_restart` runs first.
- any failure to convert it (encoding, size: empty, absurd or unexpected; undecodable
  bytes, OpenCV's errors included) is counted (`malformed`), logged once per kind of
  defect every 5 s, and skipped.
- an input silent for longer than `input_warn_after` makes the diagnostics WARN, for
  longer than `input_error_after` ERROR (uav_vs.ros.liveness, steady clock).
- an exception raised by the node's processing of a frame is counted (`errors`) and
  logged as an ERROR with its type, text and where it was raised, at most every 5 s;
  the node goes on with the next frame. It is not hidden: diagnostics go WARN and show
  the last one (`health`).

Raw images are taken serialized and read in place (`image_from_cdr`), so a bgr8
(colour) or mono8 (grey) frame is a read-only view of the message, not a copy.
"""
import traceback
from dataclasses import dataclass
from typing import Callable

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from uav_vs.ros.convert import (MessageError, RawImage, compressed_to_bgr, compressed_to_gray,
                                image_from_cdr, image_to_bgr, image_to_gray, stamp_to_ns)
from uav_vs.ros.liveness import Silence, silence_params
from uav_vs.ros.node_main import WARN, ThrottledWarnings
from uav_vs.ros.params import Param, T
from uav_vs.vision.frame_sync import StampOrder, Verdict

QOS_CHOICES = ('sensor_data', 'reliable')


def image_qos(name: str) -> QoSProfile:
    """sensor_data: best effort, keep last 5 (live cameras); reliable: keep last 10 (bags)."""
    if name == 'sensor_data':
        return qos_profile_sensor_data
    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def stamp_params(prefix: str, what: str = 'an image') -> list[Param]:
    """`<prefix>.future_tolerance`, `<prefix>.restart_after` and the silence bounds, for a
    node taking stamped frames (`what` names one in the descriptions); all live."""
    return [
        Param(f'{prefix}.future_tolerance', T.DOUBLE, 1.0,
              f'{what} stamped further ahead of this node\'s clock is dropped, s', 0.0, 1e9,
              live=True),
        Param(f'{prefix}.restart_after', T.DOUBLE, 1.0,
              f'{what} older than the last one by more than this restarts the stamp order '
              '(time went back: a new replay), s', 0.0, 1e9, live=True),
        *silence_params(prefix, what),
    ]


@dataclass(frozen=True)
class InputLimits:
    """The values of `stamp_params`, in seconds."""

    future_tolerance_s: float = 1.0
    restart_after_s: float = 1.0
    warn_after_s: float = 1.0
    error_after_s: float = 5.0

    @classmethod
    def of(cls, p: dict, prefix: str) -> 'InputLimits':
        return cls(p[f'{prefix}.future_tolerance'], p[f'{prefix}.restart_after'],
                   p[f'{prefix}.input_warn_after'], p[f'{prefix}.input_error_after'])


def error_text(err: BaseException) -> str:
    """'ZeroDivisionError: division by zero (plane_pose.py:123 in update)'."""
    text = ''.join(traceback.format_exception_only(err)).strip()
    frames = traceback.extract_tb(err.__traceback__)
    if not frames:
        return text
    where = frames[-1]
    return f"{text} ({where.filename.rsplit('/', 1)[-1]}:{where.lineno} in {where.name})"


class ImageInput:
    def __init__(self, node: Node, topic: str, qos: str,
                 callback: Callable[[np.ndarray, Header], None],
                 expected_size: tuple[int, int] | None = None, warn_period_s: float = 5.0,
                 colour: bool = False, limits: InputLimits = InputLimits(),
                 on_restart: Callable[[], None] | None = None) -> None:
        self._node, self._callback, self._size = node, callback, expected_size
        self._on_restart = on_restart
        self._clock = node.get_clock()
        self._warnings = ThrottledWarnings(node, warn_period_s)
        self._warn_period = warn_period_s
        self._order = StampOrder(0, 0)
        self.silence = Silence()
        self.set_limits(limits)
        self._counts = dict(malformed=0, errors=0)
        self._processed = 0
        self._reported = dict(self.counts, processed=0)
        self._last_error = ''
        self._ahead_s = 0.0
        profile = image_qos(qos)
        raw, compressed = ((image_to_bgr, compressed_to_bgr) if colour
                           else (image_to_gray, compressed_to_gray))
        node.create_subscription(Image, topic, lambda b: self._on_serialized(b, raw), profile,
                                 raw=True)
        node.create_subscription(CompressedImage, topic + '/compressed',
                                 lambda m: self._on(m, compressed), profile)

    def set_limits(self, limits: InputLimits) -> None:
        """New stamp and silence limits, from the next image on."""
        self._order.future_tolerance_ns = int(limits.future_tolerance_s * 1e9)
        self._order.restart_after_ns = int(limits.restart_after_s * 1e9)
        self.silence.warn_after_s = limits.warn_after_s
        self.silence.error_after_s = limits.error_after_s

    def _on_serialized(self, data: bytes, convert) -> None:
        try:
            msg = image_from_cdr(data)
        except MessageError as err:
            self._malformed(err)
            return
        self._on(msg, convert)

    def _on(self, msg: Image | RawImage | CompressedImage, convert) -> None:
        self.silence.heard()
        stamp = stamp_to_ns(msg.header.stamp)
        now = self._clock.now().nanoseconds
        verdict = self._order.check(stamp, now)
        if verdict is Verdict.FUTURE:
            self._future(stamp, now)
        if verdict is Verdict.STALE or verdict is Verdict.FUTURE:
            return
        try:
            frame = convert(msg, self._size)
        except Exception as err:        # OpenCV's errors are not MessageError
            self._malformed(err)
            return
        back = self._order.take(stamp)
        if back:
            self._restart(back)
        self._processed += 1
        try:
            self._callback(frame, msg.header)
        except Exception as err:        # counted, logged and in the diagnostics
            self._failed(stamp, err)

    @property
    def counts(self) -> dict[str, int]:
        """Images `malformed`, `stale`, `future`; `restarts`; frames whose processing
        raised (`errors`)."""
        return {**self._counts, **self._order.counts}

    def health(self) -> str:
        """What went wrong with the input since the last call ('' when nothing did)."""
        now = dict(self.counts, processed=self._processed)
        new = {k: v - self._reported[k] for k, v in now.items()}
        self._reported = now
        problems = []
        if new['future']:
            problems.append(f"{new['future']} images stamped in the future dropped (up to "
                            f'{self._ahead_s:.1f} s ahead of the clock)')
        if new['errors']:
            problems.append(f"{new['errors']} frames failed: {self._last_error}")
        if not new['processed'] and (new['stale'] or new['malformed']):
            problems.append(f"no image processed ({new['stale']} stale, "
                            f"{new['malformed']} malformed)")
        self._ahead_s = 0.0
        return '; '.join(problems)

    def diagnose(self, level: int, message: str) -> tuple[int, str]:
        """The node's diagnostics (level, message), made WARN by a problem of the input,
        WARN or ERROR by its silence."""
        if problem := self.health():
            level, message = max(level, WARN), f'{message}; {problem}'
        return self.silence.judge(level, message, 'image')

    def _future(self, stamp: int, now: int) -> None:
        ahead = (stamp - now) * 1e-9
        self._ahead_s = max(self._ahead_s, ahead)
        self._warnings.warn('future', f'image stamped {stamp * 1e-9:.3f} s, {ahead:.3f} s '
                            'ahead of the clock; skipped')

    def _restart(self, back_ns: int) -> None:
        self._node.get_logger().warn(f'time went back {back_ns * 1e-9:.3f} s (a new replay?): '
                                     'stamp order restarted')
        if self._on_restart is not None:
            self._on_restart()

    def _malformed(self, err: Exception) -> None:
        self._counts['malformed'] += 1
        text = str(err) if isinstance(err, MessageError) else error_text(err)
        self._warnings.skipped(text)

    def _failed(self, stamp: int, err: Exception) -> None:
        self._counts['errors'] += 1
        self._last_error = error_text(err)
        self._node.get_logger().error(
            f'processing the image stamped {stamp * 1e-9:.3f} s failed: {self._last_error}; '
            'skipped', throttle_duration_sec=self._warn_period)
