"""Silence: how long an input has been quiet, judged against a WARN and an ERROR bound.

Truth: a hand-driven clock, so every boundary is exact.
"""
from uav_vs.ros.liveness import Silence
from uav_vs.ros.node_main import ERROR, OK, WARN


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_an_input_never_heard_is_left_to_the_node():
    clock = FakeClock()
    silence = Silence(1.0, 5.0, clock)
    clock.t += 1000.0
    assert silence.silent_s() is None and silence.level() == OK
    assert silence.judge(WARN, 'no image yet') == (WARN, 'no image yet')


def test_silence_goes_warn_past_the_first_bound_and_error_past_the_second():
    clock = FakeClock()
    silence = Silence(1.0, 5.0, clock)
    silence.heard()
    clock.t += 1.0                                  # at the bound: still fine
    assert silence.judge(OK, 'pose ok') == (OK, 'pose ok')
    clock.t += 0.5
    assert silence.judge(OK, 'pose ok') == (WARN, 'no input for 1.5 s; pose ok')
    clock.t += 3.5                                  # 5.0: at the second bound
    assert silence.judge(OK, 'pose ok', 'frame')[0] == WARN
    clock.t += 1.0
    assert silence.judge(OK, 'pose ok', 'frame') == (ERROR, 'no frame for 6.0 s; pose ok')
    silence.heard()
    assert silence.judge(OK, 'pose ok') == (OK, 'pose ok')


def test_silence_never_lowers_what_the_node_said():
    clock = FakeClock()
    silence = Silence(1.0, 5.0, clock)
    silence.heard()
    clock.t += 2.0
    assert silence.judge(ERROR, 'no landmark found')[0] == ERROR


def test_new_bounds_apply_at_once():
    clock = FakeClock()
    silence = Silence(1.0, 5.0, clock)
    silence.heard()
    clock.t += 2.0
    assert silence.level() == WARN
    silence.error_after_s = 1.5
    assert silence.level() == ERROR
    silence.warn_after_s = silence.error_after_s = 10.0
    assert silence.level() == OK
