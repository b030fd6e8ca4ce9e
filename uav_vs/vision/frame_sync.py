"""Approximate time synchronisation of the cameras' detections (section 3.1.1).

Triangulation needs the landmark centroids of the same instant from every camera.
Cameras that are not hardware-triggered stamp their frames a few ms apart, so a
frame set is formed from one message per camera whose stamps lie within a
tolerance of each other. When a camera has nothing within tolerance and either it has
already sent a later frame (the frame of that instant was lost) or the others have
moved `max_wait_ns` past the set (it stalled), the set is released with the cameras it
has, if they are at least `min_sources` (a lost or stalled camera must not stop the pose).

`StampOrder` keeps one stream's frames in stamp order against the receiver's clock:
a frame stamped further ahead of that clock than a tolerance (a camera clock glitch)
is dropped without moving the order on, and a frame far older than the last one (a
bag loop, a new replay, a reset /clock) starts the order again instead of being
dropped as stale forever. FrameSync restarts the same way.
"""
from collections import deque
from dataclasses import dataclass, field
from enum import Enum
from typing import Any


class Verdict(Enum):
    """What to do with a frame, by its stamp."""

    NEW = 'new'            # newer than the last one: process it
    RESTART = 'restart'    # far older than the last one: time went back, start again
    STALE = 'stale'        # not newer than the last one (a copy, or late): drop it
    FUTURE = 'future'      # ahead of the clock by more than the tolerance: drop it


def ahead_of_clock(stamp_ns: int, now_ns: int, tolerance_ns: int) -> bool:
    """True if `stamp_ns` is more than `tolerance_ns` ahead of `now_ns`.

    A clock at 0 has not started (ROS time before the first /clock message): no frame
    is ahead of it.
    """
    return now_ns > 0 and stamp_ns - now_ns > tolerance_ns


@dataclass
class StampOrder:
    """One stream's frames in stamp order, a future glitch or a jump back survived.

    `check` judges a frame and counts the drops (`stale`, `future`); `take` records a
    frame that was processed, so a frame that could not be used moves nothing on.
    """

    future_tolerance_ns: int
    restart_after_ns: int
    last_ns: int | None = None
    counts: dict[str, int] = field(default_factory=lambda: dict(stale=0, future=0, restarts=0))

    def check(self, stamp_ns: int, now_ns: int) -> Verdict:
        if ahead_of_clock(stamp_ns, now_ns, self.future_tolerance_ns):
            self.counts['future'] += 1
            return Verdict.FUTURE
        if self.last_ns is None or stamp_ns > self.last_ns:
            return Verdict.NEW
        if self.last_ns - stamp_ns > self.restart_after_ns:
            return Verdict.RESTART
        self.counts['stale'] += 1
        return Verdict.STALE

    def take(self, stamp_ns: int) -> int:
        """Record a processed frame; how far time went back (ns) if it restarted the
        order, else 0."""
        back = 0 if self.last_ns is None else max(self.last_ns - stamp_ns, 0)
        self.last_ns = stamp_ns
        if back:
            self.counts['restarts'] += 1
        return back


@dataclass(frozen=True)
class FrameSet:
    """One synchronised set: the reference stamp and an item per source (None if absent)."""

    stamp_ns: int
    items: tuple[Any, ...]

    @property
    def n_present(self) -> int:
        return sum(item is not None for item in self.items)


class FrameSync:
    """Groups (source, stamp, item) arrivals into FrameSets, oldest first."""

    def __init__(self, n_sources: int, tolerance_ns: int, max_wait_ns: int,
                 min_sources: int = 2, queue_size: int = 30,
                 restart_after_ns: int | None = None) -> None:
        if n_sources < 1 or not 1 <= min_sources <= n_sources:
            raise ValueError(f'need 1 <= min_sources <= n_sources, got {min_sources}, {n_sources}')
        self.tolerance_ns = tolerance_ns
        self.max_wait_ns = max_wait_ns
        self.min_sources = min_sources
        self.restart_after_ns = restart_after_ns
        self.dropped = 0
        self.restarts = 0
        self._queues: list[deque] = [deque(maxlen=queue_size) for _ in range(n_sources)]

    def add(self, source: int, stamp_ns: int, item: Any) -> list[FrameSet]:
        """Queue one arrival; return the frame sets it completes (possibly none).

        An arrival older than its source's last one by more than `restart_after_ns`
        (time went back: a new replay) empties every queue first (`restarts`).
        """
        queue = self._queues[source]
        if queue and stamp_ns <= queue[-1][0]:
            if (self.restart_after_ns is None
                    or queue[-1][0] - stamp_ns <= self.restart_after_ns):
                self.dropped += 1        # out of order or duplicate: the set has moved on
                return []
            self._restart()
        if len(queue) == queue.maxlen:
            self.dropped += 1
        queue.append((stamp_ns, item))
        out = []
        while (frame_set := self._next()) is not None:
            out.append(frame_set)
        return out

    def _restart(self) -> None:
        self.restarts += 1
        for q in self._queues:
            self.dropped += len(q)
            q.clear()

    def _next(self) -> FrameSet | None:
        heads = [q[0][0] for q in self._queues if q]
        if not heads:
            return None
        pivot = min(heads)
        newest = max(q[-1][0] for q in self._queues if q)
        picks: list[int | None] = []
        for q in self._queues:
            best = min(range(len(q)), key=lambda k: abs(q[k][0] - pivot), default=None)
            picks.append(best if best is not None and abs(q[best][0] - pivot) <= self.tolerance_ns
                         else None)
        complete = all(p is not None for p in picks)
        timed_out = newest - pivot > self.max_wait_ns
        # A source with nothing within tolerance but something queued has moved past the
        # set (its stream is in stamp order): its frame of that instant was lost.
        passed = all(p is not None or q for q, p in zip(self._queues, picks))
        if not complete and not timed_out and not passed:
            return None
        items = tuple(self._queues[k][p][1] if p is not None else None
                      for k, p in enumerate(picks))
        for q, p in zip(self._queues, picks):
            if p is not None:
                self.dropped += p          # older arrivals of that source lose their set
                for _ in range(p + 1):
                    q.popleft()
            while q and q[0][0] <= pivot:      # nothing older than a released set stays
                q.popleft()
                self.dropped += 1
        frame_set = FrameSet(pivot, items)
        if frame_set.n_present < self.min_sources:
            self.dropped += frame_set.n_present
            return self._next()
        return frame_set
