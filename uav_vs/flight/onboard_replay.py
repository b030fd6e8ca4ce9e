"""Replay an onboard-camera bag through homography_pose_node and score it against truth.

The node is started as a separate process from its console script with the params
file, as `ros2 run` would; the bag's images are published with their recorded stamps
and every `onboard/pose` is matched by stamp to the bag's `truth/pose`
(uav_vs.flight.pose_replay). Position errors are also given relative to the camera's height
above the ground plane, the natural scale of a plane-homography pose (section 4).
"""
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from uav_vs import graph
from uav_vs.flight.pose_replay import PoseErrors, pose_errors, replay_bag
from uav_vs.flight.report import rms
from uav_vs.vision.ground_config import read_params_file
from uav_vs.vision.onboard_config import load_onboard_config


@dataclass
class OnboardReport:
    frames: int                          # image stamps in the bag
    poses: int                           # poses received with a truth of the same stamp
    position_rmse_m: float
    relative_rmse: float                 # RMS of position error / camera height
    attitude_rmse_deg: float             # RMS of the full rotation error angle
    errors: PoseErrors = field(repr=False)
    camera_heights_m: np.ndarray = field(repr=False)
    return_codes: list[int] = field(default_factory=list)

    def summary(self) -> str:
        e = self.errors
        return (f'{self.poses}/{self.frames} frames gave a pose; position RMSE '
                f'{self.position_rmse_m * 1000:.1f} mm = {self.relative_rmse * 100:.2f} % of the '
                f'camera height (worst {np.max(e.position_m / self.camera_heights_m) * 100:.2f} %),'
                f' attitude RMSE {self.attitude_rmse_deg:.3f} deg (worst '
                f'{np.max(e.attitude_deg):.3f} deg)')


def onboard_graph(config: Path, log_dir: Path, extra_args: list[str] = ()) -> list:
    """Start the homography_pose_node with the params file."""
    return [graph.start('homography_pose_node', ['--params-file', str(config), *extra_args],
                        log_dir, 'homography_pose_node')]


def replay_onboard_bag(bag: Path, config: Path, log_dir: Path, rate: float = 1.0,
                       settle_s: float = 2.0, extra_args: list[str] = ()) -> OnboardReport:
    """Run homography_pose_node on `bag` and compare its poses with the bag's truth."""
    camera_to_body = load_onboard_config(read_params_file(config)).camera_to_body
    replay = replay_bag(bag, lambda: onboard_graph(config, log_dir, extra_args), 'onboard/pose',
                        rate, settle_s)
    err = pose_errors(replay.poses, replay.truth)
    R_wb = Rotation.from_quat(err.truth_quaternions).as_matrix() if len(err.stamps) else []
    heights = np.array([p[2] + (R @ camera_to_body[:3, 3])[2]
                        for p, R in zip(err.truth_positions, R_wb)], float)
    return OnboardReport(len(replay.truth), len(err.stamps), rms(err.position_m),
                         rms(err.position_m / heights),
                         rms(err.attitude_deg), err, heights, replay.return_codes)
