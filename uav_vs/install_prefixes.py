"""The install prefixes a package's shared files are looked for under, in order: those
of AMENT_PREFIX_PATH (a sourced ROS workspace), then this Python's own (the venv)."""
import os
import sys
from pathlib import Path


def install_prefixes() -> list[Path]:
    """AMENT_PREFIX_PATH's entries, then sys.prefix, each once."""
    ament = [Path(p) for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    return list(dict.fromkeys([*ament, Path(sys.prefix)]))
