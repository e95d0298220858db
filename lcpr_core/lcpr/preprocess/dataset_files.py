"""Reading raw LiDAR files of the datasets users have (nuScenes, KITTI)."""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lcpr_common.point_files import KITTI_COLUMNS, NUSCENES_COLUMNS, PointFileError, read_float32_rows

from ...errors import DatasetFileError, InputShapeError
from .camera import NUSCENES_CAMERAS


def read_float32_points(path: str | os.PathLike[str], *, columns: tuple[str, ...]) -> np.ndarray:
    """A flat float32 file -> N x len(columns) array (lcpr_common's reader; its size error as InputShapeError)."""
    try:
        return read_float32_rows(path, columns=columns)
    except PointFileError as err:
        raise InputShapeError(str(err)) from err


def read_nuscenes_lidar(path: str | os.PathLike[str]) -> np.ndarray:
    """nuScenes ``*.pcd.bin``: N x 5 (x, y, z, intensity, ring), LIDAR_TOP frame."""
    return read_float32_points(path, columns=NUSCENES_COLUMNS)


def read_kitti_velodyne(path: str | os.PathLike[str]) -> np.ndarray:
    """KITTI ``velodyne/*.bin``: N x 4 (x, y, z, reflectance), Velodyne frame (x forward)."""
    return read_float32_points(path, columns=KITTI_COLUMNS)


@dataclass(frozen=True)
class KeyframeFiles:
    """One nuScenes-style keyframe on disk: camera JPEGs (in camera order) and a LiDAR sweep."""

    cameras: tuple[Path, ...]
    lidar: Path

    def read(self) -> tuple[list[bytes], np.ndarray]:
        """-> (encoded camera images, N x 5 points)."""
        return [p.read_bytes() for p in self.cameras], read_nuscenes_lidar(self.lidar)


def find_nuscenes_keyframe(
    folder: str | os.PathLike[str], *, cameras: Sequence[str] = NUSCENES_CAMERAS
) -> KeyframeFiles:
    """One keyframe in ``folder``, in either layout: nuScenes' own file names (``*__CAM_X__*.jpg`` for each
    camera and one ``*__LIDAR_TOP__*.pcd.bin``), or an export's ``imgs/CAM_X.jpg`` and one ``*.bin``."""
    root = Path(folder)
    if (root / "imgs").is_dir() and not list(root.glob("*__LIDAR_TOP__*.pcd.bin")):
        return _exported_keyframe(root, cameras)
    found = []
    for cam in cameras:
        matches = sorted(root.glob(f"*__{cam}__*.jpg"))
        if len(matches) != 1:
            raise DatasetFileError(f"expected one *__{cam}__*.jpg in {root}, found {len(matches)}")
        found.append(matches[0])
    lidar = sorted(root.glob("*__LIDAR_TOP__*.pcd.bin"))
    if len(lidar) != 1:
        raise DatasetFileError(f"expected one *__LIDAR_TOP__*.pcd.bin in {root}, found {len(lidar)}")
    return KeyframeFiles(tuple(found), lidar[0])


def _exported_keyframe(root: Path, cameras: Sequence[str]) -> KeyframeFiles:
    missing = [cam for cam in cameras if not (root / "imgs" / f"{cam}.jpg").is_file()]
    if missing:
        raise DatasetFileError(f"{root / 'imgs'} lacks {', '.join(f'{cam}.jpg' for cam in missing)}")
    lidar = sorted(root.glob("*.bin"))
    if len(lidar) != 1:
        raise DatasetFileError(f"expected one *.bin LIDAR_TOP sweep in {root}, found {len(lidar)}")
    return KeyframeFiles(tuple(root / "imgs" / f"{cam}.jpg" for cam in cameras), lidar[0])
