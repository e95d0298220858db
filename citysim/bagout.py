"""Writing a synthetic drive to a rosbag2 with the converters' topics (via msg_tools.bags.BagWriter)."""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

from msg_tools.bags import BagWriter
from msg_tools.frames import SensorFrame

from .drive import FrameTiming, SyntheticDrive


@dataclass
class WriteReport:
    """What was written and where the time went (seconds; render stages summed over workers)."""

    frames: int = 0
    nights: int = 0
    missing_images: int = 0
    points: int = 0
    timing: FrameTiming = field(default_factory=FrameTiming)
    write_s: float = 0.0
    wall_s: float = 0.0


def write_bag_once(drive: SyntheticDrive, out: str | os.PathLike[str], *, desc: str, workers: int = 2) -> bool:
    """Write ``drive`` to ``out`` with a progress bar unless a bag is there already (a demo run again reuses
    its drives); True when it was written."""
    from lcpr_common.progress import progress_iter

    if os.path.exists(out):
        return False
    write_bag(drive, out, workers=workers,
              wrap=lambda frames: progress_iter(frames, total=len(drive), desc=desc, unit="frame"))
    return True


def write_bag(drive: SyntheticDrive, out: str | os.PathLike[str], *, workers: int = 1, storage: str = "sqlite3",
              overwrite: bool = False, wrap: Callable[[Iterator[SensorFrame]], Iterable[SensorFrame]] | None = None
              ) -> WriteReport:
    """Render every frame of ``drive`` and write it, with camera infos, odometry and /tf_static.

    ``wrap`` can decorate the frame iterator (e.g. with a progress bar).
    """
    rig = drive.rig
    report = WriteReport()
    start = time.perf_counter()
    rendered = drive.frames(workers=workers)
    frames: Iterable[SensorFrame] = rendered if wrap is None else wrap(rendered)
    with BagWriter(out, storage=storage, overwrite=overwrite) as writer:  # type: ignore[arg-type]
        writer.write_static_transforms(rig.cameras, rig.lidar.frame_id, rig.lidar.base_T_lidar,
                                       stamp=float(drive.keyframes.stamps[0]))
        for frame in frames:
            t0 = time.perf_counter()
            writer.write_frame(frame, topics=rig.topics, cameras=rig.cameras)
            report.write_s += time.perf_counter() - t0
            report.frames += 1
            report.nights += bool(frame.extras.get("night"))
            report.missing_images += sum(c is None for c in frame.cameras)
            report.points += len(frame.cloud)
            timing = frame.extras.get("timing")
            if isinstance(timing, FrameTiming):
                report.timing.lidar += timing.lidar
                report.timing.cameras += timing.cameras
                report.timing.encode += timing.encode
                report.timing.cpu += timing.cpu
        t0 = time.perf_counter()
    report.write_s += time.perf_counter() - t0  # closing the bag
    report.wall_s = time.perf_counter() - start
    return report
