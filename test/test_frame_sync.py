"""FrameSync groups the cameras' detections by stamp (section 3.1.1)."""
import pytest

from uav_vs.vision.frame_sync import FrameSync, StampOrder, Verdict

MS = 1_000_000


def test_sets_form_from_stamps_within_tolerance_in_any_arrival_order():
    sync = FrameSync(3, tolerance_ns=5 * MS, max_wait_ns=100 * MS)
    out = []
    for t in range(0, 300, 33):                      # 30 Hz, cameras 0-3 ms apart
        out += sync.add(2, (t + 3) * MS, ('c2', t))
        out += sync.add(0, t * MS, ('c0', t))
        out += sync.add(1, (t + 1) * MS, ('c1', t))
    assert len(out) == 10
    for frame_set in out:
        assert frame_set.n_present == 3
        assert len({item[1] for item in frame_set.items}) == 1   # same instant everywhere
    assert sync.dropped == 0


def test_silent_camera_releases_set_after_max_wait_with_the_others():
    sync = FrameSync(3, tolerance_ns=5 * MS, max_wait_ns=50 * MS)
    out = []
    for t in range(0, 200, 20):
        out += sync.add(0, t * MS, t)
        out += sync.add(1, t * MS, t)
    # camera 2 never speaks: sets older than 50 ms behind the newest come out with 2 items
    assert [s.stamp_ns // MS for s in out] == [0, 20, 40, 60, 80, 100, 120]
    assert all(s.items[2] is None and s.n_present == 2 for s in out)


def test_a_lost_frame_releases_its_set_with_that_cameras_next_frame_not_after_max_wait():
    sync = FrameSync(3, tolerance_ns=5 * MS, max_wait_ns=200 * MS)
    assert sync.add(0, 0, 'c0 at 0') == [] and sync.add(1, 1 * MS, 'c1 at 0') == []
    # camera 2's frame of instant 0 was lost; its frame of instant 33 ms arrives first
    [lost] = sync.add(2, 35 * MS, 'c2 at 33')
    assert lost.stamp_ns == 0 and lost.items == ('c0 at 0', 'c1 at 0', None)
    assert sync.add(0, 33 * MS, 'c0 at 33') == []
    [whole] = sync.add(1, 34 * MS, 'c1 at 33')
    assert whole.stamp_ns == 33 * MS and whole.items == ('c0 at 33', 'c1 at 33', 'c2 at 33')


def test_lone_camera_never_makes_a_set_and_old_arrivals_are_dropped():
    sync = FrameSync(3, tolerance_ns=5 * MS, max_wait_ns=50 * MS, min_sources=2)
    out = []
    for t in range(0, 200, 20):
        out += sync.add(0, t * MS, t)
    assert out == []
    assert sync.add(0, 100 * MS, 'late duplicate') == []
    assert sync.dropped > 0


def test_min_sources_is_checked():
    with pytest.raises(ValueError, match='min_sources'):
        FrameSync(2, 1, 1, min_sources=3)


def test_stamp_order_drops_a_future_stamp_without_moving_on():
    order = StampOrder(future_tolerance_ns=1000 * MS, restart_after_ns=1000 * MS)
    now = 50_000 * MS
    assert order.check(now - 10, now) is Verdict.NEW
    order.take(now - 10)
    assert order.check(now + 3600_000 * MS, now) is Verdict.FUTURE      # a clock glitch
    assert order.check(now + 900 * MS, now) is Verdict.NEW               # within tolerance
    assert order.check(now - 10, now) is Verdict.STALE                   # a copy
    assert order.counts == dict(stale=1, future=1, restarts=0)


def test_stamp_order_before_the_clock_starts_takes_any_stamp():
    """ROS time reads 0 until the first /clock message: nothing is ahead of it."""
    order = StampOrder(future_tolerance_ns=0, restart_after_ns=1000 * MS)
    assert order.check(10**18, 0) is Verdict.NEW


def test_stamp_order_restarts_when_time_goes_back_far():
    order = StampOrder(future_tolerance_ns=1000 * MS, restart_after_ns=1000 * MS)
    now = 50_000 * MS
    order.take(20_000 * MS)
    assert order.check(19_500 * MS, now) is Verdict.STALE                # late, not a replay
    assert order.check(5_000 * MS, now) is Verdict.RESTART               # the bag again
    assert order.take(5_000 * MS) == 15_000 * MS
    assert order.check(5_100 * MS, now) is Verdict.NEW
    assert order.counts['restarts'] == 1


def test_frame_sync_restarts_when_a_source_goes_back_far():
    """Sets waiting on a silent camera hold the queues; a new replay must not be dropped
    behind them as out of order."""
    sync = FrameSync(3, tolerance_ns=5 * MS, max_wait_ns=10_000 * MS, restart_after_ns=1000 * MS)
    for t in range(0, 300, 33):
        assert sync.add(0, (60_000 + t) * MS, t) == []
        assert sync.add(1, (60_000 + t) * MS, t) == []        # camera 2 silent: all wait
    out = []
    for t in range(0, 100, 33):                                # the replay from its start
        for k in range(3):
            out += sync.add(k, t * MS, t)
    assert sync.restarts == 1
    assert [s.stamp_ns // MS for s in out] == [0, 33, 66, 99]
    assert all(s.n_present == 3 for s in out)
