"""Closed loop (chapter section 5): the vehicle flies on vision alone, judged against truth.

The whole graph runs as separate processes around the simulated vehicle
(uav_vs.flight.scenario.fly): sim_world, mavlink_relay_node, three camshift_node and the
trinocular_pose_node, homography_pose_node and fuzzy_controller_node. The vehicle takes
off, holds, flies to a setpoint on the ground station's pose and lands on a pad on the
onboard pose. Every assertion is against the simulator's truth (`truth/pose`), and the
ROS graph itself is asked what the controller flew on.
"""
import re
from collections import defaultdict

import numpy as np
import yaml
from rclpy.serialization import deserialize_message
from rosbags.typesys.base import Nodetype

from conftest import REPO
from ros2msg import schema_types
from uav_vs.bag.reader import Bag
from uav_vs.bag.schemas import message_schema
from uav_vs.flight.live_view import LAYOUT, SLOW_LINK, load_layout, references
from uav_vs.flight.replay import replay_flight
from uav_vs.flight.report import FlightReport
from uav_vs.flight.scenario import Configs, Landing, Scenario, Setpoint, fly
from uav_vs.ros.convert import stamp_to_ns
from uav_vs.ros.replay import message_class
from uav_vs.vision.ground_config import default_config_path

SCENARIO = Scenario('test', 1.3, Setpoint((0.0, 0.0, 1.3), hold=1.0),
                    (Setpoint((0.7, -0.5, 1.5), hold=1.5),),
                    Landing((-0.5, 0.4), approach=1.1, final=0.8, hold=1.0))


def test_reaches_setpoint_and_lands_on_pad_on_vision_alone(tmp_path):
    log = fly(SCENARIO, tmp_path)
    report = FlightReport.from_log(log)
    print(report.summary())
    assert log.failure == '', log.failure

    # The controller's only pose input was a vision pose: the ground station's for the
    # setpoints, the onboard camera's over the pad; never the truth nor autopilot/odom.
    for event in log.setpoints:
        assert event.controller_inputs == tuple(sorted((f'/{event.source}/pose', '/setpoint'))), \
            (event.name, event.controller_inputs)
    assert [e.source for e in log.setpoints] == ['ground', 'ground', 'onboard', 'onboard']

    setpoint = report.setpoints[1]
    assert setpoint.reached
    assert setpoint.error_max_m <= 0.2           # true distance over the whole hold

    assert report.landing is not None
    assert report.landing.touchdown[2] < 0.01    # on the ground
    assert report.landing.error_m <= 0.3         # true touchdown point to the pad

    # Both vision poses were scored against truth in flight and are accurate.
    assert report.sources['ground'].samples > 0 and report.sources['onboard'].samples > 0
    assert report.sources['ground'].position_rmse_m <= 0.05
    assert report.sources['onboard'].position_rmse_m <= 0.05

    # The flight's bag replays through the open-loop graph (`make demo BAG=...`): the
    # vision nodes see the recorded (JPEG) frames and are as accurate as in flight.
    # The recorder kept the frames: as many JPEG images as (reliable) camera_info, but for
    # a frame or two at the start, before both subscriptions were matched, and the few a
    # loaded machine loses of a best-effort stream (sensor-data QoS, as a camera offers it).
    with Bag(tmp_path / 'bag') as bag:
        counts = {t.lstrip('/'): info.count for t, info in bag.topics.items()}
    for cam in ('cam1', 'cam2', 'cam3', 'onboard'):
        infos, images = counts[f'{cam}/camera_info'], counts[f'{cam}/image_raw/compressed']
        assert infos > 100
        assert 0.95 * infos - 2 <= images <= infos + 2, (cam, images, infos)
    # The windows a viewer draws over the recorded frames (the layout opens the bag):
    # each on the stamp of a frame of its camera, each landmark found in it inside one.
    for cam in ('cam1', 'cam2', 'cam3'):
        windows, landmarks, on_frames, inside, found = windows_in_bag(tmp_path / 'bag', cam)
        assert windows >= 0.95 * landmarks, (cam, windows, landmarks)
        assert on_frames == windows and inside == found > 3 * windows, \
            (cam, windows, on_frames, inside, found)
    posable = posable_poses(tmp_path / 'bag', {'ground': ('cam1', 'cam2', 'cam3'),
                                                'onboard': ('onboard',)})
    replay = FlightReport.from_log(replay_flight(tmp_path / 'bag', tmp_path / 'replay'))
    print(replay.summary())
    assert not any(replay.exit_codes.values()), replay.exit_codes
    for name in ('ground', 'onboard'):
        score = replay.sources[name]
        assert posable[name] >= 0.9 * counts[f'{name}/pose'], (name, posable[name])
        assert score.samples >= 0.95 * posable[name], (name, score, posable[name])
        assert score.position_rmse_m <= 0.05, (name, score)
    assert replay.commands.from_images > 0      # the controller ran on the replayed poses


def test_a_px4_vehicle_flies_on_the_fused_pose_through_blind_ground_cameras(tmp_path):
    """The simulated vehicle behaves as PX4 (OFFBOARD only once setpoints stream, AMSL
    takeoff altitude, AUTO.LOITER after the takeoff): the unchanged relay and mission
    hold and fly to a setpoint on the pose filter's estimate, the ground cameras covered
    for the first 3 s of the way, then approach the pad on the onboard pose and land on
    it. The live view runs beside it as `make demo VIEW=1` runs it (with the pose filter
    and frames_node), on a free port, with the slow link's copies too: the layouts that
    ship name only topics and fields it served."""
    scenario = Scenario('px4', 1.3, Setpoint((0.0, 0.0, 1.3), hold=1.0),
                        (Setpoint((-0.4, 0.5, 1.4), hold=1.0),),
                        Landing((0.5, -0.4), approach=1.1, final=0.8, hold=1.0),
                        fused=True, blind=3.0)
    viewer = tmp_path / 'foxglove.yaml'
    params = yaml.safe_load((REPO / 'config' / 'foxglove_slow_link.yaml').read_text())
    params['/**']['ros__parameters']['foxglove']['port'] = 0
    viewer.write_text(yaml.safe_dump(params))
    configs = Configs(foxglove=viewer, frames=default_config_path('frames.yaml'),
                      pose_filter=default_config_path('pose_filter.yaml'))
    log = fly(scenario, tmp_path, configs, record=False, autopilot='px4')
    report = FlightReport.from_log(log)
    print(report.summary())
    assert log.failure == '', log.failure
    assert [e.source for e in log.setpoints] == ['fused', 'fused', 'onboard', 'onboard']
    assert [e.controller_inputs for e in log.setpoints[:2]] == [('/fused/pose', '/setpoint')] * 2
    assert all(s.reached for s in report.setpoints)
    # The ground station gave no pose for the 3 s (its poses' stamps say so); the filter
    # went on publishing on the onboard pose and the autopilot's odometry, within 10 cm
    # of the truth all along.
    blind = report.blind
    assert blind is not None and blind.covered_s >= 3.0 and blind.ground_gap_s >= 3.0, blind
    assert blind.fused_samples >= 10 * blind.ground_gap_s, blind      # it runs at 50 Hz
    assert blind.fused_max_m <= 0.10, blind
    assert report.landing is not None and report.landing.touchdown[2] < 0.01
    assert report.landing.error_m <= 0.3
    assert not any(log.exit_codes.values()), log.exit_codes
    # OFFBOARD before arming, and again after the takeoff ended in AUTO.LOITER.
    relay = (tmp_path / 'logs' / 'mavlink_relay_node.log').read_text()
    assert 'set_guided: done (OFFBOARD, disarmed)' in relay
    assert 'set_guided: done (OFFBOARD, armed)' in relay
    viewer_log = (tmp_path / 'logs' / 'foxglove_node.log').read_text()
    assert 'serving ws://127.0.0.1:' in viewer_log
    served = dict(re.findall(r'advertising (\S+) \((\S+)\)', viewer_log))
    layouts = [references(load_layout(path)) for path in (LAYOUT, SLOW_LINK)]
    for panel, topic, fields in layouts[0] + layouts[1]:
        if topic in ONLY_WHILE_FOLLOWING:
            continue
        assert topic in served, (panel, topic, sorted(served))
        if fields:
            assert leaf_type(served[topic], fields), (panel, topic, fields)


# Topics of the layout that only the follow mission's nodes publish (target_tracker_node).
ONLY_WHILE_FOLLOWING = {'/onboard/target_outline', '/onboard/target_outline/jpeg'}


def leaf_type(msgtype: str, fields: tuple[str, ...]) -> str | None:
    """The type of msgtype's field `a.b.c` (a number or string for a plot), from the
    schema foxglove_node advertises it with; None if there is no such field."""
    types = schema_types(msgtype, message_schema(msgtype))
    for k, name in enumerate(fields):
        definitions = dict(types[msgtype][1])
        if name not in definitions:
            return None
        kind, desc = definitions[name]
        if kind == Nodetype.NAME:
            msgtype = desc
        else:
            return desc[0] if k == len(fields) - 1 and kind == Nodetype.BASE else None
    return None


def windows_in_bag(bag, cam: str) -> tuple[int, int, int, int, int]:
    """A camera's recorded landmark_windows from its first recorded camera_info on (the
    frames' reliable twin: a best-effort image may be lost): how many, how many
    `cam/landmarks` from the first of them on (the recorder may have matched one topic
    later than the other), how many on the stamp of one of its frames, and of the
    landmark centres `cam/landmarks` gave for those stamps, how many lie inside one of
    the windows of the same stamp and how many were found."""
    topics = {f'{cam}/{t}' for t in ('camera_info', 'landmarks', 'landmark_windows')}
    frames, centres, windows = set(), {}, {}
    with Bag(bag) as recorded:
        for m in recorded.messages([t for t in recorded.topics if t.lstrip('/') in topics]):
            msg = deserialize_message(m.raw, message_class(m.msgtype))
            stamp, kind = stamp_to_ns(msg.header.stamp), m.topic.rsplit('/', 1)[-1]
            if kind == 'camera_info':
                frames.add(stamp)
            elif kind == 'landmarks':
                centres[stamp] = [(p.x, p.y) for p in msg.polygon.points if p.x == p.x]
            else:       # LINE_LIST: each window's 4 sides, 8 points
                corners = np.array([(p.x, p.y) for p in msg.points]).reshape(-1, 8, 2)
                windows[stamp] = np.hstack([corners.min(axis=1), corners.max(axis=1)])
    windows = {stamp: boxes for stamp, boxes in windows.items() if stamp >= min(frames)}
    inside = found = 0
    for stamp, boxes in windows.items():
        for x, y in centres.get(stamp, []):
            found += 1
            inside += any(x0 <= x <= x1 and y0 <= y <= y1 for x0, y0, x1, y1 in boxes)
    since = [stamp for stamp in centres if windows and stamp >= min(windows)]
    return len(windows), len(since), len(windows.keys() & frames), inside, found


def posable_poses(bag, sources: dict[str, tuple[str, ...]]) -> dict[str, int]:
    """Per pose source, the flight's poses whose camera frames and truth are all in the
    bag: the poses a replay of the bag can give again and score (a recorder under load
    may miss a message)."""
    stamps: dict[str, set[int]] = defaultdict(set)
    wanted = {f'{cam}/image_raw/compressed' for cams in sources.values() for cam in cams}
    wanted |= {f'{name}/pose' for name in (*sources, 'truth')}
    with Bag(bag) as recorded:
        topics = [t for t in recorded.topics if t.lstrip('/') in wanted]
        for m in recorded.messages(topics):
            msg = deserialize_message(m.raw, message_class(m.msgtype))
            stamps[m.topic.lstrip('/')].add(stamp_to_ns(msg.header.stamp))
    return {name: len(stamps[f'{name}/pose'].intersection(
                stamps['truth/pose'], *(stamps[f'{cam}/image_raw/compressed'] for cam in cams)))
            for name, cams in sources.items()}
