"""Where the third-party test data lives (used by tests and benchmarks)."""
import os
from pathlib import Path

HOW_TO_GET = ('third-party data not found: set UAV_VS_DATA to a folder holding '
              'oxford/, opencv/ and rosbag2/ (see docs/data.md)')


def shared_data_dir() -> Path | None:
    """Return $UAV_VS_DATA, else ../shared/data beside the checkout, else None."""
    env = os.environ.get('UAV_VS_DATA')
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / 'shared' / 'data')
    for path in candidates:
        if path.is_dir():
            return path
    return None
