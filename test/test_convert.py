"""Message <-> numpy conversions: exact round trips, clear errors on malformed input."""
import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from uav_vs.ros import convert as cv
from uav_vs.vision.camera import Camera

RNG = np.random.default_rng(7)
BGR = RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)


def test_image_round_trip_and_encodings():
    header = Header(frame_id='cam1_optical')
    msg = cv.bgr_to_image(BGR, header)
    assert (msg.width, msg.height, msg.encoding, msg.step) == (64, 48, 'bgr8', 192)
    assert np.array_equal(cv.image_to_bgr(msg, (64, 48)), BGR)
    rgb = Image(height=48, width=64, encoding='rgb8', step=192)
    rgb.data = BGR[:, :, ::-1].tobytes()
    assert np.array_equal(cv.image_to_bgr(rgb), BGR)
    mono = Image(height=48, width=64, encoding='mono8', step=64)
    mono.data = BGR[:, :, 0].tobytes()
    assert np.array_equal(cv.image_to_bgr(mono)[:, :, 2], BGR[:, :, 0])


def test_padded_rows_are_read_correctly():
    padded = np.zeros((48, 200), np.uint8)
    padded[:, :192] = BGR.reshape(48, 192)
    msg = Image(height=48, width=64, encoding='bgr8', step=200)
    msg.data = padded.tobytes()
    assert np.array_equal(cv.image_to_bgr(msg), BGR)


@pytest.mark.parametrize('encoding, width, data_len, match', [
    ('16UC1', 64, 48 * 128, "unsupported encoding '16UC1'"),
    ('bgr8', 32, 48 * 96, 'image is 32x48, expected 64x48'),
    ('bgr8', 64, 100, 'image data too short'),
])
def test_malformed_images_raise(encoding, width, data_len, match):
    msg = Image(height=48, width=width, encoding=encoding, step=data_len // 48)
    msg.data = bytes(data_len)
    with pytest.raises(cv.MessageError, match=match):
        cv.image_to_bgr(msg, (64, 48))


def test_compressed_round_trip_and_garbage():
    smooth = cv2.GaussianBlur(BGR, (0, 0), 4)
    out = cv.compressed_to_bgr(cv.bgr_to_compressed(smooth, Header(), quality=95), (64, 48))
    assert np.abs(out.astype(int) - smooth).mean() < 1.5
    png = CompressedImage(format='png')
    png.data = cv2.imencode('.png', BGR)[1].tobytes()
    assert np.array_equal(cv.compressed_to_bgr(png), BGR)
    bad = CompressedImage(format='jpeg')
    bad.data = b'not an image'
    with pytest.raises(cv.MessageError, match='cannot decode'):
        cv.compressed_to_bgr(bad)


def test_polygon_pose_twist_and_stamp_round_trips():
    pts = np.array([[1.5, 2.25, 0.5], [np.nan, np.nan, 0.0]])
    back = cv.polygon_to_array(cv.points_to_polygon(pts, Header()))
    assert np.array_equal(back, pts, equal_nan=True)
    q = np.array([0.0, 0.0, np.sin(0.4), np.cos(0.4)])
    pos, quat = cv.msg_to_pose(cv.pose_to_msg(np.array([1.0, -2.0, 3.0]), q, Header()))
    assert np.array_equal(pos, [1.0, -2.0, 3.0]) and np.array_equal(quat, q)
    assert cv.yaw_of(q) == pytest.approx(0.8)
    assert np.allclose(cv.yaw_quaternion(0.8), q)
    assert cv.yaw_of(cv.yaw_quaternion(-3.0)) == pytest.approx(-3.0)
    lin, ang = cv.msg_to_twist(cv.twist_to_msg(np.array([1.0, 2, 3]), np.array([0, 0, 0.5]),
                                               Header()))
    assert np.array_equal(lin, [1, 2, 3]) and ang[2] == 0.5
    ns = 1_700_000_000_123_456_789
    assert cv.stamp_to_ns(cv.ns_to_stamp(ns)) == ns


def test_a_message_in_another_frame_is_refused_naming_both_frames():
    cv.check_frame(Header(frame_id='world'), 'world')
    with pytest.raises(cv.MessageError, match="^frame 'map', expected 'world'$"):
        cv.check_frame(Header(frame_id='map'), 'world')


def test_a_pose_in_another_frame_or_not_finite_is_refused():
    q = np.array([0.0, 0.0, 0.6, 0.8])
    position, quaternion = cv.msg_to_pose_in(
        cv.pose_to_msg([1.0, 2.0, 3.0], q, Header(frame_id='world')), 'world')
    assert position.tolist() == [1.0, 2.0, 3.0] and np.allclose(quaternion, q)
    with pytest.raises(cv.MessageError, match="^frame 'map', expected 'world'$"):
        cv.msg_to_pose_in(cv.pose_to_msg([1.0, 2.0, 3.0], q, Header(frame_id='map')), 'world')
    with pytest.raises(cv.MessageError, match='^non-finite position$'):
        cv.msg_to_pose_in(cv.pose_to_msg([1.0, np.nan, 3.0], q, Header(frame_id='world')),
                          'world')


def test_a_pose_covariance_must_be_one():
    q, header = np.array([0.0, 0.0, 0.6, 0.8]), Header(frame_id='world')
    cov = np.diag([0.01, 0.01, 0.02, 1e6, 1e6, 0.003])
    *_, back = cv.msg_to_pose_cov_in(cv.pose_cov_to_msg([1.0, 2.0, 3.0], q, cov, header), 'world')
    assert np.array_equal(back, cov)
    bad = cov.copy()
    bad[0, 1] = bad[1, 0] = 0.02                   # x, y correlated beyond +-1: no covariance
    asymmetric = cov.copy()
    asymmetric[0, 1] = 0.001
    for wrong, match in ((bad, 'positive semi-definite'), (asymmetric, 'not symmetric'),
                         (np.diag([0.01, 0.0, 0.02, 1.0, 1.0, 1.0]), 'positive diagonal')):
        with pytest.raises(cv.MessageError, match=match):
            cv.msg_to_pose_cov_in(cv.pose_cov_to_msg([1.0, 2.0, 3.0], q, wrong, header), 'world')


@pytest.mark.parametrize('encoding, channels, frame_id', [('bgr8', 3, 'cam1_optical'),
                                                          ('mono8', 1, ''), ('rgba8', 4, 'abc')])
def test_serialized_image_is_read_in_place_as_rclpy_reads_it(encoding, channels, frame_id):
    from rclpy.serialization import serialize_message
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 256, (7, 5, channels), np.uint8)
    msg = Image(header=Header(frame_id=frame_id), height=7, width=5, encoding=encoding,
                step=5 * channels)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_123, 456_789
    msg.data = pixels.tobytes()
    raw = serialize_message(msg)
    got = cv.image_from_cdr(raw)
    assert (got.header, got.height, got.width, got.encoding, got.step) == \
        (msg.header, 7, 5, encoding, 5 * channels)
    assert bytes(got.data) == bytes(msg.data)
    if encoding != 'rgba8':
        read = cv.image_to_bgr if channels == 3 else cv.image_to_gray
        np.testing.assert_array_equal(read(got, (5, 7)), read(msg, (5, 7)))
    for cut in (3, 20, len(raw) - 1):          # truncated anywhere: a clear error
        with pytest.raises(cv.MessageError, match='malformed serialized image'):
            cv.image_from_cdr(raw[:cut])



def test_outlines_become_one_line_list_marker():
    from visualization_msgs.msg import ImageMarker
    header = Header(frame_id='cam1')
    square = cv.rect_corners(10, 20, 4, 2)
    marker = cv.outlines_to_marker([square, square + 100], header, (1, 0.5, 0, 1), ns='x')
    assert (marker.header, marker.ns, marker.type) == (header, 'x', ImageMarker.LINE_LIST)
    drawn = np.array([(p.x, p.y) for p in marker.points]).reshape(8, 2, 2)
    np.testing.assert_array_equal(drawn[:4, 0], square)            # each edge from a corner
    np.testing.assert_array_equal(drawn[:4, 1], np.roll(square, -1, axis=0))   # to the next
    np.testing.assert_array_equal(drawn[4:, 0], square + 100)
    assert (marker.outline_color.r, marker.outline_color.g) == (1.0, 0.5)
    assert cv.outlines_to_marker([], header, (1, 1, 1, 1)).points == []


def test_a_serialized_image_becomes_a_serialized_jpeg_of_it():
    from rclpy.serialization import deserialize_message, serialize_message
    y, x = np.mgrid[0:48, 0:64]
    smooth = np.dstack([x * 4, y * 5, (x + y) * 2]).astype(np.uint8)
    header = Header(frame_id='cam1')
    header.stamp.sec, header.stamp.nanosec = 1_700_000_000, 5
    raw = serialize_message(cv.bgr_to_image(smooth, header))
    jpeg = deserialize_message(cv.image_cdr_to_jpeg_cdr(raw, 90), CompressedImage)
    assert (jpeg.header, jpeg.format) == (header, 'jpeg')
    decoded = cv2.imdecode(np.frombuffer(bytes(jpeg.data), np.uint8), cv2.IMREAD_COLOR)
    assert np.abs(decoded.astype(int) - smooth).mean() < 2.0
    with pytest.raises(cv.MessageError, match='image data too short'):
        bad = cv.bgr_to_image(smooth, header)
        bad.data = bad.data[:100]
        cv.image_cdr_to_jpeg_cdr(serialize_message(bad))
    half = deserialize_message(cv.image_cdr_to_jpeg_cdr(raw, 90, scale=0.5), CompressedImage)
    decoded = cv2.imdecode(np.frombuffer(bytes(half.data), np.uint8), cv2.IMREAD_COLOR)
    shrunk = cv2.resize(smooth, (32, 24), interpolation=cv2.INTER_AREA)
    assert decoded.shape == (24, 32, 3) and np.abs(decoded.astype(int) - shrunk).mean() < 2.0
    jpeg_frame = serialize_message(cv.bgr_to_compressed(smooth, header))      # from a JPEG stream
    again = deserialize_message(cv.image_cdr_to_jpeg_cdr(jpeg_frame, 90, 0.5, compressed=True),
                                CompressedImage)
    decoded = cv2.imdecode(np.frombuffer(bytes(again.data), np.uint8), cv2.IMREAD_COLOR)
    assert again.header == header and decoded.shape == (24, 32, 3)
    assert np.abs(decoded.astype(int) - shrunk).mean() < 3.0
    with pytest.raises(cv.MessageError):
        broken = cv.bgr_to_compressed(smooth, header)
        broken.data = bytes(broken.data[:40]) + bytes(200)
        cv.image_cdr_to_jpeg_cdr(serialize_message(broken), compressed=True)


def test_a_serialized_marker_scales_with_its_image():
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import ImageMarker
    header = Header(frame_id='cam1')
    marker = cv.outlines_to_marker([cv.rect_corners(10, 20, 4, 2)], header, (1, 1, 0, 1))
    marker.position.x, marker.position.y = 8.0, 6.0
    half = deserialize_message(cv.marker_cdr_scaled(serialize_message(marker), 0.5), ImageMarker)
    assert half.header == header and (half.position.x, half.position.y) == (4.0, 3.0)
    np.testing.assert_allclose([(p.x, p.y) for p in half.points],
                               [(p.x / 2, p.y / 2) for p in marker.points])
    assert (half.scale, half.outline_color) == (marker.scale, marker.outline_color)
    with pytest.raises(cv.MessageError, match='ImageMarker'):
        cv.marker_cdr_scaled(b'\x00\x01\x00\x00' + b'\x07' * 3, 0.5)

@pytest.mark.parametrize('n', [0, 4, 5, 8, 12, 14])
def test_camera_from_camera_info_of_every_opencv_model(n):
    """Camera -> CameraInfo -> Camera projects as the original (cv2.projectPoints' model)."""
    K = np.array([[510.0, 0.0, 318.0], [0.0, 505.0, 242.0], [0.0, 0.0, 1.0]])
    D = np.array([0.12, -0.03, 0.0006, -0.0003, 0.001, 0.25, -0.04, 0.008,
                  0.001, -0.0005, 0.0008, 0.0002, 0.01, -0.02])[:n]
    cam = Camera('c', 640, 480, K, D)
    info = cv.camera_info(cam.camera_info_fields(), Header(frame_id='c_optical'))
    back = cv.camera_from_info(info)
    X = np.random.default_rng(n).uniform([-1, -1, 2], [1, 1, 4], (50, 3))
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, D if n else None)
    np.testing.assert_allclose(back.project(X), ref.reshape(-1, 2), atol=1e-9)
    assert (back.width, back.height, back.frame_id) == (640, 480, 'c_optical')


def test_camera_info_the_camera_model_cannot_use_is_refused():
    k = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]
    with pytest.raises(cv.MessageError, match="^camera_info: distortion model 'equidistant'"):
        cv.camera_from_info(CameraInfo(k=k, d=[0.1, 0.0, 0.0, 0.0], distortion_model='equidistant'))
    with pytest.raises(cv.MessageError, match=r'^camera_info: D: expected 0, 4, 5, 8, 12 or 14'):
        cv.camera_from_info(CameraInfo(k=k, d=[0.1] * 6, distortion_model='plumb_bob'))
    with pytest.raises(cv.MessageError, match=r'^camera_info: K: expected'):
        cv.camera_from_info(CameraInfo(distortion_model='plumb_bob'))     # uncalibrated: K = 0
    assert cv.camera_from_info(CameraInfo(k=k)).width is None              # size 0: unknown
