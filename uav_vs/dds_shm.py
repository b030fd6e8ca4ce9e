"""Fast DDS shared-memory segments left behind by processes that have gone.

With the shared-memory transport (config/fastdds_shm.xml) each DDS participant keeps its
segment as a file in /dev/shm, next to a lock file `<segment>_el` that the owner holds
while it lives, and removes both when it is destroyed. A process killed (SIGKILL, a
crash) never does, and /dev/shm is memory: a test run or a long session that kills node
processes fills it until the kernel's OOM killer picks a process. `remove_orphaned`
removes the segments no living process holds, by the rule of Fast DDS's own
`fastdds shm clean`; `remove_own`, for a process about to exit, removes those it holds.
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


def held_by(pid: int, shm_dir: Path = SHM_DIR) -> list[Path]:
    """The Fast DDS segments whose lock process `pid` holds (its flocks in /proc/locks);
    none where /proc/locks cannot be read."""
    try:
        lines = Path('/proc/locks').read_text().splitlines()
    except OSError:
        return []
    inodes = {int(fields[5].rsplit(':', 1)[1]) for fields in map(str.split, lines)
              if len(fields) > 5 and fields[1] == 'FLOCK' and fields[4] == str(pid)}
    out = []
    for lock in shm_dir.glob('fastrtps_*_el'):
        try:
            if _SEGMENT_LOCK.match(lock.name) and lock.stat().st_ino in inodes:
                out.append(shm_dir / lock.name[:-3])
        except FileNotFoundError:
            continue
    return out


def remove_own(shm_dir: Path = SHM_DIR) -> int:
    """Remove the segments this process holds; how many. For a process about to exit
    whose DDS participant may not have been destroyed yet (it is, once nothing holds its
    nodes' handles): the memory stays mapped for whoever has it open, and no living
    process owns the files after the exit."""
    own = held_by(os.getpid(), shm_dir)
    for segment in own:
        for path in (segment, segment.with_name(f'{segment.name}_el')):
            path.unlink(missing_ok=True)
    return len(own)
