"""sim_world: the closed-loop simulated world (chapter section 5), one process.

Its vehicle (`vehicle.model`) is the MAVLink vehicle simulator, run in-process (its
endpoint `vehicle.connection` is what mavlink_relay_node connects to), or ArduPilot SITL,
whose physics' own state it reads as SIM_STATE from `vehicle.sitl_connection` (a SITL
port the relay does not use; uav_vs.sim.sitl_truth). It renders, from that true state, the
ground cameras of `cameras.names` (config/ground_trinocular.yaml) at `ground.rate` and
the onboard down-looking camera (config/onboard.yaml) at `onboard.rate`. Start it with
the three params files:

    sim_world --ros-args --params-file config/ground_trinocular.yaml \\
        --params-file config/onboard.yaml --params-file config/sim_world.yaml

Publishes, every frame with the stamp of the instant the truth was sampled (a ground
camera lagging the first, with `unsynchronised` on: its own capture's):
`camK/image_raw` (sensor_msgs/Image bgr8, sensor-data QoS), `camK/image_raw/compressed`
(JPEG of `world.jpeg_quality`, encoded only while someone subscribes, e.g. a bag
recorder) and `camK/camera_info` for each ground camera, the same three under `onboard/`
(not while the onboard camera is below `onboard.min_height`), `truth/pose`
(PoseStamped, base_link in `world` ENU, for evaluation only) and /diagnostics. With
`ground_target.enabled` the onboard camera also sees a picture (`ground_target.template`)
lying on the ground and driving round a circle (uav_vs.sim.ground_target), whose true
centre and heading go out with every onboard frame on `truth/target` (PoseStamped, z = 0).
The camera effects of uav_vs.sim.camera_effects (noise, lens distortion, motion blur,
exposure drift, JPEG artefacts, dropped frames, latency, unsynchronised ground cameras,
landmarks partly occluded),
calibration error (the cameras render from a rig a little off the calibration
camera_info carries) and, for the builtin vehicle, wind gusts and the drift of its
estimate are each switched by their own parameter group; by default only the noise and
the calibrated distortion are on.
Several vehicles share one world: each vehicle's sim_world (or SITL) has its home at
`vehicle.start` in `world`, and serves its truth on `vehicle.truth_connection`; the
sim_world that renders the ground cameras reads the others' (`fleet.names`, each with
`fleet.<name>.truth_connection`, `.system_id`, `.start` and `.landmarks`, a params file
of its landmark colours such as config/landmarks_uav2.yaml), draws them all and publishes
each one's truth at the ground frames' instants on `<name>/truth/pose`.
The service `ground_cameras/enable` (std_srvs/SetBool) covers the ground cameras (false:
they deliver no frame, counted as `blind_frames`; the truth goes on) and uncovers them.
Every parameter is read-only: the world, its vehicle and cameras are built at start-up.
"""
import math
import time
from dataclasses import replace
from typing import Callable

import cv2
import numpy as np
import yaml
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header
from std_srvs.srv import SetBool

from uav_vs.autopilot.frames import euler_to_quat
from uav_vs.nodes.homography_pose_node import ONBOARD_PARAMS
from uav_vs.ros.convert import (bgr_to_compressed, bgr_to_image, camera_info, ns_to_stamp,
                                pose_to_msg, stamp_to_ns)
from uav_vs.ros.ground_params import declare_cameras, declare_landmarks
from uav_vs.ros.image_files import read_image
from uav_vs.ros.node_main import OK, WARN, Diagnostics, run
from uav_vs.ros.params import Param, T, declare
from uav_vs.sim.calibration_error import CalibrationSpread, true_camera, true_mount
from uav_vs.sim.camera_effects import CameraEffects, CameraLags, EffectsConfig, Latency, Occlusion
from uav_vs.sim.delay_line import DelayLine
from uav_vs.sim.ground_scene import GroundScene
from uav_vs.sim.ground_target import CirclePath, GroundTarget
from uav_vs.sim.mavlink_vehicle import CUSTOM_MODES, MavlinkVehicle, VehicleConfig
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.sim.sitl_truth import SitlTruth
from uav_vs.sim.world import SimulatedVehicle, SimWorld, Vehicle, VehicleState
from uav_vs.vision.camera import CalibrationError, Camera
from uav_vs.vision.ground_config import GroundConfig, load_ground_config, read_params_file
from uav_vs.vision.onboard_config import OnboardConfig, load_onboard_config

_V = VehicleConfig()
MODELS = ('builtin', 'sitl')
SITL_WAIT_S = 30.0      # for the first SIM_STATE at start-up
PARAMS = [
    Param('vehicle.model', T.STRING, 'builtin',
          'the vehicle: builtin (the MAVLink vehicle simulator, served on vehicle.connection) '
          'or sitl (ArduPilot SITL, its truth read from vehicle.sitl_connection)', choices=MODELS),
    Param('vehicle.connection', T.STRING, _V.connection,
          'builtin: MAVLink endpoint the vehicle serves: tcpin:HOST:PORT, udpin:HOST:PORT or '
          'udpout:HOST:PORT'),
    Param('vehicle.sitl_connection', T.STRING, 'tcp:127.0.0.1:5762',
          "sitl: a SITL MAVLink port the relay does not use (SERIAL1 or SERIAL2), where the "
          'SIM_STATE truth is read: tcp:HOST:PORT or udpin:HOST:PORT'),
    Param('vehicle.truth_connection', T.STRING, '',
          'builtin: also serve the true state as SIM_STATE on this MAVLink endpoint, as SITL '
          'does on SERIAL2 (another sim_world reads it with vehicle.model sitl); empty: no'),
    Param('vehicle.system_id', T.INTEGER, _V.system_id,
          'MAVLink system id of the vehicle (builtin or SITL)', 1, 255),
    Param('vehicle.autopilot', T.STRING, _V.autopilot,
          "builtin: whose MAVLink behaviour the vehicle follows: ArduPilot Copter's or PX4's",
          choices=tuple(CUSTOM_MODES)),
    Param('vehicle.rate', T.DOUBLE, _V.rate, 'builtin: simulation and telemetry loop rate, Hz',
          10.0, 1000.0),
    Param('vehicle.ready_delay', T.DOUBLE, _V.ready_delay,
          'builtin: seconds after start before the vehicle can arm (estimator ready)', 0.0, 600.0),
    Param('vehicle.start', T.DOUBLE_ARRAY, [0.0, 0.0],
          "where the vehicle's home (its autopilot's local origin, where it stands at boot) "
          'is in world: x y, m', size=2),
    Param('wind.enabled', T.BOOL, False, 'builtin: horizontal wind gusts the velocity loop has '
          'not yet rejected push the vehicle'),
    Param('wind.gust_sigma', T.DOUBLE, 0.05, 'builtin: spread of the gust velocity per axis, m/s',
          0.0, 5.0),
    Param('wind.time_constant', T.DOUBLE, 1.0, 'builtin: time constant of the gusts, s',
          0.05, 600.0),
    Param('drift.enabled', T.BOOL, False, "builtin: the autopilot's position estimate drifts "
          'from the truth (LOCAL_POSITION_NED, ODOMETRY, GLOBAL_POSITION_INT)'),
    Param('drift.rate', T.DOUBLE, 0.01, 'builtin: random-walk rate of the drift per axis, '
          'm/sqrt(s)', 0.0, 1.0),
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
    # Camera effects (uav_vs.sim.camera_effects), each on its own switch.
    Param('noise.enabled', T.BOOL, True, 'add Gaussian sensor noise of ground.noise_sigma and '
          'onboard.noise_sigma'),
    Param('distortion.enabled', T.BOOL, True, "render through each camera's calibrated lens "
          'distortion D, published in camera_info; false: ideal pinhole images, D = 0'),
    Param('calibration.enabled', T.BOOL, False, 'the rendering cameras are a little off the '
          'calibration the nodes are given (and camera_info carries)'),
    Param('calibration.position_sigma', T.DOUBLE, 0.005, 'error of each optical centre (and '
          'of the onboard mount) per axis, m', 0.0, 1.0),
    Param('calibration.angle_sigma', T.DOUBLE, 0.001, 'error of each camera orientation (and '
          'of the onboard mount) about each axis, rad', 0.0, 0.5),
    Param('calibration.focal_sigma', T.DOUBLE, 0.002, 'relative error of the focal lengths',
          0.0, 0.5),
    Param('calibration.principal_sigma', T.DOUBLE, 0.5, 'error of the principal points per '
          'axis, px', 0.0, 100.0),
    Param('motion_blur.enabled', T.BOOL, False, 'blur along the image-plane motion during the '
          'exposure'),
    Param('motion_blur.exposure', T.DOUBLE, 0.01, 'exposure time, s', 1e-5, 1.0),
    Param('exposure.enabled', T.BOOL, False, 'auto-exposure gain and offset drifting slowly'),
    Param('exposure.gain_sigma', T.DOUBLE, 0.1, 'standard deviation of the gain around 1',
          0.0, 1.0),
    Param('exposure.offset_sigma', T.DOUBLE, 5.0, 'standard deviation of the offset, grey levels',
          0.0, 100.0),
    Param('exposure.time_constant', T.DOUBLE, 5.0, 'time constant of the drift, s', 0.01, 1e4),
    Param('jpeg.enabled', T.BOOL, False, 'JPEG artefacts in image_raw (a compressed camera link)'),
    Param('jpeg.quality', T.INTEGER, 50, 'JPEG quality of the artefacts', 1, 100),
    Param('drops.enabled', T.BOOL, False, 'frames lost at random, each camera on its own'),
    Param('drops.probability', T.DOUBLE, 0.05, 'probability that a frame is lost', 0.0, 1.0),
    Param('latency.enabled', T.BOOL, False, 'publish each frame late: its stamp (the capture) is '
          'earlier than its publication by latency.mean +- latency.jitter'),
    Param('latency.mean', T.DOUBLE, 0.03, 'capture-to-publication delay, s', 0.0, 1.0),
    Param('latency.jitter', T.DOUBLE, 0.005, 'uniform jitter of the delay, s (at most '
          'latency.mean)', 0.0, 1.0),
    Param('unsynchronised.enabled', T.BOOL, False, 'the ground cameras are not triggered '
          'together: each after the first captures (and stamps its frame) a little later'),
    Param('unsynchronised.lag', T.DOUBLE, 0.005, "largest fixed lag of a camera's capture "
          'behind the first, s (each drawn once in [0, lag])', 0.0, 0.1),
    Param('unsynchronised.jitter', T.DOUBLE, 0.001, 'per-frame jitter added to each lag, s '
          '(uniform in [0, jitter])', 0.0, 0.1),
    Param('occlusion.enabled', T.BOOL, False, 'landmarks partly hidden at random by a dark '
          'object between them and a ground camera'),
    Param('occlusion.probability', T.DOUBLE, 0.05, 'probability per landmark, camera and frame',
          0.0, 1.0),
    Param('occlusion.fraction', T.DOUBLE, 0.3, "fraction of the landmark's disc hidden", 0.0, 1.0),
    # The target to follow (section 5), seen by the onboard camera only.
    Param('ground_target.enabled', T.BOOL, False, 'a picture moving on the ground under the '
          'onboard camera, its truth on truth/target'),
    Param('ground_target.template', T.STRING, 'uav_vs/sim/assets/box.png',
          'the picture (found like target_tracker_node\'s target.template)'),
    Param('ground_target.width', T.DOUBLE, 0.4, "the picture's width on the ground, m", 0.01,
          100.0),
    Param('ground_target.center', T.DOUBLE_ARRAY, [0.0, 0.0],
          'centre of its circular path, x y in world, m', size=2),
    Param('ground_target.radius', T.DOUBLE, 0.4, 'radius of the path, m', 0.0, 1000.0),
    Param('ground_target.speed', T.DOUBLE, 0.08, 'speed along the path (counter-clockwise), '
          'm/s', 0.0, 20.0),
    Param('ground_target.phase', T.DOUBLE, 0.0, 'where on the path it is when the world '
          'starts, rad (0: east of the centre)', -2 * math.pi, 2 * math.pi),
]


def declare_fleet(node: Node) -> dict[str, dict]:
    """Declare `fleet.*`, the other vehicles the ground cameras see; per name, its
    parameters without the `fleet.<name>.` prefix."""
    names = declare(node, [Param('fleet.names', T.STRING_ARRAY, [], (
        "other vehicles in the ground cameras' view, each with its fleet.<name>.*"))])
    fleet = {}
    for name in names['fleet.names']:
        key = f'fleet.{name}.'
        values = declare(node, [
            Param(key + 'truth_connection', T.STRING, description=(
                'where its true state is read as SIM_STATE (its sim_world\'s '
                'vehicle.truth_connection, or a SITL port): tcp:HOST:PORT or udpin:HOST:PORT')),
            Param(key + 'system_id', T.INTEGER, 1, 'its MAVLink system id', 1, 255),
            Param(key + 'start', T.DOUBLE_ARRAY, [0.0, 0.0],
                  'where its home is in world: x y, m', size=2),
            Param(key + 'landmarks', T.STRING, description=(
                'a params file with its landmarks.* (config/landmarks_uav2.yaml)'))])
        fleet[name] = {k[len(key):]: v for k, v in values.items()}
    return fleet


def fleet_landmarks(cameras: dict, params_file: str, key: str) -> GroundConfig:
    """The cameras' flat parameters with the landmarks of `params_file` (its
    `landmarks.*`); `key` names the parameter that gave the file."""
    try:
        landmarks = {k: v for k, v in read_params_file(params_file).items()
                     if k.startswith('landmarks.')}
        return load_ground_config({**cameras, **landmarks})
    except (OSError, yaml.YAMLError, CalibrationError) as err:
        raise ValueError(f'{key}: {params_file}: {err}') from None


def effects_config(p: dict, noise_sigma: float) -> EffectsConfig:
    """The image effects the parameters switch on, for a camera of `noise_sigma`."""
    return EffectsConfig(
        noise_sigma=noise_sigma if p['noise.enabled'] else 0.0,
        jpeg_quality=p['jpeg.quality'] if p['jpeg.enabled'] else 0,
        exposure_time=p['motion_blur.exposure'] if p['motion_blur.enabled'] else 0.0,
        gain_sigma=p['exposure.gain_sigma'] if p['exposure.enabled'] else 0.0,
        offset_sigma=p['exposure.offset_sigma'] if p['exposure.enabled'] else 0.0,
        drift_time_constant=p['exposure.time_constant'],
        drop_probability=p['drops.probability'] if p['drops.enabled'] else 0.0)


def true_rig(ground: GroundConfig, onboard: OnboardConfig, p: dict
             ) -> tuple[GroundConfig, OnboardConfig]:
    """The cameras as they really are, off the calibration by the calibration.* spread
    (uav_vs.sim.calibration_error), drawn from world.seed."""
    spread = CalibrationSpread(p['calibration.position_sigma'], p['calibration.angle_sigma'],
                               p['calibration.focal_sigma'], p['calibration.principal_sigma'])
    rng = np.random.default_rng([p['world.seed'], 1])
    cameras = [true_camera(c, spread, rng) for c in ground.cameras]
    intrinsics_only = replace(spread, position_sigma=0.0, angle_sigma=0.0)
    return (replace(ground, cameras=cameras),
            replace(onboard,   # its pose error is the mount's: R, t of its Camera are unused
                    camera=true_camera(onboard.camera, intrinsics_only, rng),
                    camera_to_body=true_mount(onboard.camera_to_body, spread, rng)))


def ideal_lens(camera: Camera) -> Camera:
    """The camera without its lens distortion."""
    return replace(camera, D=np.zeros(0))


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
        cameras = declare_cameras(self)
        ground = load_ground_config({**cameras, **declare_landmarks(self)})
        onboard = load_onboard_config(declare(self, [s for s in ONBOARD_PARAMS
                                                     if s.name.startswith('camera')]))
        p = declare(self, PARAMS)
        fleet = declare_fleet(self)
        others = [fleet_landmarks(cameras, f['landmarks'], f'fleet.{name}.landmarks')
                  for name, f in fleet.items()]
        self.frame_id = p['world.frame_id']
        if not p['distortion.enabled']:
            ground = replace(ground, cameras=[ideal_lens(c) for c in ground.cameras])
            onboard = replace(onboard, camera=ideal_lens(onboard.camera))
        nominal_ground, nominal_onboard = ground, onboard    # what the nodes are given
        if p['calibration.enabled']:
            ground, onboard = true_rig(ground, onboard, p)
        try:
            ground_scene = GroundScene(ground, background=p['ground.background'],
                                       noise_sigma=0.0, seed=p['world.seed'],
                                       others=others)
        except FileNotFoundError as err:
            raise ValueError(f'ground.background: {err}') from None
        onboard_scene = OnboardScene(onboard.camera, onboard.camera_to_body, noise_sigma=0.0)
        n = len(ground.cameras)
        seeds = np.random.SeedSequence(p['world.seed']).spawn(n + 5)
        self.ground_effects = [
            CameraEffects(effects_config(p, p['ground.noise_sigma']), (c.height, c.width), s)
            for c, s in zip(ground.cameras, seeds)]
        self.onboard_effects = CameraEffects(effects_config(p, p['onboard.noise_sigma']),
                                             (onboard.camera.height, onboard.camera.width),
                                             seeds[n])
        self.lags = None
        if p['unsynchronised.enabled']:
            self.lags = CameraLags(n, p['unsynchronised.lag'], p['unsynchronised.jitter'],
                                   np.random.default_rng(seeds[n + 3]))
        self.occlusion = None
        if p['occlusion.enabled']:
            self.occlusion = Occlusion(p['occlusion.probability'], p['occlusion.fraction'],
                                       np.random.default_rng(seeds[n + 4]))
        if p['latency.jitter'] > p['latency.mean']:
            raise ValueError(f"latency.jitter: {p['latency.jitter']:g} s is more than "
                             f"latency.mean {p['latency.mean']:g} s")
        self.latency = self.delay_line = None
        if p['latency.enabled']:
            self.delay_line = DelayLine('sim_world latency')
            self.latency = {which: Latency(p['latency.mean'], p['latency.jitter'],
                                           np.random.default_rng(s))
                            for which, s in zip(('ground', 'onboard'), seeds[n + 1:n + 3])}
        self.dt = {'ground': 1.0 / p['ground.rate'] if p['ground.rate'] > 0 else 0.0,
                   'onboard': 1.0 / p['onboard.rate'] if p['onboard.rate'] > 0 else 0.0}
        vehicle, where = self._vehicle(p)
        flying = [self._truth(f'fleet.{name}.truth_connection', f['truth_connection'],
                              f['system_id'], f['start']) for name, f in fleet.items()]
        self.world = SimWorld(vehicle, ground_scene, onboard_scene, p['onboard.min_height'],
                              self._target(p), others=flying)

        quality = p['world.jpeg_quality']
        self.cameras = [CameraOutput(self, cam.name, cam, quality)
                        for cam in nominal_ground.cameras]
        self.onboard_camera = CameraOutput(self, 'onboard', nominal_onboard.camera, quality)
        self.truth_pub = self.create_publisher(PoseStamped, 'truth/pose', 50)
        self.fleet_truth_pubs = [self.create_publisher(PoseStamped, f'{name}/truth/pose', 50)
                                 for name in fleet]
        self.target_truth_pub = self.create_publisher(PoseStamped, 'truth/target', 50)
        self.counts = dict(ground_frames=0, onboard_frames=0, onboard_too_low=0,
                           dropped_frames=0, occluded_landmarks=0, blind_frames=0)
        self.ground_enabled = True
        self.render_ms = dict(ground_render_ms=float('nan'), onboard_render_ms=float('nan'))
        if p['ground.rate'] > 0:
            self.create_timer(1.0 / p['ground.rate'], self.on_ground)
            self.create_service(SetBool, 'ground_cameras/enable', self.on_enable_ground)
        if p['onboard.rate'] > 0:
            self.create_timer(1.0 / p['onboard.rate'], self.on_onboard)
        self.diag = Diagnostics(self, hardware_id=where)
        self.create_timer(p['world.diagnostics_period'], self.publish_diagnostics)
        self.get_logger().info(f'vehicle: {where}; {len(self.cameras)} ground cameras at '
                               f'{p["ground.rate"]:g} Hz, onboard camera at '
                               f'{p["onboard.rate"]:g} Hz')

    @staticmethod
    def _target(p: dict) -> GroundTarget | None:
        """The moving ground target of the `ground_target.*` parameters, if enabled."""
        if not p['ground_target.enabled']:
            return None
        template, _ = read_image('ground_target.template', p['ground_target.template'],
                                 cv2.IMREAD_COLOR)
        return GroundTarget(template, p['ground_target.width'], CirclePath(
            tuple(p['ground_target.center']), p['ground_target.radius'],
            p['ground_target.speed'], p['ground_target.phase']))

    @staticmethod
    def _vehicle(p: dict) -> tuple[Vehicle, str]:
        """The world's vehicle, started, and where it is."""
        if p['vehicle.model'] == 'sitl':
            url = p['vehicle.sitl_connection']
            truth = SimWorldNode._truth('vehicle.sitl_connection', url, p['vehicle.system_id'],
                                        p['vehicle.start'])
            return truth, f'ArduPilot SITL, truth from SIM_STATE on {url}'
        try:
            vehicle = MavlinkVehicle(VehicleConfig(
                connection=p['vehicle.connection'], system_id=p['vehicle.system_id'],
                rate=p['vehicle.rate'], ready_delay=p['vehicle.ready_delay'],
                autopilot=p['vehicle.autopilot'],
                gust_sigma=p['wind.gust_sigma'] if p['wind.enabled'] else 0.0,
                gust_time_constant=p['wind.time_constant'],
                drift_rate=p['drift.rate'] if p['drift.enabled'] else 0.0,
                seed=p['world.seed'], truth_connection=p['vehicle.truth_connection'] or None))
        except OSError as err:
            names = ('vehicle.connection', 'vehicle.truth_connection')
            raise ValueError(f"{' or '.join(n for n in names if p[n])}: cannot serve "
                             f'{err.strerror or err}') from None
        host, port = vehicle.address
        return (SimulatedVehicle(vehicle.start(), p['vehicle.start']),
                f'simulated {p["vehicle.autopilot"]} on {p["vehicle.connection"]} ({host}:{port})')

    @staticmethod
    def _truth(key: str, url: str, system_id: int, start: list[float]) -> SitlTruth:
        """A vehicle's SIM_STATE truth read from `url` (the parameter `key`), once it came."""
        try:
            return SitlTruth(url, target_system=system_id, start=start).start().wait(SITL_WAIT_S)
        except (OSError, TimeoutError) as err:
            raise ValueError(f'{key}: {url}: {getattr(err, "strerror", None) or err}') from None

    def _sample(self) -> tuple[VehicleState, Header]:
        """The vehicle's truth now, published on truth/pose, and the stamp of that instant."""
        state = self.world.state()
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=self.frame_id)
        self.truth_pub.publish(pose_to_msg(state.position, state.quaternion, header))
        return state, header

    def _capture(self, effects: CameraEffects, image: np.ndarray, velocity: np.ndarray,
                 which: str) -> np.ndarray | None:
        """The frame the camera delivers of an exact render; None (counted) if dropped."""
        frame = effects(image, velocity, self.dt[which])
        if frame is None:
            self.counts['dropped_frames'] += 1
        return frame

    def _occlude(self, image: np.ndarray, discs: np.ndarray) -> np.ndarray:
        image, count = self.occlusion(image, discs)
        self.counts['occluded_landmarks'] += count
        return image

    def _deliver(self, which: str, header: Header, publish: Callable[[], None]) -> None:
        """Publish now, or with latency on, once the frame's delay after its stamp is over."""
        if self.latency is None:
            publish()
            return
        capture = stamp_to_ns(header.stamp) * 1e-9
        wait = capture + self.latency[which].offset(capture) - \
            self.get_clock().now().nanoseconds * 1e-9
        self.delay_line.put(time.monotonic() + wait, publish)

    def on_enable_ground(self, request: SetBool.Request, response: SetBool.Response
                         ) -> SetBool.Response:
        self.ground_enabled = request.data
        response.success, response.message = True, ('ground cameras uncovered' if request.data
                                                    else 'ground cameras covered')
        self.get_logger().info(response.message)
        return response

    def on_ground(self) -> None:
        state, header = self._sample()
        others = self.world.other_states()
        for pub, other in zip(self.fleet_truth_pubs, others):
            pub.publish(pose_to_msg(other.position, other.quaternion, header))
        if not self.ground_enabled:
            self.counts['blind_frames'] += 1
            return
        start = time.perf_counter()
        lags = None if self.lags is None else self.lags.sample()
        images = self.world.ground_images(state, lags, others)
        if self.occlusion is not None:
            images = [self._occlude(image, discs) for image, discs in
                      zip(images, self.world.ground_landmark_discs(state, lags, others))]
        velocities = self.world.ground_image_velocities(state)
        frames = [self._capture(fx, image, v, 'ground')
                  for fx, image, v in zip(self.ground_effects, images, velocities)]
        self.render_ms['ground_render_ms'] = round((time.perf_counter() - start) * 1e3, 2)
        stamps = [header.stamp] * len(frames) if lags is None else \
            [ns_to_stamp(stamp_to_ns(header.stamp) + int(round(dt * 1e9))) for dt in lags]

        def publish() -> None:
            for camera, frame, stamp in zip(self.cameras, frames, stamps):
                if frame is not None:
                    camera.publish(frame, stamp)
        self._deliver('ground', header, publish)
        self.counts['ground_frames'] += 1

    def on_onboard(self) -> None:
        state, header = self._sample()
        start = time.perf_counter()
        image = self.world.onboard_image(state)
        if image is None:
            self.counts['onboard_too_low'] += 1
            return
        frame = self._capture(self.onboard_effects, image,
                              self.world.onboard_image_velocity(state), 'onboard')
        self.render_ms['onboard_render_ms'] = round((time.perf_counter() - start) * 1e3, 2)
        target = self.world.target_pose(state)
        if target is not None:
            (x, y), heading = target
            self.target_truth_pub.publish(pose_to_msg(np.array([x, y, 0.0]),
                                                      euler_to_quat(0, 0, heading), header))
        if frame is not None:
            self._deliver('onboard', header,
                          lambda: self.onboard_camera.publish(frame, header.stamp))
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
        if self.delay_line is not None:
            self.delay_line.close()
        self.world.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    run(SimWorldNode, 'sim_world', args)


if __name__ == '__main__':
    main()
