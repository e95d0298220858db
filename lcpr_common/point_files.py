"""Flat little-endian float32 point files (KITTI ``velodyne/*.bin``, nuScenes ``*.pcd.bin``): one reader."""
from __future__ import annotations

import os

import numpy as np

from .errors import ProjectError

KITTI_COLUMNS = ("x", "y", "z", "reflectance")
NUSCENES_COLUMNS = ("x", "y", "z", "intensity", "ring")


class PointFileError(ProjectError, ValueError):
    """A point file whose size is not a whole number of rows; callers re-raise it as their own error."""


def read_float32_rows(path: str | os.PathLike[str], *, columns: tuple[str, ...]) -> np.ndarray:
    """The file as an N x len(columns) float32 array; a size that is not whole rows is a PointFileError."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % len(columns):
        raise PointFileError(f"{os.fspath(path)} holds {raw.size} float32 values, not a multiple of "
                             f"{len(columns)} ({', '.join(columns)})")
    return raw.reshape(-1, len(columns))
