"""The simulated world's camera effects per 640x480 frame (uav_vs.sim.camera_effects).

Each effect is timed next to the onboard render it degrades (OnboardScene.render of
the same frame, no noise), so its cost reads as a share of the frame's.
"""
import numpy as np

from bench.common import report, timeit
from uav_vs.sim.camera_effects import (CameraEffects, EffectsConfig, Exposure, GaussianNoise,
                                       LensDistortion, jpeg_roundtrip, motion_blur)
from uav_vs.sim.onboard_scene import OnboardScene
from uav_vs.vision.ground_config import default_config_path, read_params_file
from uav_vs.vision.onboard_config import load_onboard_config

R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
P = np.array([0.3, -0.2, 1.5])


def main() -> None:
    cfg = load_onboard_config(read_params_file(default_config_path('onboard.yaml')))
    scene = OnboardScene(cfg.camera, cfg.camera_to_body, noise_sigma=0.0)
    frame = scene.render(R, P)
    ref = timeit(lambda: scene.render(R, P), 50)
    rng = np.random.default_rng(0)
    noise, exposure = GaussianNoise(2.0, frame.shape[:2], rng), Exposure(0.1, 5.0, 5.0, rng)
    lens = LensDistortion(cfg.camera)
    cases = {
        'noise_sigma2': lambda: noise(frame),
        'jpeg_q50': lambda: jpeg_roundtrip(frame, 50),
        'motion_blur_12px_horizontal': lambda: motion_blur(frame, np.array([1200.0, 0.0]), 0.01),
        'motion_blur_13px_oblique': lambda: motion_blur(frame, np.array([1200.0, 500.0]), 0.01),
        'motion_blur_32px_oblique': lambda: motion_blur(frame, np.array([3000.0, 1000.0]), 0.01),
        'exposure': lambda: exposure(frame),
        'lens_distortion_remap': lambda: lens(frame),
    }
    every = CameraEffects(EffectsConfig(2.0, 50, 0.01, 0.1, 5.0), frame.shape[:2],
                          np.random.SeedSequence(0))
    cases['all_image_effects_13px'] = lambda: every(frame, np.array([1200.0, 500.0]), 0.1)
    for name, fn in cases.items():
        report('sim', f'sim/effect_{name}_640x480', timeit(fn, 100),
               reference='onboard render', ref_ms=ref)


if __name__ == '__main__':
    main()
