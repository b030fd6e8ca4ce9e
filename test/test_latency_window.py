"""The ground latency benchmark counts poses by the frame they came from (bench.ground_latency):
a frame set without a pose is a lost pose, wherever the measured window starts. A camera
driver hung in its teardown is stopped, not waited for."""
import subprocess
import sys

import numpy as np

from bench.ground_latency import (SECONDS, WARMUP_S, _end_drivers, expected_frames,
                                  frames_in_window)

START_NS = 1_700_000_000_123_456_789


def stamps(rate: float, frames: np.ndarray, late_s: np.ndarray) -> np.ndarray:
    """Stamps of driver frames published late_s after they were due."""
    return START_NS + np.round((frames / rate + late_s) * 1e9).astype(np.int64)


def test_every_frame_of_the_window_is_found_once_from_its_stamp():
    rate = 30.0
    frames = np.arange(int(SECONDS * rate) + 5)
    rng = np.random.default_rng(3)
    # a driver stamps its frame when it publishes it: up to a few ms early (the two
    # clocks' offset) or most of a period late (a busy machine)
    late = rng.uniform(-0.003, 0.85 / rate, len(frames))
    k = frames_in_window(stamps(rate, frames, late), START_NS, rate)
    inside = (frames >= WARMUP_S * rate) & (frames < SECONDS * rate)
    np.testing.assert_array_equal(k[inside], frames[inside])
    assert (k[~inside] == -1).all()
    assert len(np.unique(k[inside])) == expected_frames(rate) == 195


def test_a_frame_without_a_pose_is_missing_from_the_count():
    rate = 60.0
    frames = np.arange(int(SECONDS * rate))
    lost = np.array([int(WARMUP_S * rate), 200, int(SECONDS * rate) - 1])
    got = np.setdiff1d(frames, lost)
    k = frames_in_window(stamps(rate, got, np.full(len(got), 0.004)), START_NS, rate)
    assert len(np.unique(k[k >= 0])) == expected_frames(rate) - len(lost)


def test_a_driver_hung_in_its_teardown_is_stopped_and_named(capsys):
    done = subprocess.Popen([sys.executable, '-c', 'pass'])
    hung = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    _end_drivers([done, hung], ['cam1', 'cam2'], timeout=1.0)
    assert done.returncode == 0
    assert hung.poll() is not None                  # stopped, not left running
    assert 'driver(s) cam2 still running' in capsys.readouterr().err
