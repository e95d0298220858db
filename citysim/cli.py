"""``citysim``: render a synthetic city drive into a rosbag2 (``python -m citysim.cli``; also installed as
``msg_tools_synth``, the name interfaces other programs use)."""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from lcpr_common.progress import progress_iter
from msg_tools.bags.writer import STORAGES
from msg_tools.errors import MsgToolsError
from msg_tools.frames import SensorFrame

from .bagout import write_bag
from .depthnet import DEPTH_NOISE, DEPTH_RANGE
from .drive import ROUTES, SynthConfig, SyntheticDrive
from .lidar import LidarNoise
from .rigs import RIGS

DESCRIPTION = ("Generate a synthetic city drive with revisits (nuScenes-like or KITTI-like rig) as a rosbag2 with "
               "the dataset converters' topics plus ground-truth odometry.")


def image_size(text: str) -> tuple[int, int]:
    """'WIDTHxHEIGHT' -> (width, height)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"image size {text!r}; expected WIDTHxHEIGHT, e.g. 800x450") from err
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"image size {text!r}; both sides must be at least 16 pixels")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="citysim", description=DESCRIPTION)
    p.add_argument("--rig", choices=RIGS, default="nuscenes", help="sensor rig (default nuscenes)")
    p.add_argument("--frames", type=int, default=300, help="keyframes to render (default 300)")
    p.add_argument("--seed", type=int, default=0, help="world, route and noise seed (default 0)")
    p.add_argument("--drive", type=int, default=0,
                   help="drive K through the seed's city (default 0, the seed's own drive): K > 0 keeps the city and "
                        "drives another route over its streets with its own noise and lighting, K days later")
    p.add_argument("--route", choices=ROUTES, default="grid",
                   help="grid: a generated street grid with loops both ways; kitti00: the KITTI-00 trajectory")
    p.add_argument("--kitti-poses", type=Path, default=None,
                   help="poses.txt for --route kitti00 (default ../shared/data/kitti00/poses.txt)")
    p.add_argument("--keyframe-spacing", type=float, default=None,
                   help="metres between keyframes (default: nuscenes 5, kitti 1)")
    p.add_argument("--image-size", type=image_size, default=None,
                   help="camera WIDTHxHEIGHT (default: nuscenes 800x450, kitti 1241x376)")
    p.add_argument("--night-fraction", type=float, default=0.25, help="share of night lighting sessions (0..1)")
    p.add_argument("--camera-drop", type=float, default=0.01, help="chance of a missing camera image (default 0.01)")
    p.add_argument("--depth-range", type=float, default=DEPTH_RANGE,
                   help=f"kitti rig depth images: no depth beyond this many metres along the optical axis, as a "
                        f"monocular depth network (default {DEPTH_RANGE:g}; 0 = the renderer's depth to any range)")
    p.add_argument("--depth-noise", type=float, default=DEPTH_NOISE,
                   help=f"kitti rig depth images: smooth relative depth error, 1 sigma (default {DEPTH_NOISE:g}; "
                        f"0 = exact)")
    p.add_argument("--no-noise", action="store_true",
                   help="exact sensors: no pixel/range/depth noise, no dropouts (the depth range still applies)")
    p.add_argument("--no-lane-changes", action="store_true",
                   help="kitti00: drive exactly on the real trajectory (default: change lanes now and then)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="rendering processes (default: up to 2)")
    p.add_argument("--out", type=Path, required=True, help="rosbag2 folder to create")
    p.add_argument("--storage", choices=sorted(STORAGES), default="sqlite3", help="rosbag2 storage plugin")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag at --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    if args.kitti_poses is not None and args.route != "kitti00":
        raise ValueError(f"--kitti-poses is only used with --route kitti00 (got --route {args.route})")
    noise = {} if not args.no_noise else {"lidar_noise": LidarNoise.off(), "pixel_noise": False, "camera_drop": 0.0,
                                          "depth_noise": 0.0}
    return SynthConfig(
        rig=args.rig, frames=args.frames, seed=args.seed, drive=args.drive, route=args.route,
        kitti_poses=None if args.kitti_poses is None else str(args.kitti_poses),
        keyframe_spacing=args.keyframe_spacing, image_size=args.image_size, night_fraction=args.night_fraction,
        lane_changes=not args.no_lane_changes,
        depth_range=args.depth_range, **({"camera_drop": args.camera_drop, "depth_noise": args.depth_noise} | noise),
    )


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = config_from_args(args)
        if args.workers < 1:
            raise ValueError(f"--workers {args.workers}; it must be at least 1")
        start = time.perf_counter()
        drive = SyntheticDrive(config)
        print(f"world: {len(drive.world.objects)} objects, {len(drive.world.slots)} parking slots, "
              f"route {drive.path.length:.0f} m, built in {drive.build_seconds:.1f} s", flush=True)

        def bar(frames: Iterator[SensorFrame]) -> Iterator[SensorFrame]:
            return progress_iter(frames, total=len(drive), unit="frame", enabled=not args.no_progress)

        report = write_bag(drive, args.out, workers=args.workers, storage=args.storage, overwrite=args.overwrite,
                           wrap=bar)
    except (MsgToolsError, ValueError, FileNotFoundError) as err:
        print(f"citysim: error: {err}", file=sys.stderr)
        return 2
    stats = drive.revisits()
    print(f"bag:        {args.out} ({config.rig} rig, {config.route} route, seed {config.seed}, "
          f"drive {config.drive})")
    print(f"frames:     {report.frames} ({report.nights} at night, {report.missing_images} camera images dropped)")
    print(f"driven:     {stats.length_m:.0f} m in {stats.duration_s:.0f} s, keyframes every {drive.spacing:g} m")
    print(f"revisits:   {stats.revisits} frames within {stats.radius:g} m of a frame more than {stats.min_gap_s:g} s "
          f"older ({stats.same_direction} same direction, {stats.opposite_direction} opposite)")
    print(f"points:     {report.points / max(report.frames, 1):.0f} per scan")
    print(f"time:       {time.perf_counter() - start:.1f} s (world {drive.build_seconds:.1f} s; render per process: "
          f"lidar {report.timing.lidar:.1f} s, cameras {report.timing.cameras:.1f} s, "
          f"encode {report.timing.encode:.1f} s; "
          f"bag write {report.write_s:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
