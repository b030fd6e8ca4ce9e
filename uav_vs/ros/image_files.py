"""Image files named by parameters (a target template, a landmark sample), found where a
ROS user expects: a relative path from the working directory first, then in the
installed share/uav_vs/config, then beside the uav_vs package and in its sim/assets, so
the YAMLs' `uav_vs/sim/assets/...` paths work wherever `ros2 run` starts a node."""
from pathlib import Path

import cv2
import numpy as np

import uav_vs
from uav_vs.install_prefixes import install_prefixes
from uav_vs.ros.params import ParameterError


def candidates(path: str) -> list[Path]:
    """Where `path` is looked for, in order (an absolute path: only itself)."""
    given = Path(path)
    if given.is_absolute():
        return [given]
    shares = [prefix / 'share' / 'uav_vs' / 'config' for prefix in install_prefixes()]
    package = Path(uav_vs.__file__).resolve().parent
    bases = [Path.cwd(), *shares, package.parent, package / 'sim' / 'assets']
    return list(dict.fromkeys(base / given for base in bases))


def read_image(param: str, path: str, flags: int) -> tuple[np.ndarray, Path]:
    """The image (cv2.imread flags) and its file; ParameterError naming `param` when no
    candidate file exists or the first one found is not an image."""
    tried = candidates(path)
    found = next((c for c in tried if c.is_file()), None)
    if found is None:
        raise ParameterError(f'{param}: cannot read an image from {path!r} (no such file: '
                             f"{', '.join(map(str, tried))})")
    image = cv2.imread(str(found), flags)
    if image is None:
        raise ParameterError(f'{param}: cannot read an image from {str(found)!r}')
    return image, found
