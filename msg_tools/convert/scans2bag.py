"""A folder of LiDAR scans with poses and times -> rosbag2 (``msg_tools_scans2bag``).

    msg_tools_scans2bag ../shared/data/livox_hku/walk_loop --out walk_loop.bag
    msg_tools_scans2bag ../shared/data/kitti00 --out kitti.bag --poses ../shared/data/kitti00/poses.txt

Scans: ``Scans/*.pcd`` or ``*.pcd`` (PCD v0.7, any fields with x, y, z) or ``velodyne/*.bin`` or
``*.bin`` (KITTI float32 x, y, z, intensity), in the sensor frame. Poses (``--poses``, default the
first of ``optimized_poses.txt``, ``poses.txt``, ``odom_poses.txt`` in the folder; none = no
odometry): one 3 x 4 row-major ``world_T_sensor`` per line. Times: ``times.txt`` (s), else 0.1 s
apart. Scans match pose and time lines in order when the counts agree, else by the number in their
name (KITTI's ``000015.bin`` is line 15 of a sequence's files); anything else is refused with the
counts. KITTI's own ``poses.txt`` are camera-0 poses: with no ``calib.txt`` beside them they are
written as given (a fixed offset from the LiDAR frame; the summary says so).

Writes ``/points`` (sensor_msgs/PointCloud2, frame ``lidar``: the scan's fields as stored),
``/odom`` (nav_msgs/Odometry ``map`` -> ``base_link``) and ``/tf_static`` (``base_link`` -> ``lidar``,
identity: the poses are the sensor's).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lcpr_common.progress import progress_iter

from ..bags import BagWriter
from ..errors import DatasetError, MsgToolsError
from ..pcd import read_pcd
from .cli import add_output_options, run_conversion
from .kitti import kitti_cloud
from .kitti_files import read_calibration, read_scan
from .scan_folder import read_kitti_poses

POINTS_TOPIC = "/points"
ODOM_TOPIC = "/odom"
TF_STATIC_TOPIC = "/tf_static"
LIDAR_FRAME = "lidar"
#: Pose files looked for in the folder, in order, when --poses is not given.
POSE_FILES = ("optimized_poses.txt", "poses.txt", "odom_poses.txt")
SCAN_PLACES = (("Scans", ".pcd"), (".", ".pcd"), ("velodyne", ".bin"), (".", ".bin"))
DEFAULT_PERIOD_S = 0.1
DESCRIPTION = "Convert a folder of LiDAR scans (PCD or KITTI .bin) with poses and times to a rosbag2."


@dataclass
class ScansReport:
    scans: int = 0
    poses: str = "none: no odometry written"
    times: str = ""
    skipped: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"scans:    {self.scans}", f"poses:    {self.poses}", f"times:    {self.times}"]
        if self.skipped:
            out.append(f"skipped:  {len(self.skipped)} unreadable scans: {', '.join(self.skipped)}")
        return out


def find_scans(folder: Path) -> list[Path]:
    """The scans of ``folder``, sorted by name (DatasetError naming the places looked in when none)."""
    if not folder.is_dir():
        raise DatasetError(f"{folder} is not a folder")
    for sub, suffix in SCAN_PLACES:
        found = sorted((folder / sub).glob(f"*{suffix}"))
        if found:
            return found
    looked = ", ".join(f"{sub}/*{suffix}" for sub, suffix in SCAN_PLACES)
    raise DatasetError(f"{folder} holds no scans; looked for {looked}")


def line_index(scans: Sequence[Path], lines: int, what: str) -> np.ndarray:
    """Which line of a ``lines``-line file belongs to each scan: in order when the counts agree, else the number
    in each scan's name."""
    if lines == len(scans):
        return np.arange(lines)
    numbers = [int(p.stem) if p.stem.isdigit() else -1 for p in scans]
    if min(numbers) >= 0 and max(numbers) < lines:
        return np.asarray(numbers)
    raise DatasetError(f"{len(scans)} scans but {lines} lines in {what}, and the scan names "
                       f"({scans[0].name} .. {scans[-1].name}) are not line numbers of it")


def read_cloud(path: Path) -> np.ndarray:
    """One scan as a structured array with float32 x, y, z (and whatever else the file holds)."""
    if path.suffix == ".bin":
        return kitti_cloud(read_scan(path), None)
    cloud = read_pcd(path)
    missing = [n for n in "xyz" if n not in (cloud.dtype.names or ())]
    if missing:
        raise DatasetError(f"{path} has no {', '.join(missing)} field; fields: {cloud.dtype.names}")
    return cloud


def _times(folder: Path, scans: Sequence[Path], report: ScansReport) -> np.ndarray:
    path = folder / "times.txt"
    if not path.is_file():
        report.times = f"no times.txt: {DEFAULT_PERIOD_S} s apart"
        return np.arange(len(scans)) * DEFAULT_PERIOD_S
    try:
        stamps = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except ValueError as err:
        raise DatasetError(f"cannot read times from {path}: {err}") from err
    stamps = stamps[line_index(scans, len(stamps), str(path))]
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) <= 0):
        raise DatasetError(f"{path}: the scans' times must be finite and increasing")
    report.times = str(path)
    return stamps


def _poses(folder: Path, scans: Sequence[Path], poses: Path | None, report: ScansReport) -> np.ndarray | None:
    if poses is None:
        poses = next((folder / name for name in POSE_FILES if (folder / name).is_file()), None)
        if poses is None:
            return None
    elif not poses.is_file():
        beside = folder / poses  # a bare name (--poses odom_poses.txt) names a file of the folder
        if poses.is_absolute() or not beside.is_file():
            raise DatasetError(f"--poses {poses} does not exist (nor {beside}); accepted: a pose file's path, or "
                               f"the name of one in {folder}")
        poses = beside
    all_poses = read_kitti_poses(poses)
    world_T = all_poses[line_index(scans, len(all_poses), str(poses))]
    calib = poses.parent / "calib.txt"
    if poses.name == "poses.txt" and calib.is_file():  # KITTI: camera-0 poses -> Velodyne poses
        world_T = read_calibration(calib).velodyne_poses(world_T)
        report.poses = f"{poses} (KITTI camera-0 poses, moved to the LiDAR with {calib})"
    elif poses.name == "poses.txt":
        report.poses = f"{poses} (as given: KITTI's are camera-0 poses, no calib.txt beside them)"
    else:
        report.poses = str(poses)
    if not np.all(np.isfinite(world_T)):
        raise DatasetError(f"{poses} holds a pose that is not finite")
    return world_T


def convert_scans(folder: str | Path, out: str | Path, *, poses: str | Path | None = None, skip_bad: bool = False,
                  storage: str = "sqlite3", overwrite: bool = False, show_progress: bool = False) -> ScansReport:
    """Write the scans of ``folder`` (with its poses and times) as the bag ``out``.

    An unreadable or truncated scan raises DatasetError naming it, or, with ``skip_bad``, is left out and
    named in the report."""
    root = Path(folder)
    report = ScansReport()
    scans = find_scans(root)
    stamps = _times(root, scans, report)
    world_T = _poses(root, scans, None if poses is None else Path(poses), report)
    with BagWriter(out, storage=storage, overwrite=overwrite) as writer:  # type: ignore[arg-type]
        writer.write_static_transforms([], LIDAR_FRAME, np.eye(4), topic=TF_STATIC_TOPIC)
        for i in progress_iter(range(len(scans)), total=len(scans), enabled=show_progress, unit="scan"):
            try:
                cloud = read_cloud(scans[i])
            except (DatasetError, MsgToolsError, OSError, ValueError) as err:
                if not skip_bad:
                    raise DatasetError(f"{scans[i]}: {err} (--skip-bad leaves such scans out)") from err
                report.skipped.append(scans[i].name)
                continue
            stamp = float(stamps[i])
            writer.write_cloud(POINTS_TOPIC, cloud, frame_id=LIDAR_FRAME, stamp=stamp)
            if world_T is not None:
                writer.write_odometry(ODOM_TOPIC, world_T[i], stamp=stamp)
            report.scans += 1
    return report


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="msg_tools_scans2bag", description=DESCRIPTION)
    parser.add_argument("folder", type=Path, help="folder with Scans/*.pcd, *.pcd, velodyne/*.bin or *.bin")
    parser.add_argument("--poses", type=Path, default=None,
                        help=f"pose file, 3 x 4 row-major per line; a name alone that is not a file here names the "
                             f"folder's (default: the first of {', '.join(POSE_FILES)} in the folder; none: no "
                             "odometry)")
    parser.add_argument("--skip-bad", action="store_true", help="leave unreadable or truncated scans out, named")
    add_output_options(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_conversion("msg_tools_scans2bag", args.out, lambda: convert_scans(
        args.folder, args.out, poses=args.poses, skip_bad=args.skip_bad, storage=args.storage,
        overwrite=args.overwrite, show_progress=not args.no_progress,
    ))


if __name__ == "__main__":
    sys.exit(main())
