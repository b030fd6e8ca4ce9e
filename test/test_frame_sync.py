"""FrameSync groups the cameras' detections by stamp (section 3.1.1)."""
import pytest

from uav_vs.vision.frame_sync import FrameSync

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
