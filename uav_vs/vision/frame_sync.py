"""Approximate time synchronisation of the cameras' detections (section 3.1.1).

Triangulation needs the landmark centroids of the same instant from every camera.
Cameras that are not hardware-triggered stamp their frames a few ms apart, so a
frame set is formed from one message per camera whose stamps lie within a
tolerance of each other. When a camera has nothing within tolerance and the others
have already moved `max_wait_ns` past the set, the set is released with the cameras
it has, if they are at least `min_sources` (a stalled camera must not stop the pose).
"""
from collections import deque
from dataclasses import dataclass
from typing import Any


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
                 min_sources: int = 2, queue_size: int = 30) -> None:
        if n_sources < 1 or not 1 <= min_sources <= n_sources:
            raise ValueError(f'need 1 <= min_sources <= n_sources, got {min_sources}, {n_sources}')
        self.tolerance_ns = tolerance_ns
        self.max_wait_ns = max_wait_ns
        self.min_sources = min_sources
        self.dropped = 0
        self._queues: list[deque] = [deque(maxlen=queue_size) for _ in range(n_sources)]

    def add(self, source: int, stamp_ns: int, item: Any) -> list[FrameSet]:
        """Queue one arrival; return the frame sets it completes (possibly none)."""
        queue = self._queues[source]
        if queue and stamp_ns <= queue[-1][0]:
            self.dropped += 1        # out of order or duplicate: the set has moved on
            return []
        if len(queue) == queue.maxlen:
            self.dropped += 1
        queue.append((stamp_ns, item))
        out = []
        while (frame_set := self._next()) is not None:
            out.append(frame_set)
        return out

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
        if not complete and not timed_out:
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
