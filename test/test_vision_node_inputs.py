"""Vision nodes, as processes, survive every malformed image and every clock glitch.

Each node is fed the malformed images of test_image_input, a valid frame stamped in
2037 and then valid frames; it must stay up, count what it dropped, and give the right
answer for the valid frames (truth: the simulator's landmark centroids, the configured
first pose, a target pasted through a known homography, poses projected through the
calibration).
"""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PolygonStamped, PoseStamped, PoseWithCovarianceStamped
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Bool, Header

from conftest import wait_for
from test_ground_nodes import CONFIG as GROUND_CONFIG
from test_ground_nodes import _collect_diagnostics, _last_diagnostics, _project_layout
from test_image_input import MALFORMED
from test_onboard_nodes import (ASSETS, POSE_NODE_ARGS, RELIABLE, Probe, header, level_pose,
                                pasted_box)
from test_onboard_nodes import CONFIG as ONBOARD_CONFIG
from uav_vs.ros.convert import (bgr_to_compressed, bgr_to_image, msg_to_pose, ns_to_stamp,
                                points_to_polygon, polygon_to_array, stamp_to_ns)
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.vision.body_pose import solve_pose
from uav_vs.vision.ground_config import load_ground_config, read_params_file
from uav_vs.vision.pose_covariance import landmark_covariances, pose_covariance
from uav_vs.vision.triangulation import triangulate
from uav_vs.vision.onboard_config import load_onboard_config

S = 1_000_000_000
FUTURE = Header(stamp=ns_to_stamp(2_145_000_000 * S))       # year 2037


@pytest.fixture(scope='module')
def onboard():
    return load_onboard_config(read_params_file(ONBOARD_CONFIG))


def publish_malformed(raw_pub, compressed_pub, stamp_ns: int) -> None:
    for k, msg in enumerate(MALFORMED.values()):
        msg.header = Header(stamp=ns_to_stamp(stamp_ns + k))
        (compressed_pub if isinstance(msg, CompressedImage) else raw_pub).publish(msg)


def test_camshift_node_survives_bad_images_a_future_stamp_and_a_replay(ros_node, processes):
    from uav_vs.sim.ground_scene import GroundScene, figure_eight
    scene = GroundScene(load_ground_config(read_params_file(GROUND_CONFIG)), seed=1)
    proc = processes('camshift_node', ['--params-file', str(GROUND_CONFIG), '-r', '__ns:=/cam1',
                                       '-p', 'camera:=cam1', '-p', 'camshift.image_qos:=reliable',
                                       '-p', 'camshift.diagnostics_period:=0.2'], label='cam1')
    diags: dict = {}
    _collect_diagnostics(ros_node, diags)
    out: list[PolygonStamped] = []
    ros_node.create_subscription(PolygonStamped, '/cam1/landmarks', out.append, RELIABLE)
    raw = ros_node.create_publisher(Image, '/cam1/image_raw', RELIABLE)
    comp = ros_node.create_publisher(CompressedImage, '/cam1/image_raw/compressed', RELIABLE)
    assert wait_for(lambda: raw.get_subscription_count() and comp.get_subscription_count(), 30)
    name = '/cam1/camshift_node'
    publish_malformed(raw, comp, 10 * S)
    images, info = scene.render(figure_eight(3.0))
    raw.publish(bgr_to_image(images[0], FUTURE))
    assert wait_for(lambda: _last_diagnostics(diags, name).get('future') == '1', 15), diags
    assert diags[name].level == DiagnosticStatus.WARN and 'future' in diags[name].message
    stamps = [20 * S, 21 * S, 5 * S]                # the last one: the replay again
    for stamp in stamps:
        raw.publish(bgr_to_image(images[0], Header(stamp=ns_to_stamp(stamp))))
    assert wait_for(lambda: len(out) == 3, 15), _last_diagnostics(diags, name)
    assert [stamp_to_ns(m.header.stamp) for m in out] == stamps
    seen = info.visible[0] > 0.98
    assert seen.sum() >= 2
    for msg in out:
        got = polygon_to_array(msg)
        assert np.linalg.norm(got[seen, :2] - info.centroid[0, seen], axis=1).max() < 1.5
    assert wait_for(lambda: _last_diagnostics(diags, name).get('restarts') == '1', 10), diags
    assert _last_diagnostics(diags, name)['malformed'] == str(len(MALFORMED))
    assert proc.poll() is None
    assert processes.log('cam1').count('time went back 16.000 s') == 1


def test_pose_node_survives_bad_images_a_future_stamp_and_restarts_on_a_replay(
        ros_node, processes, onboard):
    proc = processes('homography_pose_node', POSE_NODE_ARGS)
    probe = Probe(ros_node)
    assert wait_for(probe.ready, 30)
    scene = OnboardScene(onboard.camera, onboard.camera_to_body, seed=1)
    first = scene.render(*level_pose(0.0, 0.0, 1.0, 0.0))      # the configured first pose
    moved = scene.render(*level_pose(0.03, -0.02, 1.02, 0.02))
    publish_malformed(probe.image, probe.compressed, 1)
    probe.compressed.publish(bgr_to_compressed(first, FUTURE))
    assert wait_for(lambda: probe.value('future') == '1', 15), probe.status
    assert probe.poses == {}
    probe.compressed.publish(bgr_to_compressed(first, header(30)))
    probe.compressed.publish(bgr_to_compressed(moved, header(31)))
    probe.compressed.publish(bgr_to_compressed(first, header(0)))    # a new replay
    stamps = [stamp_to_ns(header(k).stamp) for k in (30, 31, 0)]
    assert wait_for(lambda: len(probe.poses) == 3, 20), probe.status
    for stamp, truth in zip(stamps, [(0.0, 0.0, 1.0), (0.03, -0.02, 1.02), (0.0, 0.0, 1.0)]):
        p, _ = msg_to_pose(probe.poses[stamp])
        assert np.linalg.norm(p - truth) < 0.01, (stamp, p)
    assert wait_for(lambda: probe.value('restarts') == '1', 10), probe.status
    assert probe.value('malformed') == str(len(MALFORMED))
    assert proc.poll() is None
    log = processes.log('homography_pose_node')
    assert log.count('time went back') == 1
    assert log.count('initialised on the frame') == 2     # the replay starts from init.*


def test_target_node_survives_bad_images_and_a_future_stamp(ros_node, processes):
    proc = processes('target_tracker_node', ['--params-file', str(ONBOARD_CONFIG),
                                             '-p', f"target.template:={ASSETS / 'box.png'}",
                                             '-p', 'target.image_qos:=reliable',
                                             '-p', 'target.diagnostics_period:=0.1'])
    probe = Probe(ros_node, '/target_tracker_node')
    targets: list[PolygonStamped] = []
    found: list[bool] = []
    ros_node.create_subscription(PolygonStamped, '/onboard/target', targets.append, RELIABLE)
    ros_node.create_subscription(Bool, '/onboard/target_found', lambda m: found.append(m.data),
                                 RELIABLE)
    assert wait_for(probe.ready, 30)
    scene, _, expected = pasted_box()
    publish_malformed(probe.image, probe.compressed, 1)
    probe.compressed.publish(bgr_to_compressed(scene, FUTURE))
    assert wait_for(lambda: probe.value('future') == '1', 15), probe.status
    assert probe.status.level == DiagnosticStatus.WARN and found == []
    probe.compressed.publish(bgr_to_compressed(scene, header(0)))
    assert wait_for(lambda: found == [True], 30), probe.status
    assert np.abs(polygon_to_array(targets[0])[:, :2] - expected).max() < 2.0
    assert wait_for(lambda: probe.value('malformed') == str(len(MALFORMED)), 10), probe.status
    assert proc.poll() is None


def test_pose_node_takes_landmarks_after_one_stamped_in_the_future(ros_node, processes):
    """cam1's landmarks once stamped in 2037 used to hold every later frame set. Each pose
    also goes out with its covariance (uav_vs.vision.pose_covariance)."""
    ground = load_ground_config(read_params_file(GROUND_CONFIG))
    processes('trinocular_pose_node', ['--params-file', str(GROUND_CONFIG),
                                       '-p', 'trinocular.diagnostics_period:=0.2'])
    poses: list[PoseStamped] = []
    ros_node.create_subscription(PoseStamped, '/ground/pose', poses.append, 10)
    with_cov: list[PoseWithCovarianceStamped] = []
    ros_node.create_subscription(PoseWithCovarianceStamped, '/ground/pose_cov',
                                 with_cov.append, 10)
    diags: dict = {}
    _collect_diagnostics(ros_node, diags)
    pubs = [ros_node.create_publisher(PolygonStamped, f'/{c.name}/landmarks', 10)
            for c in ground.cameras]
    assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs), 30)
    truth = np.array([0.4, -0.3, 1.2])
    polygons = [np.column_stack([px, np.ones(len(px))])
                for px in _project_layout(ground, truth, 2.5)]
    pubs[0].publish(points_to_polygon(polygons[0], FUTURE))
    name = '/trinocular_pose_node'
    assert wait_for(lambda: _last_diagnostics(diags, name).get('future') == '1', 10), diags
    assert diags[name].level >= DiagnosticStatus.WARN and "future" in diags[name].message
    for k in range(3):
        for pub, pts in zip(pubs, polygons):
            pub.publish(points_to_polygon(pts, Header(stamp=ns_to_stamp((k + 1) * S))))
        assert wait_for(lambda: len(poses) == k + 1, 10), str(_last_diagnostics(diags, name))
    assert [stamp_to_ns(p.header.stamp) for p in poses] == [S, 2 * S, 3 * S]
    assert all(np.linalg.norm(msg_to_pose(p)[0] - truth) < 1e-6 for p in poses)
    # the same poses with their covariance: exact centroids leave no residual, so the
    # pixel noise is the floor (0.5 px), plus the bias (0.01 m), as the core computes it
    assert wait_for(lambda: len(with_cov) == 3, 10)
    pixels = np.stack(_project_layout(ground, truth, 2.5))
    tri = triangulate(ground.cameras, pixels)
    expected = pose_covariance(ground.layout, solve_pose(ground.layout, tri.points),
                               landmark_covariances(ground.cameras, tri, 0.5), bias_sigma=0.01)
    for plain, msg in zip(poses, with_cov):
        assert msg.header == plain.header and msg.pose.pose == plain.pose
        assert np.allclose(np.reshape(msg.pose.covariance, (6, 6)), expected, rtol=1e-6)
