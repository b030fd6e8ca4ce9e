"""How long a node's input has been silent, for its diagnostics.

Silence is timed on the steady clock, not the node's ROS clock: when a replay or a
simulator stops, /clock stops with it and ROS time would say nothing is missing.
"""
import time

from uav_vs.ros.node_main import ERROR, OK, WARN
from uav_vs.ros.params import Param, T


def silence_params(prefix: str, what: str = 'an image') -> list[Param]:
    """`<prefix>.input_warn_after` and `<prefix>.input_error_after`, both live."""
    return [
        Param(f'{prefix}.input_warn_after', T.DOUBLE, 1.0,
              f'diagnostics go WARN when no {what} has come for this long '
              '(steady clock), s', 0.0, 1e6, live=True),
        Param(f'{prefix}.input_error_after', T.DOUBLE, 5.0,
              '... and ERROR when none has come for this long, s', 0.0, 1e6, live=True),
    ]


class Silence:
    """The time since an input was last heard, judged against a WARN and an ERROR bound."""

    def __init__(self, warn_after_s: float = 1.0, error_after_s: float = 5.0,
                 clock=time.monotonic) -> None:
        self.warn_after_s, self.error_after_s = warn_after_s, error_after_s
        self._clock = clock
        self._last: float | None = None

    def heard(self) -> None:
        self._last = self._clock()

    def silent_s(self) -> float | None:
        """Seconds since the input was last heard; None if it never was."""
        return None if self._last is None else self._clock() - self._last

    def level(self) -> int:
        """OK, WARN or ERROR by the silence; OK for an input never heard (the node says
        'no image yet' and the like itself)."""
        silent = self.silent_s()
        if silent is None or silent <= self.warn_after_s:
            return OK
        return ERROR if silent > self.error_after_s else WARN

    def judge(self, level: int, message: str, what: str = 'input') -> tuple[int, str]:
        """(level, message) made WARN or ERROR when the input has been silent too long."""
        if (silence := self.level()) == OK:
            return level, message
        return max(level, silence), f'no {what} for {self.silent_s():.1f} s; {message}'
