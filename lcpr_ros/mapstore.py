"""The descriptor map file named by ``map.path``: load at start, refuse bad files, save atomically."""
from __future__ import annotations

import os
from pathlib import Path

from lcpr_core.descriptor_map import DescriptorMap, MapConfig
from lcpr_core.errors import MapError

from .errors import MapLoadError


def load_prior_map(path: str, expect: MapConfig) -> DescriptorMap | None:
    """The map saved at ``path`` (None when ``path`` is "" or absent). A file that cannot be
    used raises MapLoadError and is not touched."""
    if not path:
        return None
    file = Path(path)
    if not file.exists():
        _check_writable(file)
        return None
    if not file.is_file():
        raise MapLoadError(f"map.path {file} exists but is not a file; give a .npz file path")
    try:
        return DescriptorMap.load(file, expect=expect)
    except MapError as err:
        raise MapLoadError(
            f"refusing to start: {err}. The file was left as it is; move it away, or point map.path elsewhere"
        ) from err


def _check_writable(file: Path) -> None:
    folder = file.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise MapLoadError(f"map.path {file}: {folder} is not writable, so the map could never be saved")


def save_map(descriptor_map: DescriptorMap, path: str) -> int:
    """Write the map atomically (the old file stays if writing fails); returns its size."""
    descriptor_map.save(path)
    return len(descriptor_map)
