"""Replay a ground-camera bag through the ground graph and score its poses against truth.

The graph is started from console scripts with the params file, exactly as `ros2 run`
would: in the `one_process` layout (the default) as one ground_station process, in the
`processes` layout as separate processes (three camshift_node, one
trinocular_pose_node). The bag's images are published with their recorded stamps;
every `ground/pose` is matched by stamp to the bag's `truth/pose` (uav_vs.flight.pose_replay).
"""
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uav_vs import graph
from uav_vs.flight.pose_replay import pose_errors, replay_bag
from uav_vs.flight.report import rms


@dataclass
class GroundReport:
    frame_sets: int                      # image stamps in the bag
    poses: int                           # poses received
    position_rmse_m: float
    yaw_rmse_deg: float
    position_errors_m: np.ndarray = field(repr=False)
    yaw_errors_deg: np.ndarray = field(repr=False)
    return_codes: list[int] = field(default_factory=list)
    messages: dict = field(default_factory=dict, repr=False)   # stamp ns -> ground/pose

    def summary(self) -> str:
        return (f'{self.poses}/{self.frame_sets} frame sets gave a pose; position RMSE '
                f'{self.position_rmse_m * 100:.2f} cm (max {self.position_errors_m.max() * 100:.2f}'
                f' cm), yaw RMSE {self.yaw_rmse_deg:.3f} deg (max '
                f'{np.abs(self.yaw_errors_deg).max():.3f} deg)')


LAYOUTS = ('one_process', 'processes')
DEFAULT_LAYOUT = 'one_process'


def ground_graph(config: Path, cameras: list[str], log_dir: Path, extra_args: list[str] = (),
                 layout: str = DEFAULT_LAYOUT, env: dict[str, str] | None = None,
                 station_args: list[str] = ()) -> dict[str, subprocess.Popen]:
    """Start the ground station, its processes by label: `one_process`, the
    ground_station (the params file's cameras; `station_args` before its --ros-args);
    `processes`, one camshift_node per camera of `cameras` and the trinocular_pose_node."""
    if layout not in LAYOUTS:
        raise ValueError(f'ground layout {layout!r}: expected one of {", ".join(LAYOUTS)}')
    args = ['--params-file', str(config), *extra_args]
    if layout == 'one_process':
        return {'ground_station': graph.start('ground_station', args, log_dir, env=env,
                                              args=station_args)}
    procs = {cam: graph.start('camshift_node', [*args, '-r', f'__ns:=/{cam}',
                                                '-p', f'camera:={cam}'], log_dir, cam, env)
             for cam in cameras}
    procs['trinocular_pose_node'] = graph.start('trinocular_pose_node', args, log_dir, env=env)
    return procs


def replay_ground_bag(bag: Path, config: Path, log_dir: Path, cameras: list[str],
                      rate: float = 1.0, settle_s: float = 2.0, extra_args: list[str] = (),
                      layout: str = DEFAULT_LAYOUT) -> GroundReport:
    """Run the ground graph on `bag` and compare its poses with the bag's truth."""
    replay = replay_bag(bag, lambda: list(ground_graph(config, cameras, log_dir, extra_args,
                                                       layout).values()),
                        'ground/pose', rate, settle_s)
    err = pose_errors(replay.poses, replay.truth)
    return GroundReport(len(replay.truth), len(err.stamps), rms(err.position_m), rms(err.yaw_deg),
                        err.position_m, err.yaw_deg, replay.return_codes, replay.poses)
