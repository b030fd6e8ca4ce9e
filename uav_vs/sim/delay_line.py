"""A delay line: actions run at their due times, on a thread of their own.

The simulated world publishes each frame `latency` after its capture (uav_vs.sim.
camera_effects.Latency); a timer per frame in the node's executor was seen to fire
seconds late, so the frames wait here instead, each for exactly its own delay.
"""
import heapq
import itertools
import threading
import time
from typing import Callable


class DelayLine:
    """Runs each action put in at its due time (time.monotonic(), s), in due order."""

    def __init__(self, name: str = 'delay line') -> None:
        self._queue: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()     # equal due times keep their order
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, due: float, action: Callable[[], None]) -> None:
        with self._cond:
            heapq.heappush(self._queue, (due, next(self._order), action))
            self._cond.notify()

    def close(self) -> None:
        """Stop; what has not fallen due is dropped."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (
                        not self._queue or self._queue[0][0] > time.monotonic()):
                    self._cond.wait(self._queue[0][0] - time.monotonic() if self._queue
                                    else None)
                if self._closed:
                    return
                _, _, action = heapq.heappop(self._queue)
            action()
