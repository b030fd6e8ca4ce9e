"""The simulated world's delay line (uav_vs.sim.delay_line) runs each action once, never
before its due time, in due order, whatever order they were put in."""
import threading
import time

from uav_vs.sim.delay_line import DelayLine


def test_actions_run_in_due_order_never_early():
    line = DelayLine()
    ran: list[tuple[int, float]] = []
    done = threading.Event()
    start = time.monotonic()
    dues = {k: start + d for k, d in enumerate([0.3, 0.1, 0.2, 0.1, 0.0, 0.25])}
    for k, due in dues.items():
        line.put(due, lambda k=k: (ran.append((k, time.monotonic())),
                                   len(ran) == len(dues) and done.set()))
    assert done.wait(10.0)
    line.close()
    assert [k for k, _ in ran] == [4, 1, 3, 2, 5, 0]    # equal dues keep their order
    assert all(t >= dues[k] for k, t in ran)


def test_close_drops_what_is_not_due():
    line = DelayLine()
    ran = []
    line.put(time.monotonic() + 30.0, lambda: ran.append(1))
    line.close()
    assert ran == [] and not line._thread.is_alive()
