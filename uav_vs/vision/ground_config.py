"""Ground trinocular configuration: cameras and landmark layout (chapter section 3).

The parameters live in a ROS 2 params file (`config/ground_trinocular.yaml`) whose
flat keys a node can declare:

    cameras.names                      [cam1, cam2, ...]
    cameras.<name>.{width, height, frame_id, K, D, R, t}   (see Camera.from_params)
    cameras.<name>.latency             s its stamps come after the instant (optional, 0)
    landmarks.names                    [red, green, ...]    order = landmark index
    landmarks.radius                   sphere radius, m (optional, default 0.1)
    landmarks.<name>.position          [x, y, z] in base_link (FLU), m
    landmarks.<name>.hue               [lo, hi] OpenCV hue 0..180, lo > hi wraps through 0
    landmarks.<name>.saturation        [lo, hi] 0..255
    landmarks.<name>.value             [lo, hi] 0..255

`read_params_file` turns the YAML into that flat dict (`read_params_files` layers several,
as config/landmarks_uav2.yaml over config/ground_trinocular.yaml), `load_ground_config`
checks it.
"""
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import yaml

from uav_vs.vision.camera import CalibrationError, Camera, finite_numbers

_RANGES = {'hue': 180, 'saturation': 255, 'value': 255}


@dataclass(frozen=True)
class GroundConfig:
    """Cameras (eq 15-16) and the landmarks' body-frame layout and colours (eq 18, 26)."""

    cameras: list[Camera]
    landmark_names: list[str]
    layout: np.ndarray       # (n, 3) landmark centres in base_link FLU, m
    hue: np.ndarray          # (n, 2) int, OpenCV hue 0..180, lo > hi wraps through 0
    saturation: np.ndarray   # (n, 2) int, 0..255
    value: np.ndarray        # (n, 2) int, 0..255
    radius: float = 0.1      # landmark sphere radius, m
    latency: tuple[float, ...] = ()   # per camera: s its stamps come late (empty: none)

    def latency_ns(self, k: int) -> int:
        """Camera k's latency, ns (0 when none is set)."""
        return int(round(self.latency[k] * 1e9)) if self.latency else 0


def default_config_path(name: str = 'ground_trinocular.yaml') -> Path:
    """`config/<name>` of the source tree, else of the installed package's share folder."""
    source = Path(__file__).resolve().parents[2] / 'config' / name
    return source if source.exists() else Path(sys.prefix) / 'share' / 'uav_vs' / 'config' / name


def read_params_file(path: str | Path, node: str = '/**') -> dict[str, object]:
    """Flat `{dotted.key: value}` of a ROS 2 params file's `/**` section (and `node`'s)."""
    doc = yaml.safe_load(Path(path).read_text()) or {}
    flat: dict[str, object] = {}
    for section in dict.fromkeys(['/**', node]):
        flat |= flat_params((doc.get(section) or {}).get('ros__parameters') or {})
    return flat


def read_params_files(paths: Sequence[str | Path], node: str = '/**') -> dict[str, object]:
    """The flat parameters of several params files, a later file's keys replacing an
    earlier one's, as a node given several `--params-file` takes them."""
    flat: dict[str, object] = {}
    for path in paths:
        flat |= read_params_file(path, node)
    return flat


def load_ground_config(params: Mapping[str, object]) -> GroundConfig:
    """Build the cameras and landmark layout from flat parameters.

    Raises CalibrationError with one line naming the first bad parameter.
    """
    cam_names = _names(params, 'cameras.names', minimum=2)
    cameras = [Camera.from_params(n, _sub(params, f'cameras.{n}.'), f'cameras.{n}.')
               for n in cam_names]
    names = _names(params, 'landmarks.names', minimum=2)
    layout = np.array([_floats(params, f'landmarks.{n}.position', 3) for n in names])
    ranges = {kind: np.array([_range(params, f'landmarks.{n}.{kind}', top) for n in names])
              for kind, top in _RANGES.items()}
    radius = params.get('landmarks.radius', 0.1)
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not radius > 0:
        raise CalibrationError(f'landmarks.radius: expected a positive number, got {radius!r}')
    latency = tuple(_latency(params, f'cameras.{n}.latency') for n in cam_names)
    return GroundConfig(cameras, names, layout, radius=float(radius), latency=latency, **ranges)


def _latency(params: Mapping[str, object], key: str) -> float:
    value = params.get(key, 0.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not abs(value) <= 1.0:
        raise CalibrationError(f'{key}: expected a number of seconds in [-1, 1], got {value!r}')
    return float(value)


def flat_params(tree: Mapping, prefix: str = '') -> dict[str, object]:
    """`{dotted.key: value}` of a nested parameter tree, keys prefixed with `prefix`."""
    out: dict[str, object] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            out |= flat_params(value, f'{prefix}{key}.')
        else:
            out[f'{prefix}{key}'] = value
    return out


def _sub(params: Mapping[str, object], prefix: str) -> dict[str, object]:
    return {k[len(prefix):]: v for k, v in params.items() if k.startswith(prefix)}


def _names(params: Mapping[str, object], key: str, minimum: int) -> list[str]:
    value = params.get(key)
    if (not isinstance(value, (list, tuple)) or len(value) < minimum
            or not all(isinstance(v, str) and v for v in value) or len(set(value)) != len(value)):
        raise CalibrationError(f'{key}: expected a list of at least {minimum} distinct names, '
                               f'got {value!r}')
    return list(value)


def _floats(params: Mapping[str, object], key: str, n: int) -> np.ndarray:
    value = params.get(key)
    if value is None:
        raise CalibrationError(f'{key}: missing')
    return finite_numbers(value, n, key)


def _range(params: Mapping[str, object], key: str, top: int) -> list[int]:
    value = params.get(key)
    if value is None:
        raise CalibrationError(f'{key}: missing')
    wraps = key.endswith('.hue')
    arr = np.asarray(value) if isinstance(value, Sequence) or hasattr(value, '__array__') \
        else np.empty(0)
    if (arr.shape != (2,) or arr.dtype.kind not in 'iu' or arr.min() < 0 or arr.max() > top
            or (not wraps and arr[0] > arr[1])):
        order = '' if wraps else ' with lo <= hi'
        raise CalibrationError(f'{key}: expected [lo, hi], integers in 0..{top}{order}, '
                               f'got {value!r}')
    return arr.tolist()
