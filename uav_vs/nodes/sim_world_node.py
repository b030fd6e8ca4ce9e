"""sim_world: the closed-loop simulated world (chapter section 5), one process.

Runs the MAVLink vehicle simulator in-process (its endpoint `vehicle.connection` is
what mavlink_relay_node connects to) and renders, from the vehicle's true state, the
ground cameras of `cameras.names` (config/ground_trinocular.yaml) at `ground.rate` and
the onboard down-looking camera (config/onboard.yaml) at `onboard.rate`. Start it with
the three params files:

    sim_world --ros-args --params-file config/ground_trinocular.yaml \\
        --params-file config/onboard.yaml --params-file config/sim_world.yaml

Publishes, every frame with the stamp of the instant the truth was sampled:
`camK/image_raw` (sensor_msgs/Image bgr8, sensor-data QoS), `camK/image_raw/compressed`
(JPEG of `world.jpeg_quality`, encoded only while someone subscribes, e.g. a bag
recorder) and `camK/camera_info` for each ground camera, the same three under `onboard/`
(not while the onboard camera is below `onboard.min_height`), `truth/pose`
(PoseStamped, base_link in `world` ENU, for evaluation only) and /diagnostics.
"""
import time

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from uav_vs.nodes.homography_pose_node import ONBOARD_PARAMS
from uav_vs.ros.convert import bgr_to_compressed, bgr_to_image, camera_info, pose_to_msg
from uav_vs.ros.ground_params import declare_cameras, declare_landmarks
from uav_vs.ros.node_main import OK, WARN, Diagnostics, run
from uav_vs.ros.params import Param, T, declare
from uav_vs.sim.ground_scene import GroundScene
from uav_vs.sim.mavlink_vehicle import CUSTOM_MODES, MavlinkVehicle, VehicleConfig
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.sim.world import SimWorld, VehicleState
from uav_vs.vision.camera import Camera
from uav_vs.vision.ground_config import load_ground_config
from uav_vs.vision.onboard_config import load_onboard_config

_V = VehicleConfig()
PARAMS = [
    Param('vehicle.connection', T.STRING, _V.connection,
          'MAVLink endpoint the vehicle serves: tcpin:HOST:PORT, udpin:HOST:PORT or '
          'udpout:HOST:PORT'),
    Param('vehicle.system_id', T.INTEGER, _V.system_id, 'MAVLink system id of the vehicle', 1, 255),
    Param('vehicle.autopilot', T.STRING, _V.autopilot,
          "whose MAVLink behaviour the vehicle follows: ArduPilot Copter's or PX4's",
          choices=tuple(CUSTOM_MODES)),
    Param('vehicle.rate', T.DOUBLE, _V.rate, 'simulation and telemetry loop rate, Hz',
          10.0, 1000.0),
    Param('vehicle.ready_delay', T.DOUBLE, _V.ready_delay,
          'seconds after start before the vehicle can arm (estimator ready)', 0.0, 600.0),
    Param('ground.rate', T.DOUBLE, 15.0, 'ground camera frame rate, Hz (0 = not rendered)',
          0.0, 60.0),
    Param('ground.noise_sigma', T.DOUBLE, 2.0, 'ground images: Gaussian sensor noise, grey levels',
          0.0, 50.0),
    Param('ground.background', T.STRING, 'aero1.jpg',
          'ground photograph under the flight area, a file in uav_vs/sim/assets'),
    Param('onboard.rate', T.DOUBLE, 10.0, 'onboard camera frame rate, Hz (0 = not rendered)',
          0.0, 60.0),
    Param('onboard.noise_sigma', T.DOUBLE, 1.5, 'onboard images: Gaussian sensor noise, grey '
          'levels', 0.0, 50.0),
    Param('onboard.min_height', T.DOUBLE, 0.3,
          'no onboard image while the camera is lower than this above the ground, m', 0.05, 100.0),
    Param('world.frame_id', T.STRING, 'world', 'frame of truth/pose (ENU)'),
    Param('world.seed', T.INTEGER, 0, 'sensor noise seed', 0, 2**31 - 1),
    Param('world.jpeg_quality', T.INTEGER, 90, 'JPEG quality of image_raw/compressed', 1, 100),
    Param('world.diagnostics_period', T.DOUBLE, 1.0, 'diagnostics period, s', 0.05, 60.0),
]


class CameraOutput:
    """One camera's topics: `image_raw`, `image_raw/compressed` (encoded only while it has
    a subscriber) and `camera_info`, all with one header per frame."""

    def __init__(self, node: Node, prefix: str, camera: Camera, jpeg_quality: int) -> None:
        self.frame_id, self.quality = camera.frame_id, jpeg_quality
        self.info = camera.camera_info_fields()
        self.raw = node.create_publisher(Image, f'{prefix}/image_raw', qos_profile_sensor_data)
        self.compressed = node.create_publisher(CompressedImage, f'{prefix}/image_raw/compressed',
                                                qos_profile_sensor_data)
        self.info_pub = node.create_publisher(CameraInfo, f'{prefix}/camera_info', 10)

    def publish(self, image: np.ndarray, stamp: Time) -> None:
        header = Header(stamp=stamp, frame_id=self.frame_id)
        self.raw.publish(bgr_to_image(image, header))
        if self.compressed.get_subscription_count():
            self.compressed.publish(bgr_to_compressed(image, header, self.quality))
        self.info_pub.publish(camera_info(self.info, header))


class SimWorldNode(Node):
    def __init__(self) -> None:
        super().__init__('sim_world')
        ground = load_ground_config({**declare_cameras(self), **declare_landmarks(self)})
        onboard = load_onboard_config(declare(self, [s for s in ONBOARD_PARAMS
                                                     if s.name.startswith('camera')]))
        p = declare(self, PARAMS)
        self.frame_id = p['world.frame_id']
        try:
            ground_scene = GroundScene(ground, background=p['ground.background'],
                                       noise_sigma=p['ground.noise_sigma'], seed=p['world.seed'])
        except FileNotFoundError as err:
            raise ValueError(f'ground.background: {err}') from None
        onboard_scene = OnboardScene(onboard.camera, onboard.camera_to_body,
                                     noise_sigma=p['onboard.noise_sigma'], seed=p['world.seed'])
        try:
            vehicle = MavlinkVehicle(VehicleConfig(
                connection=p['vehicle.connection'], system_id=p['vehicle.system_id'],
                rate=p['vehicle.rate'], ready_delay=p['vehicle.ready_delay'],
                autopilot=p['vehicle.autopilot']))
        except OSError as err:
            raise ValueError(f"vehicle.connection: cannot serve {p['vehicle.connection']}: "
                             f'{err.strerror or err}') from None
        self.world = SimWorld(vehicle.start(), ground_scene, onboard_scene,
                              p['onboard.min_height'])

        quality = p['world.jpeg_quality']
        self.cameras = [CameraOutput(self, cam.name, cam, quality) for cam in ground.cameras]
        self.onboard_camera = CameraOutput(self, 'onboard', onboard.camera, quality)
        self.truth_pub = self.create_publisher(PoseStamped, 'truth/pose', 50)
        self.counts = dict(ground_frames=0, onboard_frames=0, onboard_too_low=0)
        self.render_ms = dict(ground_render_ms=float('nan'), onboard_render_ms=float('nan'))
        if p['ground.rate'] > 0:
            self.create_timer(1.0 / p['ground.rate'], self.on_ground)
        if p['onboard.rate'] > 0:
            self.create_timer(1.0 / p['onboard.rate'], self.on_onboard)
        self.diag = Diagnostics(self, hardware_id=p['vehicle.connection'])
        self.create_timer(p['world.diagnostics_period'], self.publish_diagnostics)
        host, port = vehicle.address
        self.get_logger().info(f'vehicle on {p["vehicle.connection"]} ({host}:{port}); '
                               f'{len(self.cameras)} ground cameras at {p["ground.rate"]:g} Hz, '
                               f'onboard camera at {p["onboard.rate"]:g} Hz')

    def _sample(self) -> tuple[VehicleState, Header]:
        """The vehicle's truth now, published on truth/pose, and the stamp of that instant."""
        state = self.world.state()
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=self.frame_id)
        self.truth_pub.publish(pose_to_msg(state.position, state.quaternion, header))
        return state, header

    def on_ground(self) -> None:
        state, header = self._sample()
        start = time.perf_counter()
        images = self.world.ground_images(state)
        self.render_ms['ground_render_ms'] = round((time.perf_counter() - start) * 1e3, 2)
        for camera, image in zip(self.cameras, images):
            camera.publish(image, header.stamp)
        self.counts['ground_frames'] += 1

    def on_onboard(self) -> None:
        state, header = self._sample()
        start = time.perf_counter()
        image = self.world.onboard_image(state)
        if image is None:
            self.counts['onboard_too_low'] += 1
            return
        self.render_ms['onboard_render_ms'] = round((time.perf_counter() - start) * 1e3, 2)
        self.onboard_camera.publish(image, header.stamp)
        self.counts['onboard_frames'] += 1

    def publish_diagnostics(self) -> None:
        state = self.world.state()
        armed = 'armed' if state.armed else 'disarmed'
        level = OK if self.counts['ground_frames'] or self.counts['onboard_frames'] else WARN
        x, y, z = state.position
        flying = 'flying' if state.flying else 'landed'
        self.diag.publish(level, f'{state.mode}, {armed}, {flying}', {
            **self.counts, **self.render_ms, 'mode': state.mode, 'armed': state.armed,
            'flying': state.flying, 'position': f'{x:.3f} {y:.3f} {z:.3f}',
            'yaw': f'{state.yaw:.4f}'})

    def destroy_node(self) -> None:
        self.world.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    run(SimWorldNode, 'sim_world', args)


if __name__ == '__main__':
    main()
