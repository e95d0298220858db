"""Reading a KITTI odometry sequence folder: calib.txt, times.txt, poses, scans, images, SemanticKITTI labels.

Frames of the KITTI odometry benchmark:

* ``Tr`` (calib.txt) maps Velodyne points into the rectified camera-0 frame: cam0_T_velo;
* ``P2`` = K2 [I | t2] projects rectified camera-0 points into image_2, so the
  left colour camera sits at cam0_T_cam2 = [I | -t2] (t2 = K2^-1 P2[:, 3]);
* poses.txt line i is cam0(0)_T_cam0(i), 3 x 4 row-major.
"""
from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..geometry import check_pose, invert_pose
from .point_files import KITTI_COLUMNS, read_points

LABEL_DTYPE = np.dtype("<u4")


@dataclass(frozen=True)
class KittiCalibration:
    P2: np.ndarray  # 3 x 4
    cam0_T_velo: np.ndarray  # 4 x 4 (Tr)

    @property
    def K(self) -> np.ndarray:
        return self.P2[:, :3].copy()

    @property
    def cam0_T_cam2(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = -np.linalg.solve(self.K, self.P2[:, 3])
        return T

    @property
    def velo_T_cam2(self) -> np.ndarray:
        """Pose of the left colour camera's optical frame in the Velodyne (= base) frame."""
        return invert_pose(self.cam0_T_velo) @ self.cam0_T_cam2

    def velodyne_poses(self, camera_poses: np.ndarray) -> np.ndarray:
        """poses.txt (cam0(0)_T_cam0(i)) -> map_T_velo(i), map = the Velodyne frame of scan 0.

        map_T_velo(i) = Tr^-1 . cam0(0)_T_cam0(i) . Tr
        """
        Tr = self.cam0_T_velo
        return invert_pose(Tr)[None] @ camera_poses @ Tr[None]


def _numbers(text: str, path: Path, line_no: int) -> np.ndarray:
    try:
        return np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError as err:
        raise DatasetError(f"{path}:{line_no}: {text.strip()!r} is not a list of numbers") from err


def read_calibration(path: Path) -> KittiCalibration:
    """calib.txt with ``P2:`` and ``Tr:`` (or ``Tr_velo_to_cam:``) lines of 12 numbers."""
    if not path.is_file():
        raise DatasetError(f"{path} is missing; a KITTI odometry sequence holds calib.txt with P2 and Tr")
    entries: dict[str, np.ndarray] = {}
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if ":" in line:
            key, values = line.split(":", 1)
            entries[key.strip()] = _numbers(values, path, line_no)
    tr = entries.get("Tr", entries.get("Tr_velo_to_cam"))
    for name, value in (("P2", entries.get("P2")), ("Tr", tr)):
        if value is None or value.size != 12:
            found = {k: v.size for k, v in entries.items()}
            raise DatasetError(f"{path} needs a '{name}:' line of 12 numbers; found keys and sizes {found}")
    assert tr is not None
    cam0_T_velo = np.vstack([tr.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    check_pose(cam0_T_velo, what=f"Tr in {path}", tol=1e-4)
    return KittiCalibration(P2=entries["P2"].reshape(3, 4), cam0_T_velo=cam0_T_velo)


def read_times_ns(path: Path) -> list[int]:
    """times.txt (seconds, one per line) -> exact integer nanoseconds (decimal parsing, no float rounding)."""
    if not path.is_file():
        raise DatasetError(f"{path} is missing; a KITTI odometry sequence holds times.txt")
    out = []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            out.append(int((Decimal(line.strip()) * 1_000_000_000).to_integral_value()))
        except InvalidOperation as err:
            raise DatasetError(f"{path}:{line_no}: {line.strip()!r} is not a time in seconds") from err
    return out


def read_camera_poses(path: Path) -> np.ndarray:
    """poses.txt (12 numbers per line, 3 x 4 row-major) -> N x 4 x 4."""
    rows = []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        values = _numbers(line, path, line_no)
        if values.size != 12:
            raise DatasetError(f"{path}:{line_no} holds {values.size} numbers; a pose line holds 12 (3 x 4 row-major)")
        rows.append(values)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        poses[:, :3, :] = np.asarray(rows).reshape(-1, 3, 4)
    return poses


def read_scan(path: Path) -> np.ndarray:
    """velodyne/*.bin -> N x 4 float32 (x, y, z, reflectance)."""
    return read_points(path, columns=KITTI_COLUMNS)


def read_labels(path: Path, points: int) -> np.ndarray:
    """SemanticKITTI labels/*.label -> uint32 per point (lower 16 bits semantic id, upper 16 instance)."""
    labels = np.fromfile(path, dtype=LABEL_DTYPE)
    if labels.size != points:
        raise DatasetError(f"{path} holds {labels.size} labels for a scan of {points} points")
    return labels.astype(np.uint32)


@dataclass(frozen=True)
class KittiSequence:
    root: Path
    stems: tuple[str, ...]  # scan names without suffix, sorted
    times_ns: tuple[int, ...]
    calibration: KittiCalibration
    camera_poses: np.ndarray | None  # N x 4 x 4 (poses.txt), None when absent
    has_labels: bool

    @classmethod
    def open(cls, root: Path, *, poses: Path | None = None) -> KittiSequence:
        velodyne, images = root / "velodyne", root / "image_2"
        if not velodyne.is_dir() or not images.is_dir():
            raise DatasetError(f"{root} is not a KITTI odometry sequence: it needs velodyne/ and image_2/ folders")
        stems = tuple(sorted(p.stem for p in velodyne.glob("*.bin")))
        if not stems:
            raise DatasetError(f"{velodyne} holds no *.bin scans")
        missing = [s for s in stems if not (images / f"{s}.png").is_file()]
        if missing:
            raise DatasetError(f"scans without an image_2/<name>.png: "
                               f"{missing[:5]}{' ...' if len(missing) > 5 else ''}")
        times = read_times_ns(root / "times.txt")
        if len(times) != len(stems):
            raise DatasetError(f"{root / 'times.txt'} has {len(times)} lines for {len(stems)} scans")
        pose_path = poses if poses is not None else root / "poses.txt"
        camera_poses = None
        if pose_path.is_file():
            camera_poses = read_camera_poses(pose_path)
            if len(camera_poses) != len(stems):
                raise DatasetError(f"{pose_path} has {len(camera_poses)} poses for {len(stems)} scans")
        elif poses is not None:
            raise DatasetError(f"poses file {poses} does not exist")
        labels = root / "labels"
        has_labels = labels.is_dir() and any(labels.glob("*.label"))
        if has_labels:
            absent = [s for s in stems if not (labels / f"{s}.label").is_file()]
            if absent:
                raise DatasetError(f"{labels} lacks labels for scans {absent[:5]}")
        return cls(root, stems, tuple(times), read_calibration(root / "calib.txt"), camera_poses, has_labels)
