"""Replay a ground-camera bag through the ground graph and score its poses against truth.

The graph is started as separate processes (three camshift_node, one
trinocular_pose_node), each from its console script with the params file, exactly
as `ros2 run` would. The bag's images are published with their recorded stamps;
every `ground/pose` is matched by stamp to the bag's `truth/pose` (uav_vs.pose_replay).
"""
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uav_vs import graph
from uav_vs.flight_report import rms
from uav_vs.pose_replay import pose_errors, replay_bag


@dataclass
class GroundReport:
    frame_sets: int                      # image stamps in the bag
    poses: int                           # poses received
    position_rmse_m: float
    yaw_rmse_deg: float
    position_errors_m: np.ndarray = field(repr=False)
    yaw_errors_deg: np.ndarray = field(repr=False)
    return_codes: list[int] = field(default_factory=list)

    def summary(self) -> str:
        return (f'{self.poses}/{self.frame_sets} frame sets gave a pose; position RMSE '
                f'{self.position_rmse_m * 100:.2f} cm (max {self.position_errors_m.max() * 100:.2f}'
                f' cm), yaw RMSE {self.yaw_rmse_deg:.3f} deg (max '
                f'{np.abs(self.yaw_errors_deg).max():.3f} deg)')


def ground_graph(config: Path, cameras: list[str], log_dir: Path,
                 extra_args: list[str] = ()) -> list:
    """Start one camshift_node per camera and the trinocular_pose_node."""
    procs = [graph.start('camshift_node', ['--params-file', str(config), '-r', f'__ns:=/{cam}',
                                           '-p', f'camera:={cam}', *extra_args], log_dir, cam)
             for cam in cameras]
    procs.append(graph.start('trinocular_pose_node', ['--params-file', str(config), *extra_args],
                             log_dir, 'trinocular_pose_node'))
    return procs


def replay_ground_bag(bag: Path, config: Path, log_dir: Path, cameras: list[str],
                      rate: float = 1.0, settle_s: float = 2.0,
                      extra_args: list[str] = ()) -> GroundReport:
    """Run the ground graph on `bag` and compare its poses with the bag's truth."""
    replay = replay_bag(bag, lambda: ground_graph(config, cameras, log_dir, extra_args),
                        'ground/pose', rate, settle_s)
    err = pose_errors(replay.poses, replay.truth)
    return GroundReport(len(replay.truth), len(err.stamps), rms(err.position_m), rms(err.yaw_deg),
                        err.position_m, err.yaw_deg, replay.return_codes)
