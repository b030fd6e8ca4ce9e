"""`make demo`: replay the bundled trinocular bag through the ground graph and score it.

Three camshift_node processes and a trinocular_pose_node are started from their
console scripts with config/ground_trinocular.yaml; the bag's images are published
at their recorded rate, and every published pose is compared with the bag's truth.
"""
import argparse
import sys
from pathlib import Path

from uav_vs.ground_replay import replay_ground_bag


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', type=Path, default=Path('bags/ground_trinocular'))
    parser.add_argument('--config', type=Path, default=Path('config/ground_trinocular.yaml'))
    parser.add_argument('--cameras', nargs='+', default=['cam1', 'cam2', 'cam3'])
    parser.add_argument('--rate', type=float, default=1.0, help='replay speed (1 = recorded)')
    parser.add_argument('--out', type=Path, default=Path('demo-output'), help='node logs go here')
    args = parser.parse_args(argv)
    print(f'replaying {args.bag} through {len(args.cameras)} camshift_node + '
          f'trinocular_pose_node (logs in {args.out}/)', flush=True)
    report = replay_ground_bag(args.bag, args.config, args.out, args.cameras, args.rate)
    print(report.summary())
    return 0 if report.poses else 1


if __name__ == '__main__':
    sys.exit(main())
