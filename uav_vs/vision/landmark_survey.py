"""Survey of the vehicle's landmarks with the calibrated ground cameras (chapter section 3.1).

The pose of eq 26 needs each landmark's position in the vehicle's body frame, and the
detector of eq 18-19 works best from a sample of each landmark's colour as the cameras
see it. Both are measured here, with the vehicle standing still where the rig sees it:

1. every camera's frames go through the landmark detector (`LandmarkDetector`, the
   configured colour ranges); a landmark's centroid in a camera is the median over the
   frames that found it, kept when at least half of them did;
2. the landmarks are triangulated (eq 24-25) from every camera that kept them; a
   landmark the cameras disagree on (reprojection RMS over `max_reproj_px`, after
   leaving out each camera in turn) is refused;
3. the world positions are brought into base_link (FLU) by the vehicle's placement, which
   the user defines: its body origin in the world frame (ENU, m) and its heading (the
   body x axis, rad counter-clockwise from east), standing level;
4. each landmark's sample is cut from the camera that sees it at the median size among
   the cameras: its final CamShift window of the last frame that found it, the ellipse
   inscribed in the window (less its anti-aliased rim) opaque, the corners transparent,
   as `ColourModel.from_patch` reads it.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields

import cv2
import numpy as np
import yaml

from uav_vs.vision.camera import Camera
from uav_vs.vision.colour_model import ColourModel
from uav_vs.vision.landmarks import DetectorParams, LandmarkDetector, Rect
from uav_vs.vision.triangulation import triangulate


class SurveyError(ValueError):
    """The frames cannot give a landmark's position: one line naming it and why."""


@dataclass(frozen=True)
class Placement:
    """Where the vehicle stands: base_link's origin in world ENU (m) and its heading."""

    origin: np.ndarray       # (3,) m
    yaw: float               # rad, body x from world x (east), counter-clockwise

    def to_body(self, world: np.ndarray) -> np.ndarray:
        """(n, 3) world points in base_link: R_z(yaw)^T (p - origin)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return (np.asarray(world, float) - self.origin) @ Rz


@dataclass(frozen=True)
class Sighting:
    """One landmark in one camera over the survey's frames."""

    centroid: np.ndarray     # (2,) median pixel centroid (eq 19), NaN when not kept
    found: int               # frames that found it
    spread_px: float         # median distance of the frames' centroids from the median
    window: Rect | None      # the final window of the last frame that found it
    patch: np.ndarray | None  # that window of that frame, BGR


@dataclass(frozen=True)
class Survey:
    """The landmarks' positions and colour samples."""

    names: list[str]
    cameras: list[str]
    frames: list[int]                # frames per camera
    sightings: list[list[Sighting]]  # [camera][landmark]
    world: np.ndarray                # (n, 3) m, world ENU
    body: np.ndarray                 # (n, 3) m, base_link FLU
    reproj_px: np.ndarray            # (n,) RMS reprojection error of the triangulation
    n_views: np.ndarray              # (n,) cameras used
    samples: dict[str, np.ndarray]   # name -> BGRA sample
    sample_camera: dict[str, str]    # name -> the camera it was cut from

    def report(self) -> list[str]:
        lines = ['landmarks surveyed from ' + ', '.join(
            f'{c} ({n} frames)' for c, n in zip(self.cameras, self.frames))]
        for i, name in enumerate(self.names):
            seen = ', '.join(
                f'{c} {s[i].found}/{n} frames, spread {s[i].spread_px:.2f} px'
                for c, n, s in zip(self.cameras, self.frames, self.sightings))
            x, y, z = self.body[i]
            wx, wy, wz = self.world[i]
            lines += [f'{name}: base_link ({x:+.4f}, {y:+.4f}, {z:+.4f}) m, world ({wx:+.4f}, '
                      f'{wy:+.4f}, {wz:+.4f}) m, {self.n_views[i]} cameras, reprojection RMS '
                      f'{self.reproj_px[i]:.2f} px',
                      f'  {seen}',
                      f'  sample {self.samples[name].shape[1]}x{self.samples[name].shape[0]} px '
                      f'from {self.sample_camera[name]}']
        return lines

    def landmarks_yaml(self, params: Mapping[str, object], sample_paths: Mapping[str, str]
                       ) -> str:
        """The `landmarks` block of config/ground_trinocular.yaml, as YAML."""
        return yaml.safe_dump({'landmarks': self.landmarks_block(params, sample_paths)},
                              sort_keys=False, width=100)

    def landmarks_block(self, params: Mapping[str, object], sample_paths: Mapping[str, str]
                        ) -> dict:
        """The `landmarks` block of config/ground_trinocular.yaml: the surveyed positions and
        samples, with the colour ranges, radius and areas of `params` (flat, as read)."""
        block: dict = {'names': list(self.names)}
        if 'landmarks.radius' in params:
            block['radius'] = float(params['landmarks.radius'])
        for i, name in enumerate(self.names):
            entry: dict = {'position': [round(float(v), 4) for v in self.body[i]]}
            for key in ('hue', 'saturation', 'value', 'area_px'):
                if f'landmarks.{name}.{key}' in params:
                    entry[key] = params[f'landmarks.{name}.{key}']
            entry['sample'] = str(sample_paths[name])
            block[name] = entry
        return block


def detector_params(params: Mapping[str, object]) -> DetectorParams:
    """The detector's settings of a ground config's `camshift` block (flat), the node's
    own (image_qos, ...) left out."""
    keys = {f'camshift.{f.name}' for f in fields(DetectorParams)}
    return DetectorParams.from_params({k: v for k, v in params.items() if k in keys})


def sight(models: Sequence[ColourModel], params: DetectorParams,
          frames: Sequence[np.ndarray]) -> list[Sighting]:
    """Each landmark's sighting in one camera's frames of the still vehicle (steps 1, 4)."""
    detector = LandmarkDetector(models, params)
    tracks: list[list[tuple[float, float]]] = [[] for _ in models]
    last: list[tuple[Rect, np.ndarray] | None] = [None] * len(models)
    for frame in frames:
        for i, det in enumerate(detector.detect(frame)):
            if det.found:
                tracks[i].append(det.centroid)
                last[i] = det.window, frame
    out = []
    for track, seen in zip(tracks, last):
        kept = len(track) >= max(1, (len(frames) + 1) // 2)
        if not kept:
            out.append(Sighting(np.full(2, np.nan), len(track), math.nan, None, None))
            continue
        points = np.array(track)
        centre = np.median(points, axis=0)
        spread = float(np.median(np.linalg.norm(points - centre, axis=1)))
        (x, y, w, h), frame = seen
        out.append(Sighting(centre, len(track), spread, (x, y, w, h),
                            frame[y:y + h, x:x + w].copy()))
    return out


def cut_sample(patch: np.ndarray) -> np.ndarray:
    """BGRA sample from a window's pixels: opaque inside the landmark's disc, which the
    window holds with 1-2 px to spare on each side (`landmarks._box_window`), less half a
    pixel of anti-aliased rim; transparent outside."""
    h, w = patch.shape[:2]
    alpha = np.zeros((h, w), np.uint8)
    # in half pixels (shift=1): centre of the window, semi-axes (w - 4) / 2 px
    cv2.ellipse(alpha, (w - 1, h - 1), (max(w - 4, 1), max(h - 4, 1)), 0.0, 0.0, 360.0, 255,
                -1, cv2.LINE_8, 1)
    return np.dstack([patch, alpha])


def survey(cameras: Sequence[Camera], models: Sequence[ColourModel], params: DetectorParams,
           frames: Sequence[Sequence[np.ndarray]], placement: Placement,
           max_reproj_px: float = 2.0) -> Survey:
    """Steps 1-4 over `frames[k]`, camera k's frames of the vehicle standing still."""
    if len(frames) != len(cameras):
        raise SurveyError(f'frames of {len(frames)} cameras for {len(cameras)} cameras')
    for cam, shots in zip(cameras, frames):
        if not shots:
            raise SurveyError(f'{cam.name}: no frames')
        for frame in shots:
            if frame.shape[:2] != (cam.height, cam.width):
                raise SurveyError(f'{cam.name}: a frame of {frame.shape[1]}x{frame.shape[0]}, '
                                  f'the camera is {cam.width}x{cam.height}')
    names = [m.name for m in models]
    sightings = [sight(models, params, shots) for shots in frames]
    pixels = np.array([[s.centroid for s in row] for row in sightings])
    result = triangulate(cameras, pixels, 'lsq', max_reproj_px)
    for i, name in enumerate(names):
        if result.n_views[i] < 2:
            seen = [c.name for c, row in zip(cameras, sightings) if row[i].window is not None]
            raise SurveyError(f'{name}: found by {len(seen)} camera(s) ({", ".join(seen) or "none"}'
                              f'), two are needed: check its colour ranges and that the '
                              f'cameras see it')
        if not result.inlier[i]:
            raise SurveyError(f'{name}: the cameras disagree on where it is (reprojection RMS '
                              f'{result.reproj_px[i]:.1f} px > {max_reproj_px} px): another '
                              f'object of its colour in view, or a camera off its calibration?')
    samples, sample_camera = {}, {}
    for i, name in enumerate(names):
        seen = [(row[i].window[2] * row[i].window[3], k) for k, row in enumerate(sightings)
                if row[i].window is not None]
        seen.sort()
        k = seen[(len(seen) - 1) // 2][1]
        samples[name] = cut_sample(sightings[k][i].patch)
        sample_camera[name] = cameras[k].name
    return Survey(names, [c.name for c in cameras], [len(f) for f in frames], sightings,
                  result.points, placement.to_body(result.points), result.reproj_px,
                  result.n_views, samples, sample_camera)
