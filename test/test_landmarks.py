"""Colour landmarks (chapter section 3.1, eq 18-19) on synthetic frames with known truth:
anti-aliased, shaded discs at sub-pixel centres over a real aerial photo, with noise."""
import cv2
import numpy as np
import pytest

from bench.ground_detection import (ASSETS, COLOURS, SIZE, background, colour_models,
                                    disc_path, render_discs, synthetic_frames)
from uav_vs.sim.ground_scene import GroundScene, figure_eight
from uav_vs.vision.colour_model import ColourModel, models_from_params, ratio_histograms
from uav_vs.vision.ground_config import default_config_path, load_ground_config, read_params_file
from uav_vs.vision.landmarks import DetectorParams, LandmarkDetector, centroids

BGR = [c[0] for c in COLOURS.values()]


def test_ratio_histogram_is_eq18_on_a_hand_built_case():
    M = np.array([[[4, 0, 3], [2, 6, 0]]], np.float32)
    I = np.array([[2, 5, 0], [0, 12, 0]], np.float32)
    expected = [[[1, 0, 1], [1, 0.5, 0]]]   # min(M/I, 1); M = 0 gives 0 even where I = 0
    np.testing.assert_array_equal(ratio_histograms(M, I), expected)


def test_range_model_weights_each_bin_by_its_share_of_the_ranges():
    m = ColourModel.from_ranges('red', hue=(170, 8), saturation=(120, 255), bins=(30, 32),
                                area_px=100)
    hue = np.zeros(30)
    hue[[28, 29, 0, 1]] = [4 / 6, 1, 1, 3 / 6]   # 170..173 of 168..173, ..., 6..8 of 6..11
    sat = np.zeros(32)
    sat[15:] = 1                                  # 120..255 = bins 15..31 exactly
    np.testing.assert_allclose(m.hist, 100 * np.outer(hue, sat), rtol=1e-6)


def test_detector_ratio_histogram_uses_this_frames_pixel_counts():
    """Independent count of the frame's H-S bins with numpy, then eq 18."""
    frame, _ = next(synthetic_frames(1))
    params = DetectorParams(histogram_smoothing=0, downscale=1)
    models = [ColourModel.from_ranges('red', (170, 8), (120, 255), bins=params.bins),
              ColourModel.from_patch('patch', frame[100:140, 100:140], bins=params.bins)]
    det = LandmarkDetector(models, params)
    det.detect(frame)
    hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV).reshape(-1, 3).astype(int)
    I = np.zeros(params.bins)
    np.add.at(I, (hsv[:, 0] * 30 // 180, hsv[:, 1] * 32 // 256), 1)
    for k, m in enumerate(models):
        with np.errstate(divide='ignore', invalid='ignore'):
            expected = np.where(m.hist > 0, np.minimum(m.hist / I, 1), 0)
        np.testing.assert_allclose(det.ratio_hists[k], expected, atol=1e-6)


def test_centroids_follow_moving_discs_to_subpixel():
    """120 frames, up to 8 px/frame, noise sigma 3: every landmark found on every frame;
    eq 19's centroid within 0.5 px of the true centre, bias under 0.1 px."""
    det = LandmarkDetector(colour_models())
    err = []
    for frame, truth in synthetic_frames(120, radius=10):
        xy, conf = centroids(det.detect(frame))
        assert np.all(np.isfinite(xy)) and np.all(conf > 0.5)
        err.append(xy - truth)
    err = np.array(err)
    assert np.abs(err).max() < 0.5
    assert np.abs(err.mean(axis=0)).max() < 0.1


def test_backprojection_only_inside_the_search_regions(monkeypatch):
    """Once tracking, each landmark is backprojected only over its window plus margin:
    the pixels computed are counted by wrapping cv2.calcBackProject."""
    frames = list(synthetic_frames(20, radius=10))
    params = DetectorParams()
    det = LandmarkDetector(colour_models(params.bins), params)
    for frame, _ in frames[:5]:
        det.detect(frame)
    sizes = []
    real = cv2.calcBackProject

    def counting(images, *args):
        sizes.append(images[0].shape[:2])
        return real(images, *args)

    monkeypatch.setattr(cv2, 'calcBackProject', counting)
    for frame, truth in frames[5:]:
        sizes.clear()
        previous = list(det.windows)
        det.detect(frame)
        assert len(sizes) == 4
        for (x, y, w, h), region, shape, c in zip(previous, det.search_regions, sizes, truth):
            m = max(int(params.search_margin * max(w, h)), params.min_search_margin_px)
            x0, y0 = max(x - m, 0), max(y - m, 0)
            assert region == (x0, y0, min(x + w + m, SIZE[0]) - x0, min(y + h + m, SIZE[1]) - y0)
            assert shape == region[:1:-1]
            assert x0 <= c[0] < x0 + region[2] and y0 <= c[1] < y0 + region[3]
        assert sum(h * w for h, w in sizes) < 0.05 * SIZE[0] * SIZE[1]


def test_hidden_landmark_is_lost_then_reacquired_where_it_reappears():
    """Red is hidden for frames 20-39 (the others stay), then reappears at the image
    centre, far from where it vanished: lost while hidden, found again within 2 frames."""
    rng = np.random.default_rng(3)
    bg = background()
    path = disc_path(70)
    det = LandmarkDetector(colour_models())
    for k in range(70):
        centres = path[k].copy()
        if k >= 40:
            centres[0] = (320.3 + 0.5 * (k - 40), 240.6)
        frame = render_discs(bg, centres, BGR, 10, rng, visible=[not 20 <= k < 40] + [True] * 3)
        xy, _ = centroids(det.detect(frame))
        found = np.isfinite(xy[:, 0])
        assert found[1:].all()
        if k < 20 or k >= 42:
            assert found[0] and np.hypot(*(xy[0] - centres[0])) < 0.5, k
        elif k < 40:
            assert not found[0], k


def test_absent_colours_are_never_found_on_real_backgrounds():
    """Models of colours not in the scene (magenta, cyan, orange, wide enough, S >= 80,
    that a few background pixels match them) over two aerial photos with the four
    discs present: never found; the present ones always are."""
    params = DetectorParams()
    absent = [ColourModel.from_ranges('magenta', (140, 165), (80, 255), (60, 255)),
              ColourModel.from_ranges('cyan', (82, 95), (80, 255), (60, 255)),
              ColourModel.from_ranges('orange', (9, 18), (80, 255), (60, 255))]
    rng = np.random.default_rng(5)
    path = disc_path(40)
    for photo in ('aero1.jpg', 'aero3.jpg'):
        bg = cv2.resize(cv2.imread(str(ASSETS / photo)), SIZE, interpolation=cv2.INTER_AREA)
        det = LandmarkDetector(colour_models() + absent, params)
        for centres in path:
            xy, _ = centroids(det.detect(render_discs(bg, centres, BGR, 10, rng)))
            assert np.isfinite(xy[:4]).all() and np.isnan(xy[4:]).all(), photo


def test_sample_patches_model_the_landmarks_as_well_as_ranges():
    """Each landmark cut 13x13 px from one simulator frame of cam1 is its colour model (no
    hue or saturation given): on the next 4 s at 10 Hz, in all three cameras, every
    unoccluded landmark is found within 1.5 px of its true centroid (median < 0.5 px)."""
    flat = read_params_file(default_config_path())
    scene = GroundScene(load_ground_config(flat), seed=1)
    names = flat['landmarks.names']
    images, info = scene.render(figure_eight(0.0))
    samples = {}
    for i, name in enumerate(names):
        u, v = np.round(info.full_centroid[0, i]).astype(int)
        samples[name] = images[0][v - 6:v + 7, u - 6:u + 7]
        del flat[f'landmarks.{name}.hue'], flat[f'landmarks.{name}.saturation']
    models = models_from_params(flat, samples=samples)
    detectors = [LandmarkDetector(models) for _ in range(3)]
    errors = []
    for t in np.arange(0.1, 4.0, 0.1):
        images, info = scene.render(figure_eight(t))
        for k, img in enumerate(images):
            xy, _ = centroids(detectors[k].detect(img))
            seen = info.visible[k] > 0.99
            assert not np.isnan(xy[seen]).any(), (t, k)
            errors += list(np.linalg.norm(xy[seen] - info.centroid[k, seen], axis=1))
    assert len(errors) > 300 and np.median(errors) < 0.5 and max(errors) < 1.5


def test_sample_alpha_leaves_the_transparent_pixels_out():
    """A BGRA sample counts only its opaque pixels whose value is in range."""
    bgr = np.zeros((20, 20, 3), np.uint8)
    bgr[:] = (40, 200, 40)                         # green background
    cv2.circle(bgr, (10, 10), 6, (0, 0, 255), -1)  # red disc
    alpha = np.zeros((20, 20), np.uint8)
    cv2.circle(alpha, (10, 10), 6, 255, -1)
    model = ColourModel.from_patch('red', np.dstack([bgr, alpha]), value=(50, 255))
    assert model.hist.sum() == cv2.countNonZero(alpha)
    hsv = cv2.cvtColor(bgr[:1, :1], cv2.COLOR_BGR2HSV)[0, 0].astype(int)
    assert model.hist[hsv[0] * 30 // 180, hsv[1] * 32 // 256] == 0    # background left out
    assert model.hist[0, 31] == cv2.countNonZero(alpha)                # red: hue 0, sat 255
    with pytest.raises(ValueError, match='landmarks.red.sample: expected an 8-bit colour'):
        ColourModel.from_patch('red', alpha)


def test_params_from_flat_ros_style_dict():
    p = DetectorParams.from_params({'camshift.hue_bins': 18, 'camshift.min_confidence': 0.3,
                                    'camshift.epsilon_px': 1, 'other.key': 'ignored'})
    assert (p.hue_bins, p.saturation_bins, p.min_confidence, p.epsilon_px) == (18, 32, 0.3, 1.0)
    models = models_from_params({
        'landmarks.names': ['red', 'blue'],
        'landmarks.red.hue': [170, 8], 'landmarks.red.saturation': [120, 255],
        'landmarks.red.value': [60, 255],
        'landmarks.blue.hue': [100, 125], 'landmarks.blue.saturation': [120, 255],
        'landmarks.blue.area_px': 900}, p.bins)
    assert [m.name for m in models] == ['red', 'blue']
    assert models[0].value == (60, 255) and models[1].value == (0, 255)
    assert models[1].hist.max() == pytest.approx(900) and models[1].hist.shape == (18, 32)


LANDMARKS = {'landmarks.names': ['red'], 'landmarks.red.hue': [170, 8],
             'landmarks.red.saturation': [120, 255]}


@pytest.mark.parametrize('key, value', [
    ('camshift.hue_bins', 0), ('camshift.hue_bins', 2.5), ('camshift.hue_bins', 'many'),
    ('camshift.saturation_bins', 300), ('camshift.min_confidence', 1.5),
    ('camshift.histogram_smoothing', -0.1), ('camshift.downscale', True),
    ('camshift.epsilon_px', float('nan')), ('camshift.reacquire_interval', 0),
    ('camshift.search_margins', 0.5),
])
def test_malformed_detector_params_name_the_parameter(key, value):
    with pytest.raises(ValueError) as e:
        DetectorParams.from_params({key: value})
    assert str(e.value).startswith(key + ':') and '\n' not in str(e.value)


@pytest.mark.parametrize('key, value', [
    ('landmarks.names', []), ('landmarks.names', 'red'), ('landmarks.names', ['red', 'red']),
    ('landmarks.red.hue', [10]), ('landmarks.red.hue', [10, 200]), ('landmarks.red.hue', 'red'),
    ('landmarks.red.saturation', [200, 100]), ('landmarks.red.value', [0, 256]),
    ('landmarks.red.area_px', -5), ('landmarks.red.area_px', 'big'),
])
def test_malformed_landmark_params_name_the_parameter(key, value):
    with pytest.raises(ValueError) as e:
        models_from_params({**LANDMARKS, key: value})
    assert str(e.value).startswith(key + ':') and '\n' not in str(e.value)


@pytest.mark.parametrize('missing', ['landmarks.names', 'landmarks.red.hue',
                                     'landmarks.red.saturation'])
def test_missing_landmark_params_name_the_parameter(missing):
    params = {k: v for k, v in LANDMARKS.items() if k != missing}
    with pytest.raises(ValueError, match=f'^{missing}:'):
        models_from_params(params)


def test_draw_marks_found_landmarks_and_leaves_the_input_alone():
    frame, truth = next(synthetic_frames(1))
    original = frame.copy()
    det = LandmarkDetector(colour_models())
    dets = det.detect(frame)
    img = det.draw(frame, dets)
    np.testing.assert_array_equal(frame, original)
    for d in dets:
        x, y, w, h = d.window
        assert (img[y, x:x + w] != frame[y, x:x + w]).any()
