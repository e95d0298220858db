"""A folder of keyframe scans as LiDAR SLAM systems save them (FAST-LIO, SC-A-LOAM, LIO-SAM exports).

    Scans/000000.pcd ...       one cloud per keyframe, in the sensor (body) frame
    optimized_poses.txt        one 3 x 4 row-major world_T_body per line (KITTI layout)
    odom_poses.txt             (optional) the same before loop closing
    times.txt                  (optional) one stamp per line, seconds

    seq = ScanFolder("../shared/data/livox_hku/walk_loop")
    seq.poses            # N x 4 x 4
    seq.points(i)        # N_i x 3 float64, body frame
"""
from __future__ import annotations

import os
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..pcd import pcd_xyz, read_pcd

POSE_FILES = ("optimized_poses.txt", "odom_poses.txt")


def read_kitti_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """A KITTI-style pose file (12 numbers a line, 3 x 4 row-major) -> N x 4 x 4 float64."""
    where = os.fspath(path)
    try:
        values = np.loadtxt(where, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as err:
        raise DatasetError(f"cannot read poses from {where}: {err}") from err
    if values.shape[1] != 12:
        raise DatasetError(f"{where} has {values.shape[1]} numbers a line; expected 12 (a 3 x 4 row-major pose)")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :4] = values.reshape(-1, 3, 4)
    return poses


class ScanFolder:
    """Keyframe scans with poses; ``poses_file`` picks optimized (default) or odometry poses."""

    def __init__(self, folder: str | os.PathLike[str], *, poses_file: str = "optimized_poses.txt") -> None:
        self.folder = Path(folder)
        if poses_file not in POSE_FILES:
            raise DatasetError(f"poses_file={poses_file!r}; accepted: {', '.join(POSE_FILES)}")
        self.scans = sorted((self.folder / "Scans").glob("*.pcd"))
        if not self.scans:
            raise DatasetError(f"{self.folder} has no Scans/*.pcd; expected a scan folder (Scans/, {poses_file})")
        self.poses = read_kitti_poses(self.folder / poses_file)
        if len(self.poses) != len(self.scans):
            raise DatasetError(f"{self.folder}: {len(self.scans)} scans but {len(self.poses)} poses in {poses_file}")

    def __len__(self) -> int:
        return len(self.scans)

    @cached_property
    def stamps(self) -> np.ndarray:
        """(N,) seconds from times.txt, or 0.1 s apart when the file is absent."""
        path = self.folder / "times.txt"
        if not path.exists():
            return np.arange(len(self), dtype=np.float64) * 0.1
        stamps = np.loadtxt(path, dtype=np.float64, ndmin=1)
        if stamps.shape != (len(self),):
            raise DatasetError(f"{path} holds {stamps.shape[0]} stamps for {len(self)} scans")
        return stamps

    def points(self, i: int) -> np.ndarray:
        """Scan i as N x 3 float64 in its body frame."""
        return pcd_xyz(read_pcd(self.scans[i]))
