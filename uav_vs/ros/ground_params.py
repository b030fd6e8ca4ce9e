"""Parameters of the ground station shared by camshift_node and trinocular_pose_node.

The keys are those of config/ground_trinocular.yaml: `cameras.names` and per camera
`cameras.<name>.{width,height,frame_id,K,D,R,t,latency}`; `landmarks.names` and per landmark
`landmarks.<name>.{position,sample,hue,saturation,value}` (hue required unless there
is a sample).
"""
from rclpy.node import Node

from uav_vs.ros.params import REQUIRED, Param, T, declare


def declare_landmarks(node: Node) -> dict:
    """Declare `landmarks.*`; return them as a flat dict."""
    out = declare(node, [Param('landmarks.names', T.STRING_ARRAY, description=(
        'landmark names; their order is the point index in every landmarks message'))])
    specs = []
    for name in out['landmarks.names']:
        key = f'landmarks.{name}.'
        sample = declare(node, [Param(key + 'sample', T.STRING, '', (
            'image file of the landmark as the cameras see it (alpha 0: not the landmark); '
            'when set, the colour model comes from it, not from hue and saturation'))])
        out.update(sample)
        by_sample = bool(sample[key + 'sample'])
        specs += [
            Param(key + 'position', T.DOUBLE_ARRAY, description='position in base_link FLU, m',
                  size=3),
            Param(key + 'hue', T.INTEGER_ARRAY, [0, 179] if by_sample else REQUIRED, (
                'OpenCV hue range [lo, hi] in 0..180; lo > hi wraps through 0 (unused with a '
                'sample)'), low=0, high=180, size=2),
            Param(key + 'saturation', T.INTEGER_ARRAY, [0, 255] if by_sample else [60, 255],
                  'saturation range, 0..255 (unused with a sample)', 0, 255, size=2),
            Param(key + 'value', T.INTEGER_ARRAY, [40, 255], 'value range, 0..255', 0, 255,
                  size=2),
        ]
    specs.append(Param('landmarks.radius', T.DOUBLE, 0.1, 'landmark sphere radius, m', 0.001, 10.0))
    return {**out, **declare(node, specs)}


def declare_cameras(node: Node, only: str | None = None) -> dict:
    """Declare `cameras.*` (all cameras, or just `only`); return them as a flat dict."""
    names = declare(node, [Param('cameras.names', T.STRING_ARRAY, description=(
        'ground cameras; each has its own cameras.<name>.* calibration'))])
    if only is not None and only not in names['cameras.names']:
        raise ValueError(f'camera: {only!r} is not in cameras.names {names["cameras.names"]}')
    specs = []
    for name in names['cameras.names'] if only is None else [only]:
        key = f'cameras.{name}.'
        specs += [
            Param(key + 'width', T.INTEGER, description='image width, px', low=1, high=100000),
            Param(key + 'height', T.INTEGER, description='image height, px', low=1, high=100000),
            Param(key + 'frame_id', T.STRING, f'{name}_optical', 'optical frame of the camera'),
            Param(key + 'K', T.DOUBLE_ARRAY, description='intrinsics, 3x3 row-major (eq 15)',
                  size=9),
            Param(key + 'D', T.DOUBLE_ARRAY, description=(
                "distortion in OpenCV's order, k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]: "
                '4, 5, 8, 12 or 14 numbers (uav_vs_calibrate writes 5 or 8)')),
            Param(key + 'R', T.DOUBLE_ARRAY, description=(
                'world-to-camera rotation, 3x3 row-major (eq 16)'), size=9),
            Param(key + 't', T.DOUBLE_ARRAY, description='world-to-camera translation, m (eq 16)',
                  size=3),
            Param(key + 'latency', T.DOUBLE, 0.0, (
                'how much later than the instant it shows the camera stamps a frame, after '
                'the first camera (uav_vs_calibrate rig --latency), s: taken off its stamps '
                'before the cameras are matched'), -1.0, 1.0),
        ]
    return {**names, **declare(node, specs)}
