"""Fast DDS shared-memory segments left behind by processes that have gone.

With the shared-memory transport (config/fastdds_shm.xml) each DDS participant keeps its
segment as a file in /dev/shm, next to a lock file `<segment>_el` that the owner holds
while it lives, and removes both when it is destroyed. A process killed (SIGKILL, a
crash) never does, and /dev/shm is memory: a test run or a long session that kills node
processes fills it until the kernel's OOM killer picks a process. `remove_orphaned`
removes the segments no living process holds, by the rule of Fast DDS's own
`fastdds shm clean`.
"""
import fcntl
import os
import re
import time
from pathlib import Path

SHM_DIR = Path('/dev/shm')
_SEGMENT_LOCK = re.compile(r'^fastrtps_[0-9a-z]{16}_el$')
# A lock file younger than this may belong to a participant still taking its lock.
MIN_AGE_S = 5.0


def _held(lock: Path) -> bool:
    """Whether a living process holds `lock` (its owner's flock)."""
    try:
        with open(lock, 'ab') as fd:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    return False


def remove_orphaned(shm_dir: Path = SHM_DIR, min_age_s: float = MIN_AGE_S) -> int:
    """Remove every Fast DDS segment in `shm_dir` whose owner has gone; how many."""
    try:
        names = os.listdir(shm_dir)
    except FileNotFoundError:
        return 0
    now, removed = time.time(), 0
    for name in filter(_SEGMENT_LOCK.match, names):
        lock = shm_dir / name
        try:
            young = now - lock.stat().st_mtime < min_age_s
        except FileNotFoundError:
            continue
        if young or _held(lock):
            continue
        for path in (shm_dir / name[:-3], lock):
            path.unlink(missing_ok=True)
        removed += 1
    return removed
