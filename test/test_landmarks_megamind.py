"""CamShift landmark tracking on a real video (OpenCV's Megamind.avi, no ground truth):
four regions of the first shot tracked as landmarks (chapter section 3.1, eq 18-19),
against the OpenCV-sample way (full-frame backprojection + cv2.CamShift per landmark)."""
import numpy as np

from bench.ground_detection import MEGAMIND_REGIONS, compare, megamind_frames, megamind_pair


def test_tracks_stay_stable_and_agree_with_full_frame_camshift(shared_data):
    frames = megamind_frames(shared_data / 'opencv' / 'Megamind.avi')
    ours, ref = megamind_pair(frames[0])
    _, _, xy, ref_xy = compare(frames, ours, ref)
    assert np.isfinite(xy).all(), 'a landmark was lost'
    # same answer as backprojecting the whole frame: restricting the work to the
    # search regions changes nothing but the last few pixels of CamShift's window
    dist = np.linalg.norm(xy - ref_xy, axis=-1)
    assert (np.median(dist, axis=0) < 4).all(), np.median(dist, axis=0)
    assert (dist.max(axis=0) < 10).all(), dist.max(axis=0)
    # stable: the shot moves slowly, so no centroid jumps between frames
    jumps = np.linalg.norm(np.diff(xy, axis=0), axis=-1)
    assert (jumps.max(axis=0) < 6).all(), jumps.max(axis=0)
    # and each track stays on the region it started on
    start = np.array([(x + w / 2, y + h / 2) for x, y, w, h in MEGAMIND_REGIONS.values()])
    sizes = np.array([max(w, h) for _, _, w, h in MEGAMIND_REGIONS.values()])
    assert (np.linalg.norm(xy - start, axis=-1).max(axis=0) < sizes).all()
