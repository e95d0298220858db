"""The datasets' flat float32 point files as the converters read them: :mod:`lcpr_common.point_files`'s
reader, its size error raised as :class:`~msg_tools.errors.DatasetError` like every converter error."""
from __future__ import annotations

import os

import numpy as np

from lcpr_common.point_files import KITTI_COLUMNS, NUSCENES_COLUMNS, PointFileError, read_float32_rows

from ..errors import DatasetError

__all__ = ["KITTI_COLUMNS", "NUSCENES_COLUMNS", "read_points"]


def read_points(path: str | os.PathLike[str], *, columns: tuple[str, ...]) -> np.ndarray:
    """The file as an N x len(columns) float32 array (a size that is not whole rows: DatasetError)."""
    try:
        return read_float32_rows(path, columns=columns)
    except PointFileError as err:
        raise DatasetError(str(err)) from err
