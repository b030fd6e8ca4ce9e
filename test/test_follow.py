"""Following a moving target (section 5): the simulated target, its place on the ground
from the onboard camera, and the follower's setpoints, against analytic geometry."""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uav_vs.control.follow import FollowConfig, TargetFollower, interpolate, with_yaw_of
from uav_vs.sim.ground_scene import rot_z
from uav_vs.sim.ground_target import CirclePath, GroundTarget
from uav_vs.sim.onboard_scene import ASSETS, OnboardScene
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.ground_target import ground_points, target_on_ground
from uav_vs.vision.onboard_config import load_onboard_config
from uav_vs.vision.plane_pose import camera_pose
from uav_vs.vision.target_tracking import PlanarTargetTracker

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'onboard.yaml'
NORTH = math.pi / 2


@pytest.fixture(scope='module')
def cfg():
    return load_onboard_config(read_params_file(CONFIG))


@pytest.fixture(scope='module')
def box():
    return cv2.imread(str(ASSETS / 'box.png'))


def project(cfg, R_wb, p_wb, ground_xy: np.ndarray) -> np.ndarray:
    """Raw pixels of ground points (z = 0) seen from the vehicle (OpenCV's projection)."""
    R, t = camera_pose(R_wb, p_wb, cfg.camera_to_body)
    points = np.column_stack([ground_xy, np.zeros(len(ground_xy))])
    px, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, cfg.camera.K, cfg.camera.D)
    return px.reshape(-1, 2)


def tilted(yaw: float, roll: float, pitch: float) -> np.ndarray:
    """World-from-body rotation: yaw about z, then pitch about y, roll about x."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    R_x = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    R_y = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return rot_z(yaw) @ R_y @ R_x


def test_the_target_drives_round_its_circle_facing_the_way_it_goes():
    path = CirclePath((1.0, -2.0), 0.5, 0.1, phase=0.3)
    for t in (0.0, 3.7, 40.0):
        (x, y), heading = path.pose(t)
        assert math.hypot(x - 1.0, y + 2.0) == pytest.approx(0.5)
        h = 1e-4
        ahead, _ = path.pose(t + h)
        step = (ahead - [x, y]) / h
        assert np.linalg.norm(step) == pytest.approx(0.1, rel=1e-3)
        assert math.atan2(step[1], step[0]) == pytest.approx(
            math.remainder(heading, 2 * math.pi), abs=1e-3)
        assert np.allclose(path.velocity(t), step, atol=1e-5)
    assert np.allclose(path.pose(0.0)[0], [1.0 + 0.5 * math.cos(0.3), -2.0 + 0.5 * math.sin(0.3)])


def test_the_template_lies_on_the_ground_at_the_targets_pose(box):
    target = GroundTarget(box, 0.4, CirclePath((0.0, 0.0), 0.4, 0.08))
    h, w = box.shape[:2]
    for t in (0.0, 5.0, 12.5):
        (x, y), heading = target.path.pose(t)
        H = target.plane_from_template(t)
        mapped = cv2.perspectiveTransform(np.float64([[[w / 2, h / 2], [w / 2, 0], [0, h / 2]]]),
                                          H)[0]
        assert np.allclose(mapped[0], [x, y])
        forward = np.array([math.cos(heading), math.sin(heading)])
        left = np.array([-forward[1], forward[0]])
        assert np.allclose(mapped[1], [x, y] + target.length / 2 * forward)   # top edge: front
        assert np.allclose(mapped[2], [x, y] + 0.2 * left)                      # left edge
    assert target.length == pytest.approx(0.4 * h / w)
    with pytest.raises(ValueError, match='width'):
        GroundTarget(box, 0.0, CirclePath())


def test_a_pixels_ray_meets_the_ground_where_it_was_projected_from(cfg):
    rng = np.random.default_rng(3)
    for _ in range(5):
        R_wb = tilted(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.2, 0.2, 2))
        p_wb = np.array([*rng.uniform(-2, 2, 2), rng.uniform(0.8, 4.0)])
        ground = p_wb[:2] + rng.uniform(-0.4, 0.4, (20, 2))
        found = ground_points(cfg.camera, cfg.camera_to_body, R_wb, p_wb,
                              project(cfg, R_wb, p_wb, ground))
        assert np.abs(found - ground).max() < 1e-6
    # Upside down, the camera looks at the sky: no ground point.
    upside_down = ground_points(cfg.camera, cfg.camera_to_body, tilted(0.0, math.pi, 0.0),
                                np.array([0.0, 0.0, 1.5]), np.array([[319.5, 239.5]]))
    assert np.isnan(upside_down).all()


def test_the_rendered_target_is_found_and_placed_on_the_ground(cfg, box):
    """Through the renderer (lens distortion, sensor noise), the tracker and the rays:
    within 1 cm and 1.5 degrees of the target's true pose, from poses above and beside it
    at the heights the follow scenario flies (ORB finds this 0.4 m target up to ~1.8 m).
    The homography is Algorithm 1 with its robust refinement ('ransac'), whose heading
    does not hinge on the draws: over 40 runs of these three views its largest error was
    0.83 degrees, cv2 RANSAC's (which draws anew on every call) 1.74 (p95 1.33)."""
    scene = OnboardScene(cfg.camera, cfg.camera_to_body)
    target = GroundTarget(box, 0.4, CirclePath((0.0, 0.0), 0.4, 0.08))
    tracker = PlanarTargetTracker(cv2.cvtColor(box, cv2.COLOR_BGR2GRAY), 'orb',
                                  method='ransac', max_features=2000)
    for t, offset, yaw, height in ((0.0, (0.0, 0.0), NORTH, 1.5), (9.0, (0.3, -0.2), 0.4, 1.2),
                                   (21.0, (-0.2, 0.3), -2.0, 1.6)):
        (x, y), heading = target.path.pose(t)
        R_wb, p_wb = tilted(yaw, 0.03, -0.05), np.array([x + offset[0], y + offset[1], height])
        image = scene.render(R_wb, p_wb, decals=((box, target.plane_from_template(t)),))
        found = tracker.find(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        assert found.ok, found.reason
        placed = target_on_ground(cfg.camera, cfg.camera_to_body, R_wb, p_wb,
                                  np.vstack([found.corners, found.center]))
        assert np.linalg.norm(placed.position - [x, y]) < 0.01
        assert abs(math.degrees(math.remainder(placed.heading - heading, 2 * math.pi))) < 1.5
        assert placed.size == pytest.approx((0.4 + target.length) / 2, rel=0.03)


def test_without_decals_the_rendering_is_unchanged(cfg, box):
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, noise_sigma=0.0)
    R_wb, p_wb = rot_z(NORTH), np.array([3.0, 3.0, 1.5])
    far = GroundTarget(box, 0.4, CirclePath((-3.0, -3.0), 0.0, 0.0))   # out of view
    assert np.array_equal(scene.render(R_wb, p_wb),
                          scene.render(R_wb, p_wb, decals=((box, far.plane_from_template(0)),)))


def polygon(cfg, target: GroundTarget, t: float, R_wb, p_wb) -> np.ndarray:
    """The tracker's polygon of the target (corners TL TR BR BL, centre) by projection."""
    h, w = target.template.shape[:2]
    template = np.float64([[[0, 0], [w, 0], [w, h], [0, h], [w / 2, h / 2]]])
    ground = cv2.perspectiveTransform(template, target.plane_from_template(t))[0]
    return project(cfg, R_wb, p_wb, ground)


def test_the_follower_leads_a_moving_target_by_its_velocity(cfg, box):
    path = CirclePath((0.0, 0.0), 5.0, 0.3)            # nearly straight at this scale
    target = GroundTarget(box, 0.4, path)
    config = FollowConfig(height=1.8, yaw=0.7, lead=0.5)
    follower = TargetFollower(cfg.camera, cfg.camera_to_body, config)
    R_wb = rot_z(0.2)
    for k in range(100):
        t = k / 10
        (x, y), _ = path.pose(t)
        p_wb = np.array([x - 0.2, y + 0.1, 1.5])
        follower.on_pose(t + 0.03, R_wb, p_wb)             # ground/pose of another camera
        step, = follower.on_target(t, polygon(cfg, target, t, R_wb, p_wb))
        assert step.reason == '' and step.stamp == t
    assert np.linalg.norm(step.velocity - path.velocity(t)) < 0.01
    (x, y), heading = path.pose(t)
    assert np.allclose(step.setpoint[:2], np.add([x, y], 0.5 * path.velocity(t)), atol=0.01)
    assert step.setpoint[2:] == (1.8, 0.7)
    assert abs(math.remainder(step.target.heading - heading, 2 * math.pi)) < 1e-3


def test_the_follower_says_why_it_has_no_setpoint(cfg, box):
    target = GroundTarget(box, 0.4, CirclePath((0.0, 0.0), 0.0, 0.0))
    follower = TargetFollower(cfg.camera, cfg.camera_to_body,
                              FollowConfig(max_pose_gap=0.1, max_wait=0.5))
    p_wb = np.array([0.1, 0.0, 1.5])
    seen = polygon(cfg, target, 0.0, rot_z(NORTH), p_wb)
    assert follower.on_target(1.0, seen) == []         # waits for a pose at its stamp
    assert follower.waiting_for() == "waiting for the vehicle pose at the image's stamp"
    assert follower.on_target(1.4, seen) == []
    steps = follower.on_target(1.5, seen)              # 0.5 s newer: the first waited enough
    assert [(s.stamp, s.reason) for s in steps] == [(1.0, 'vehicle pose: none yet')]
    steps = follower.on_pose(1.55, rot_z(NORTH), p_wb)  # after the others: placed on it
    assert [(s.stamp, s.reason) for s in steps] == [
        (1.4, 'vehicle pose: none within 0.1 s of the image'), (1.5, '')]
    assert follower.waiting_for() == ''
    assert np.allclose(steps[1].setpoint[:2], [0.0, 0.0], atol=1e-6)
    follower.on_pose(2.0, tilted(NORTH, math.pi, 0.0), p_wb)       # upside down
    step, = follower.on_target(2.0, seen)
    assert step.reason == 'target rays miss the ground'


def test_an_image_waits_for_its_pose_which_is_interpolated(cfg, box):
    """Poses arriving after the image, 0.3 s apart either side of it (a slow ground
    station): the image waits for the second, and the target, seen from the pose
    interpolated to its stamp, is placed exactly; the nearest pose alone is too far."""
    target = GroundTarget(box, 0.4, CirclePath((0.2, 0.1), 0.0, 0.0))
    R0, p0 = rot_z(1.0), np.array([0.0, 0.0, 1.5])
    R1, p1 = tilted(1.2, 0.1, -0.05), np.array([0.3, -0.2, 1.6])
    stamp, f = 0.12, 0.4                                # 0.4 of the way from 0.0 to 0.3 s
    R_at, p_at = interpolate((0.0, R0, p0), (0.3, R1, p1), stamp)
    assert np.allclose(p_at, p0 + f * (p1 - p0))
    turn = Rotation.from_matrix(R0.T @ R1).as_rotvec()
    assert np.allclose(Rotation.from_matrix(R0.T @ R_at).as_rotvec(), f * turn)
    seen = polygon(cfg, target, 0.0, R_at, p_at)
    follower = TargetFollower(cfg.camera, cfg.camera_to_body, FollowConfig(lead=0.0))
    assert follower.on_target(stamp, seen) == []
    assert follower.on_pose(0.0, R0, p0) == []         # only before the image: it waits
    step, = follower.on_pose(0.3, R1, p1)
    assert np.allclose(step.target.position, [0.2, 0.1], atol=1e-6)
    nearest = TargetFollower(cfg.camera, cfg.camera_to_body,
                             FollowConfig(lead=0.0, max_pose_interval=0.1))
    nearest.on_pose(0.0, R0, p0)
    nearest.on_pose(0.3, R1, p1)
    step, = nearest.on_target(stamp, seen)             # 0.12 s from the nearest pose
    assert step.reason == 'vehicle pose: none within 0.1 s of the image'


def test_the_autopilots_tilt_places_the_target_a_level_pose_cannot(cfg, box):
    """Tilted by 10 degrees, the vehicle's level vision pose misplaces a target by about
    h tan(10 deg); with the autopilot's attitude (its yaw off by 0.4 rad, not used) it is
    placed to a micrometre."""
    target = GroundTarget(box, 0.4, CirclePath((0.3, 0.2), 0.0, 0.0))
    R_true, p_wb = tilted(1.0, math.radians(6), math.radians(8)), np.array([0.0, 0.0, 1.5])
    seen = polygon(cfg, target, 0.0, R_true, p_wb)
    errors = {}
    for source in (False, True):
        follower = TargetFollower(cfg.camera, cfg.camera_to_body, FollowConfig(lead=0.0),
                                  attitude_source=source)
        follower.on_pose(0.0, rot_z(1.0), p_wb)
        follower.on_attitude(0.0, tilted(1.4, math.radians(6), math.radians(8)))
        step, = follower.on_target(0.0, seen)
        errors[source] = np.linalg.norm(step.target.position - [0.3, 0.2])
    assert errors[True] < 1e-6
    assert errors[False] > 1.5 * math.tan(math.radians(9))
    assert np.allclose(with_yaw_of(rot_z(1.0), tilted(1.4, 0.1, 0.2)), tilted(1.0, 0.1, 0.2))
    follower = TargetFollower(cfg.camera, cfg.camera_to_body, attitude_source=True)
    follower.on_pose(0.0, rot_z(1.0), p_wb)
    assert follower.on_target(0.0, seen) == []
    assert follower.waiting_for() == "waiting for the attitude at the image's stamp"
    step, = follower.on_target(0.5, seen)
    assert step.reason == 'attitude: none yet'


@pytest.mark.parametrize('field, value', [('height', 0.0), ('lead', -1.0),
                                          ('velocity_gain', 0.0), ('max_pose_gap', -0.1),
                                          ('max_pose_interval', 0.0), ('max_wait', -1.0)])
def test_a_follow_configuration_out_of_range_is_refused(field, value):
    with pytest.raises(ValueError, match=field):
        FollowConfig(**{field: value})


# ------------------------------------------------- the shipped bag of a followed target

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'onboard_follow'


def test_the_follow_bag_holds_the_target_of_the_world():
    """bags/onboard_follow: every frame with truth/pose and truth/target of its stamp, the
    target on the follow scenario's circle (sim_world's ground_target defaults)."""
    from rclpy.serialization import deserialize_message
    from geometry_msgs.msg import PoseStamped

    from uav_vs.bag.reader import read_messages
    from uav_vs.ros.convert import msg_to_pose, stamp_to_ns, yaw_of
    from uav_vs.sim.onboard_bag import START_NS, follow_target

    by_topic: dict[str, list] = {}
    for m in read_messages(BAG):
        by_topic.setdefault(m.topic, []).append(m)
    assert {t: len(v) for t, v in by_topic.items()} == {
        'onboard/image_raw/compressed': 101, 'onboard/camera_info': 101, 'truth/pose': 101,
        'truth/target': 101}
    path = follow_target().path
    for m in by_topic['truth/target']:
        msg = deserialize_message(m.raw, PoseStamped)
        t = (stamp_to_ns(msg.header.stamp) - START_NS) * 1e-9
        position, q = msg_to_pose(msg)
        (x, y), heading = path.pose(t)
        assert np.allclose(position, [x, y, 0.0], atol=1e-9) and m.t_ns == stamp_to_ns(
            msg.header.stamp)
        assert yaw_of(q) == pytest.approx(math.remainder(heading, 2 * math.pi), abs=1e-9)


def test_the_follow_bag_replayed_through_the_tracker_and_follower_places_the_target(tmp_path):
    """The shipped bag through target_tracker_node (ORB, as the follow scenario runs it)
    and target_follower_node placing the target from the bag's truth/pose: target/pose
    within 1 cm RMS of truth/target on nearly every frame."""
    from uav_vs import graph
    from uav_vs.flight.pose_replay import pose_errors, replay_bag

    def start() -> list:
        return [graph.start('target_tracker_node', [
                    '--params-file', str(CONFIG), '-p', 'target.features:=orb',
                    '-p', 'target.max_features:=2000', '-p', 'target.image_qos:=reliable'],
                    tmp_path, 'target_tracker_node'),
                graph.start('target_follower_node', [
                    '--params-file', str(CONFIG), '-p', 'follow.pose_topic:=truth/pose',
                    '-p', "follow.attitude_topic:=''"], tmp_path, 'target_follower_node')]

    replay = replay_bag(BAG, start, 'target/pose', rate=1.0, truth_topic='truth/target')
    errors = pose_errors(replay.poses, replay.truth)
    assert not any(replay.return_codes), replay.return_codes
    assert len(errors.stamps) >= 0.9 * len(replay.truth), (len(errors.stamps), len(replay.truth))
    assert np.sqrt(np.mean(errors.position_m ** 2)) < 0.01, errors.position_m
    assert np.sqrt(np.mean(errors.yaw_deg ** 2)) < 2.0, errors.yaw_deg
