"""The one place that converts between ROS messages and numpy.

Images follow the measured fast paths: `np.frombuffer` to read (zero copy) and
`tobytes()` to fill (never assign an ndarray to `msg.data`). A raw image is best
taken serialized (`raw=True`) and read with `image_from_cdr`: rclpy's own
deserialization copies the pixels three times.
"""
import math
import struct
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import (Point, Point32, Polygon, PolygonStamped, PoseStamped,
                               PoseWithCovarianceStamped, TransformStamped, TwistStamped)
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import ImageMarker

from uav_vs.vision.camera import CalibrationError, Camera

_CHANNELS = {'bgr8': 3, 'rgb8': 3, 'bgra8': 4, 'rgba8': 4, 'mono8': 1}
MAX_IMAGE_PIXELS = 1 << 26    # 8192 x 8192; larger images are refused, never decoded
_PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
# JPEG start-of-frame markers (they carry the size): C0-CF but DHT, JPG and DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_CDR_BYTE_ORDER = {b'\x00\x00': '>', b'\x00\x01': '<'}   # encapsulation CDR_BE, CDR_LE


class MessageError(ValueError):
    """A message cannot be converted; str() says why in one line."""


def stamp_to_ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def ns_to_stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@dataclass(frozen=True)
class RawImage:
    """The fields of a sensor_msgs/Image; `data` is a view of the serialized message."""

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview


def image_from_cdr(raw: bytes) -> RawImage | Image:
    """A serialized sensor_msgs/Image read without copying its pixels.

    Plain CDR (either byte order) is read field by field; any other encapsulation is
    deserialized by rclpy. A truncated or inconsistent message raises MessageError.
    """
    order = _CDR_BYTE_ORDER.get(bytes(raw[:2]))
    if order is None:
        try:
            return deserialize_message(raw, Image)
        except RuntimeError as err:
            raise MessageError(f'malformed serialized image: {err}') from None
    body = memoryview(raw)[4:]
    try:
        sec, nanosec = struct.unpack_from(order + 'iI', body, 0)
        frame_id, pos = _cdr_string(body, 8, order)
        height, width = struct.unpack_from(order + 'II', body, _align4(pos))
        encoding, pos = _cdr_string(body, _align4(pos) + 8, order)
        is_bigendian = body[pos]
        pos = _align4(pos + 1)
        step, size = struct.unpack_from(order + 'II', body, pos)
    except (struct.error, IndexError, UnicodeDecodeError) as err:
        raise MessageError(f'malformed serialized image: {err}') from None
    if pos + 8 + size > len(body):
        raise MessageError(f'malformed serialized image: {size} data bytes announced, '
                           f'{len(body) - pos - 8} present')
    return RawImage(Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id), height,
                    width, encoding, is_bigendian, step, body[pos + 8:pos + 8 + size])


def _cdr_string(body: memoryview, pos: int, order: str) -> tuple[str, int]:
    """The CDR string at `pos` (its length counts the closing NUL) and the offset after it."""
    (size,) = struct.unpack_from(order + 'I', body, pos)
    end = pos + 4 + size
    if size == 0 or end > len(body):
        raise IndexError(f'string of {size} bytes at offset {pos}')
    return str(body[pos + 4:end - 1], 'utf-8'), end


def _align4(pos: int) -> int:
    return pos + -pos % 4


def image_to_bgr(msg: Image | RawImage,
                 expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """sensor_msgs/Image (bgr8, rgb8, bgra8, rgba8, mono8) to a BGR uint8 array.

    `expected_size` is (width, height); anything else raises MessageError.
    """
    channels = _CHANNELS.get(msg.encoding)
    if channels is None:
        raise MessageError(f'unsupported encoding {msg.encoding!r} '
                           f'(expected one of {", ".join(_CHANNELS)})')
    _check_size(msg.width, msg.height, expected_size)
    row = msg.width * channels
    if msg.step < row or len(msg.data) < msg.step * msg.height:
        raise MessageError(f'image data too short: {len(msg.data)} bytes for '
                           f'{msg.width}x{msg.height} {msg.encoding} step {msg.step}')
    buf = np.frombuffer(msg.data, np.uint8, count=msg.step * msg.height)
    img = buf.reshape(msg.height, msg.step)[:, :row].reshape(msg.height, msg.width, channels)
    if msg.encoding == 'bgr8':
        return img
    code = {'rgb8': cv2.COLOR_RGB2BGR, 'bgra8': cv2.COLOR_BGRA2BGR,
            'rgba8': cv2.COLOR_RGBA2BGR, 'mono8': cv2.COLOR_GRAY2BGR}[msg.encoding]
    return cv2.cvtColor(img, code)


def compressed_to_bgr(msg: CompressedImage,
                      expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg, png) to a BGR uint8 array."""
    return _decode(msg, expected_size, cv2.IMREAD_COLOR)


def bgr_to_image(img: np.ndarray, header: Header) -> Image:
    """BGR uint8 array to sensor_msgs/Image (bgr8)."""
    msg = Image(header=header, height=img.shape[0], width=img.shape[1], encoding='bgr8',
                is_bigendian=0, step=img.shape[1] * 3)
    msg.data = np.ascontiguousarray(img).tobytes()
    return msg


def bgr_to_compressed(img: np.ndarray, header: Header, quality: int = 90) -> CompressedImage:
    ok, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    msg = CompressedImage(header=header, format='jpeg')
    msg.data = buf.tobytes()
    return msg


def image_cdr_to_jpeg_cdr(raw: bytes, quality: int = 80, scale: float = 1.0,
                          compressed: bool = False) -> bytes:
    """A serialized sensor_msgs/Image (CompressedImage with `compressed`) as a serialized
    JPEG CompressedImage, same header, `scale` times its width and height (a slow link's
    copy of a camera stream). Raises MessageError as image_to_bgr and compressed_to_bgr
    do."""
    if compressed:
        msg = _from_cdr(raw, CompressedImage)
        img = compressed_to_bgr(msg)
    else:
        msg = image_from_cdr(raw)
        img = image_to_bgr(msg)
    if scale != 1.0:
        img = cv2.resize(img, (max(1, round(img.shape[1] * scale)),
                               max(1, round(img.shape[0] * scale))),
                         interpolation=cv2.INTER_AREA)
    return serialize_message(bgr_to_compressed(img, msg.header, quality))


def marker_cdr_scaled(raw: bytes, scale: float) -> bytes:
    """A serialized visualization_msgs/ImageMarker with its pixel coordinates (position,
    points) times `scale`: the annotation of an image served `scale` times its size.
    Raises MessageError on bytes that are no ImageMarker."""
    msg = _from_cdr(raw, ImageMarker)
    msg.position.x, msg.position.y = msg.position.x * scale, msg.position.y * scale
    msg.points = [Point(x=p.x * scale, y=p.y * scale, z=p.z) for p in msg.points]
    return serialize_message(msg)


def _from_cdr(raw: bytes, cls):
    """deserialize_message, raising MessageError for bytes that are no `cls`."""
    try:
        return deserialize_message(raw, cls)
    except Exception as err:      # rclpy raises its own types for short or garbled CDR
        module = cls.__module__.split('.')[0]
        raise MessageError(f'not a {module}/{cls.__name__} ({err})') from err


def outlines_to_marker(outlines: Sequence[np.ndarray], header: Header, rgba: Sequence[float],
                       ns: str = '') -> ImageMarker:
    """Closed outlines in pixels ((k, 2) arrays: a window's corners, a target's) as one
    visualization_msgs/ImageMarker LINE_LIST, the annotation an image viewer (Foxglove,
    Lichtblick, rqt) draws over the image of the same stamp."""
    segments = [(p, q) for outline in outlines
                for p, q in zip(outline, np.roll(outline, -1, axis=0))]
    return ImageMarker(header=header, ns=ns, type=ImageMarker.LINE_LIST,
                       action=ImageMarker.ADD, scale=2.0, outline_color=ColorRGBA(
                           r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]),
                           a=float(rgba[3])),
                       points=[Point(x=float(x), y=float(y)) for seg in segments
                               for x, y in seg])


def rect_corners(x: float, y: float, w: float, h: float) -> np.ndarray:
    """An axis-aligned pixel window's four corners, (4, 2)."""
    return np.array([(x, y), (x + w, y), (x + w, y + h), (x, y + h)], np.float64)


def points_to_polygon(points: np.ndarray, header: Header) -> PolygonStamped:
    """(n, 2|3) float array to PolygonStamped; missing coordinates stay NaN."""
    pts = np.asarray(points, np.float64)
    z = pts[:, 2] if pts.shape[1] > 2 else np.zeros(len(pts))
    return PolygonStamped(header=header, polygon=Polygon(points=[
        Point32(x=float(x), y=float(y), z=float(w)) for x, y, w in zip(pts[:, 0], pts[:, 1], z)]))


def polygon_to_array(msg: PolygonStamped) -> np.ndarray:
    """PolygonStamped to an (n, 3) float array."""
    return np.array([(p.x, p.y, p.z) for p in msg.polygon.points], np.float64).reshape(-1, 3)


def pose_to_msg(position: np.ndarray, quaternion_xyzw: np.ndarray, header: Header) -> PoseStamped:
    msg = PoseStamped(header=header)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, position)
    q = msg.pose.orientation
    q.x, q.y, q.z, q.w = map(float, quaternion_xyzw)
    return msg


def check_frame(header: Header, frame: str) -> None:
    """MessageError unless the message is stamped in `frame` (its header's frame_id)."""
    if header.frame_id != frame:
        raise MessageError(f'frame {header.frame_id!r}, expected {frame!r}')


def msg_to_pose(msg: PoseStamped) -> tuple[np.ndarray, np.ndarray]:
    """PoseStamped to (position (3,), unit quaternion xyzw (4,)); see unit_quaternion."""
    p, q = msg.pose.position, msg.pose.orientation
    return np.array([p.x, p.y, p.z]), unit_quaternion(q.x, q.y, q.z, q.w)


def msg_to_pose_in(msg: PoseStamped, frame: str) -> tuple[np.ndarray, np.ndarray]:
    """msg_to_pose of a pose that must be stamped in `frame` with a finite position:
    MessageError otherwise."""
    check_frame(msg.header, frame)
    position, q = msg_to_pose(msg)
    if not np.isfinite(position).all():
        raise MessageError('non-finite position')
    return position, q


def pose_cov_to_msg(position: np.ndarray, quaternion_xyzw: np.ndarray, covariance: np.ndarray,
                    header: Header) -> PoseWithCovarianceStamped:
    """A pose with its 6x6 covariance (x, y, z, rotation about x, y, z: ROS order)."""
    msg = PoseWithCovarianceStamped(header=header)
    msg.pose.pose = pose_to_msg(position, quaternion_xyzw, header).pose
    msg.pose.covariance = np.asarray(covariance, dtype=float).reshape(36)
    return msg


def msg_to_pose_cov_in(msg: PoseWithCovarianceStamped | Odometry, frame: str
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """msg_to_pose_in of a pose with covariance (or an Odometry's pose, which has the same
    fields), and its 6x6 covariance: MessageError
    unless that is a covariance: finite with a positive diagonal, and its correlation
    matrix symmetric with no negative eigenvalue (to 1e-9)."""
    position, q = msg_to_pose_in(PoseStamped(header=msg.header, pose=msg.pose.pose), frame)
    cov = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)
    if not (np.isfinite(cov).all() and np.all(np.diag(cov) > 0)):
        raise MessageError('covariance not finite with a positive diagonal')
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd)
    if np.abs(corr - corr.T).max() > 1e-9:
        raise MessageError('covariance not symmetric')
    if np.linalg.eigvalsh(corr).min() < -1e-9:
        raise MessageError('covariance not positive semi-definite')
    return position, q, cov


def transform_to_msg(translation: np.ndarray, quaternion_xyzw: np.ndarray, header: Header,
                     child_frame_id: str) -> TransformStamped:
    """TransformStamped header.frame_id -> child_frame_id: the child's pose in the parent."""
    msg = TransformStamped(header=header, child_frame_id=child_frame_id)
    v = msg.transform.translation
    v.x, v.y, v.z = map(float, translation)
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = map(float, quaternion_xyzw)
    return msg


def msg_to_transform(msg: TransformStamped) -> tuple[np.ndarray, np.ndarray]:
    """TransformStamped to (translation (3,), unit quaternion xyzw (4,)); see unit_quaternion."""
    v, q = msg.transform.translation, msg.transform.rotation
    return np.array([v.x, v.y, v.z]), unit_quaternion(q.x, q.y, q.z, q.w)


# |q|^2 of a quaternion taken as a rotation. A quaternion names a rotation at any scale
# (tf2's rotation matrix reads it so), and senders give unit ones (to ~1e-6 from tf2, to 3-4
# digits by hand): one within a factor of ten of unit length is normalised; zero (an
# unset orientation), non-finite or further off is no rotation.
_QUATERNION_NORM2 = (0.1 ** 2, 10.0 ** 2)


def unit_quaternion(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The xyzw quaternion normalised (as is when unit to rounding); MessageError when its
    length is not finite or not within a factor of ten of 1."""
    n2 = _quaternion_norm2(x, y, z, w)
    if abs(n2 - 1.0) <= 1e-12:
        return np.array([x, y, z, w])
    return np.array([x, y, z, w]) / math.sqrt(n2)


def yaw_of(quaternion_xyzw: np.ndarray) -> float:
    """Yaw (rotation about z, rad) of an xyzw quaternion, at any scale; MessageError as
    unit_quaternion."""
    x, y, z, w = np.asarray(quaternion_xyzw, float).tolist()   # floats: faster than np scalars
    _quaternion_norm2(x, y, z, w)
    return math.atan2(2 * (w * z + x * y), w * w + x * x - y * y - z * z)


def yaw_quaternion(yaw: float) -> np.ndarray:
    """The xyzw unit quaternion of a rotation by `yaw` [rad] about z (the inverse of yaw_of)."""
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def _quaternion_norm2(x: float, y: float, z: float, w: float) -> float:
    """|q|^2, checked to lie in [0.1^2, 10^2] (NaN and inf fail the comparison)."""
    n2 = x * x + y * y + z * z + w * w
    if not _QUATERNION_NORM2[0] <= n2 <= _QUATERNION_NORM2[1]:
        raise MessageError(f'quaternion ({x:.4g}, {y:.4g}, {z:.4g}, {w:.4g}) is no rotation: '
                           f'length {math.sqrt(n2):.4g}, expected 1')
    return n2


def twist_to_msg(linear: np.ndarray, angular: np.ndarray, header: Header) -> TwistStamped:
    msg = TwistStamped(header=header)
    msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z = map(float, linear)
    msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z = map(float, angular)
    return msg


def msg_to_twist(msg: TwistStamped) -> tuple[np.ndarray, np.ndarray]:
    v, w = msg.twist.linear, msg.twist.angular
    return np.array([v.x, v.y, v.z]), np.array([w.x, w.y, w.z])


def camera_info(fields: dict, header: Header) -> CameraInfo:
    """CameraInfo from `Camera.camera_info_fields()`."""
    return CameraInfo(header=header, **fields)


def camera_from_info(msg: CameraInfo, name: str = 'camera') -> Camera:
    """A Camera (intrinsics only: R = I, t = 0) from a CameraInfo of any OpenCV D.

    `plumb_bob`, `rational_polynomial` or an empty model with D of 0, 4, 5, 8, 12 or 14
    coefficients; other models (`equidistant`: the fisheye lens) or lengths raise
    MessageError in one line. A width or height of 0 is taken as unknown.
    """
    model = msg.distortion_model
    if model not in ('', 'plumb_bob', 'rational_polynomial'):
        raise MessageError(f'camera_info: distortion model {model!r} is not supported '
                           '(plumb_bob or rational_polynomial)')
    try:
        return Camera(name, msg.width or None, msg.height or None, np.asarray(msg.k, float),
                      np.asarray(msg.d, float), frame_id=msg.header.frame_id)
    except CalibrationError as err:
        raise MessageError(f'camera_info: {err}') from None


def _check_size(width: int, height: int, expected: tuple[int, int] | None) -> None:
    """Refuse an image not of the expected size (a configured, valid one) or, with none
    expected, an empty or absurdly large image."""
    if expected is not None:
        if (width, height) != tuple(expected):
            raise MessageError(f'image is {width}x{height}, expected {expected[0]}x{expected[1]}')
        return
    if width <= 0 or height <= 0 or width * height > MAX_IMAGE_PIXELS:
        raise MessageError(f'image size {width}x{height} refused (empty, or over '
                           f'{MAX_IMAGE_PIXELS} pixels)')


def odometry_to_msg(position: np.ndarray, quaternion_xyzw: np.ndarray, velocity: np.ndarray,
                    angular_velocity: np.ndarray, header: Header, child_frame_id: str,
                    pose_covariance: np.ndarray | None = None,
                    twist_covariance: np.ndarray | None = None) -> Odometry:
    """nav_msgs/Odometry of a body: pose in header.frame_id, twist in child_frame_id (REP-105).

    `velocity` is given in the parent frame (as autopilots report it) and rotated into
    the child frame here: v_child = R(q)^T v_parent. `angular_velocity` is already in
    the child frame. The covariances (6x6, the message's frames) are zero (unknown)
    when not given.
    """
    msg = Odometry(header=header, child_frame_id=child_frame_id)
    if pose_covariance is not None:
        msg.pose.covariance = np.asarray(pose_covariance, dtype=float).reshape(36)
    if twist_covariance is not None:
        msg.twist.covariance = np.asarray(twist_covariance, dtype=float).reshape(36)
    p = msg.pose.pose.position
    p.x, p.y, p.z = map(float, position)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, quaternion_xyzw)
    u, w = -np.asarray(quaternion_xyzw[:3], dtype=float), float(quaternion_xyzw[3])  # conjugate
    v = np.asarray(velocity, dtype=float)
    t = 2.0 * np.cross(u, v)
    v_child = v + w * t + np.cross(u, t)
    tw = msg.twist.twist
    tw.linear.x, tw.linear.y, tw.linear.z = map(float, v_child)
    tw.angular.x, tw.angular.y, tw.angular.z = map(float, angular_velocity)
    return msg


def msg_to_odometry(msg: Odometry) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Odometry to (position, unit quaternion xyzw, linear and angular velocity in the child
    frame); see unit_quaternion."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    v, w = msg.twist.twist.linear, msg.twist.twist.angular
    return (np.array([p.x, p.y, p.z]), unit_quaternion(q.x, q.y, q.z, q.w),
            np.array([v.x, v.y, v.z]), np.array([w.x, w.y, w.z]))


def image_to_gray(msg: Image | RawImage,
                  expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """sensor_msgs/Image to an 8-bit grey array (mono8 without a copy); as image_to_bgr."""
    if msg.encoding != 'mono8':
        return cv2.cvtColor(image_to_bgr(msg, expected_size), cv2.COLOR_BGR2GRAY)
    _check_size(msg.width, msg.height, expected_size)
    if msg.step < msg.width or len(msg.data) < msg.step * msg.height:
        raise MessageError(f'image data too short: {len(msg.data)} bytes for '
                           f'{msg.width}x{msg.height} mono8 step {msg.step}')
    buf = np.frombuffer(msg.data, np.uint8, count=msg.step * msg.height)
    return buf.reshape(msg.height, msg.step)[:, :msg.width]


def compressed_to_gray(msg: CompressedImage,
                       expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg, png) decoded straight to 8-bit grey."""
    return _decode(msg, expected_size, cv2.IMREAD_GRAYSCALE)


def _decode(msg: CompressedImage, expected_size: tuple[int, int] | None, flags: int) -> np.ndarray:
    """Decode a JPEG or PNG whose header says it has an acceptable size (checked first,
    so a wrong or absurd size costs no decoding)."""
    _check_size(*compressed_size(msg), expected_size)
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), flags)
    if img is None:
        raise MessageError(f'cannot decode compressed image (format {msg.format!r}, '
                           f'{len(msg.data)} bytes)')
    _check_size(img.shape[1], img.shape[0], expected_size)
    return img


def compressed_size(msg: CompressedImage) -> tuple[int, int]:
    """(width, height) read from a JPEG's start of frame or a PNG's IHDR, not decoding."""
    data = memoryview(msg.data).cast('B')
    try:
        if data[:8] == _PNG_SIGNATURE and data[12:16] == b'IHDR':
            return struct.unpack_from('>II', data, 16)
        if data[:2] == b'\xff\xd8':
            return _jpeg_size(data)
    except (struct.error, IndexError):
        pass
    raise MessageError(f'cannot decode compressed image (format {msg.format!r}, '
                       f'{len(msg.data)} bytes): no JPEG or PNG header')


def _jpeg_size(data: memoryview) -> tuple[int, int]:
    """The size in a JPEG's first start-of-frame segment (IndexError if there is none)."""
    pos = 2
    while data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker in _JPEG_SOF:
            height, width = struct.unpack_from('>HH', data, pos + 5)
            return width, height
        if marker == 0xFF:                       # fill byte
            pos += 1
        else:
            pos += 2 + struct.unpack_from('>H', data, pos + 2)[0]
    raise IndexError('no start of frame')
