"""The latency of each camera of a rig that is not triggered together (the frame sets of
chapter section 3.1.1), measured while calibrating it (uav_vs.vision.rig_calibration).

Cameras that are not hardware-triggered stamp a frame when the host receives it, each
after a latency of its own: USB webcams differ by tens of milliseconds. Frames matched
by their stamps then show a moving board at different instants, and a board moving
50 px/s in the image is 1.5 px away 30 ms later: more than the corners' own error, and
enough to bend the rig's solution. Given each camera's detections by stamp (a track),
`resample` takes its board at any instant, each point linearly interpolated between
the two detections around it, and gives the point's image velocity there;
`calibrate_timed_rig` solves the rig with a time shift per camera (the velocity times
the shift added to its points) and resamples every camera at its shifted instants
again, until the shifts settle: each camera's latency after the first's.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from uav_vs.vision.calibration import (MIN_POINTS, Board, CalibrationInputError, Detection,
                                       Intrinsics)
from uav_vs.vision.rig_calibration import Rig, calibrate_rig


def resample(track: dict[float, Detection], at: dict[str, float], max_gap: float
             ) -> tuple[dict[str, Detection], dict[str, np.ndarray]]:
    """The board of `track` (detections by stamp, s) at each view's instant `at[view]`:
    each point linearly interpolated between the two consecutive detections around that
    instant that both hold it and lie at most `max_gap` apart, and its velocity there
    (px/s). A view with fewer than MIN_POINTS such points is left out."""
    stamps = np.array(sorted(track))
    views, rates = {}, {}
    for view, when in at.items():
        # an instant on a stamp lies in the gaps on both sides of it: the first that serves
        for k in dict.fromkeys((int(np.searchsorted(stamps, when, side=side))
                                for side in ('right', 'left'))):
            found = _between(track, stamps, k, when, max_gap)
            if found is not None:
                views[view], rates[view] = found
                break
    return views, rates


def _between(track: dict[float, Detection], stamps: np.ndarray, k: int, when: float,
             max_gap: float) -> tuple[Detection, np.ndarray] | None:
    """The board at `when` between the detections at stamps[k - 1] and stamps[k]."""
    if k == 0 or k == len(stamps) or stamps[k] - stamps[k - 1] > max_gap:
        return None
    t0, t1 = stamps[k - 1], stamps[k]
    a, b = track[t0], track[t1]
    ids, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(ids) < MIN_POINTS:
        return None
    p0 = a.points.reshape(-1, 2)[ia].astype(np.float64)
    p1 = b.points.reshape(-1, 2)[ib].astype(np.float64)
    rate = (p1 - p0) / (t1 - t0)
    return Detection(ids.astype(np.int32), p0 + rate * (when - t0),
                     min(a.sharpness, b.sharpness)), rate


def calibrate_timed_rig(board: Board, tracks: dict[str, dict[float, Detection]],
                        at: dict[str, float], intrinsics: dict[str, Intrinsics],
                        ground_view: str, max_gap: float, refine_intrinsics: bool = False,
                        iterations: int = 20, tolerance: float = 1e-4) -> Rig:
    """The rig (rig_calibration.calibrate_rig) and each camera's latency after the first
    camera's (`Rig.latency`, s): the views are the instants `at` (view -> s, on the first
    camera's clock), each camera's board resampled at the instant plus its latency, the
    latencies re-estimated until none moves more than `tolerance` (s)."""
    names = list(tracks)
    latency = dict.fromkeys(names, 0.0)
    for _ in range(iterations):
        views, motion = {}, {}
        for c in names:
            shifted = {v: when + latency[c] for v, when in at.items()}
            views[c], motion[c] = resample(tracks[c], shifted, max_gap)
        rig = calibrate_rig(board, views, intrinsics, ground_view, refine_intrinsics, motion)
        step = rig.latency
        for c in names:
            latency[c] += step[c]
        if max(abs(s) for s in step.values()) < tolerance:
            break
    else:
        raise CalibrationInputError(f'the cameras\' latencies did not settle in {iterations} '
                                    f'iterations: is the board moving smoothly?')
    return replace(rig, latency=latency)


def set_instants(sync: dict[tuple[str, int], int], stamps: dict[tuple[str, int], float],
                 reference: str) -> dict[str, float]:
    """Each frame set's instant on the `reference` camera's clock: its frame's stamp, or
    the median of the set's stamps where it has none (sync: (camera, frame) -> set,
    stamps: (camera, frame) -> s)."""
    by_set: dict[int, list[float]] = {}
    own: dict[int, float] = {}
    for key, index in sync.items():
        if key in stamps:
            by_set.setdefault(index, []).append(stamps[key])
            if key[0] == reference:
                own[index] = stamps[key]
    return {str(k): own.get(k, float(np.median(v))) for k, v in by_set.items()}


def frame_gap(stamps: dict[tuple[str, int], float]) -> float:
    """The longest gap to interpolate across: 1.5 frame intervals (the median interval
    between a camera's consecutive frames, over every camera)."""
    by_camera: dict[str, list[float]] = {}
    for (camera, _), when in stamps.items():
        by_camera.setdefault(camera, []).append(when)
    steps = np.concatenate([np.diff(sorted(v)) for v in by_camera.values()])
    if not len(steps) or np.median(steps) <= 0:
        raise CalibrationInputError('frame stamps: expected two frames or more per camera, '
                                    'in increasing time')
    return 1.5 * float(np.median(steps))


def timed_views(tracks: dict[str, dict[float, Detection]], at: dict[str, float],
                latency: dict[str, float], max_gap: float) -> dict[str, dict[str, Detection]]:
    """Every camera's board at the instants `at`, its latency allowed for (the views a
    timed rig triangulates, e.g. with rig_calibration.neighbour_errors)."""
    return {c: resample(track, {v: when + latency[c] for v, when in at.items()}, max_gap)[0]
            for c, track in tracks.items()}
