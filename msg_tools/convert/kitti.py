"""KITTI odometry sequence -> rosbag2 (``msg_tools_kitti2bag``; ``python -m msg_tools.convert.kitti``).

Writes, on :data:`~msg_tools.frames.KITTI_TOPICS`, for every scan:

* ``PointCloud2`` in the Velodyne frame ``velodyne``: x, y, z, intensity float32
  (KITTI reflectance), plus ``label`` uint32 when SemanticKITTI ``labels/*.label``
  exist (lower 16 bits semantic id, upper 16 instance id);
* the left colour camera (image_2) as ``sensor_msgs/Image`` ``rgb8`` (decoded PNG, so
  readers need no codec), frame ``camera_left``, with ``CameraInfo`` from P2;
* ``nav_msgs/Odometry`` (``map`` -> ``base_link``) when poses exist. KITTI poses are
  camera-0 poses; they are converted to the Velodyne frame with
  map_T_velo(i) = Tr^-1 . pose(i) . Tr, i.e. ``map`` is the Velodyne frame of the
  first scan and ``base_link`` is the Velodyne frame (x forward, y left, z up);
* ``/tf_static``: base_link -> camera_left (Tr^-1 . cam0_T_cam2) and base_link ->
  velodyne (identity);
* with ``--depth``: a sparse ``32FC1`` depth image (metres, 0 = no point) of the scan
  projected into image_2, and, with labels, a label image (``mono16``/``32SC1``).

Stamps are ``--start-time`` plus times.txt, in exact nanoseconds.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lcpr_common.progress import progress_iter

from ..bags import BagWriter
from ..bags.writer import label_image
from ..compressed import decode_image_bytes
from ..errors import DatasetError
from ..frames import KITTI_TOPICS, CameraModel, Topics
from ..geometry import invert_pose
from ..types import Stamp, sec_to_stamp
from .cli import add_output_options, run_conversion
from .kitti_files import KittiSequence, read_labels, read_scan

CAMERA_FRAME = "camera_left"
LIDAR_FRAME = "velodyne"
DESCRIPTION = "Convert a KITTI odometry sequence (velodyne, image_2, calib, poses, labels) to a rosbag2."


@dataclass
class KittiReport:
    scans: int = 0
    with_pose: bool = False
    with_labels: bool = False
    with_depth: bool = False

    def lines(self) -> list[str]:
        return [
            f"scans:    {self.scans}",
            f"poses:    {'yes (Velodyne frame, map = first scan)' if self.with_pose else 'no poses.txt: no odometry'}",
            f"labels:   {'yes (label field)' if self.with_labels else 'no'}",
            f"depth:    {'yes' if self.with_depth else 'no'}",
        ]


def kitti_cloud(points: np.ndarray, labels: np.ndarray | None) -> np.ndarray:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")]
    if labels is not None:
        fields.append(("label", "<u4"))
    cloud = np.zeros(len(points), dtype=fields)
    for column, name in enumerate(("x", "y", "z", "intensity")):
        cloud[name] = points[:, column]
    if labels is not None:
        cloud["label"] = labels
    return cloud


def project_scan(
    points: np.ndarray, labels: np.ndarray | None, model: CameraModel
) -> tuple[np.ndarray, np.ndarray | None]:
    """Velodyne points -> (H x W float32 depth in metres, H x W uint32 labels), nearest point per pixel."""
    cam_T_base = invert_pose(model.base_T_cam)
    xyz = points[:, :3].astype(np.float64) @ cam_T_base[:3, :3].T + cam_T_base[:3, 3]
    front = xyz[:, 2] > 0.1
    uvw = xyz[front] @ model.K.T
    u = np.floor(uvw[:, 0] / uvw[:, 2]).astype(np.int64)
    v = np.floor(uvw[:, 1] / uvw[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < model.width) & (v >= 0) & (v < model.height)
    pixel = v[inside] * model.width + u[inside]
    depth_values = xyz[front][inside, 2]
    order = np.lexsort((depth_values, pixel))  # by pixel, nearest first
    first = np.ones(order.size, dtype=bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    chosen = order[first]
    depth = np.zeros(model.height * model.width, dtype=np.float32)
    depth[pixel[chosen]] = depth_values[chosen]
    label_img: np.ndarray | None = None
    if labels is not None:
        label_img = np.zeros(model.height * model.width, dtype=np.uint32)
        label_img[pixel[chosen]] = labels[front][inside][chosen]
        label_img = label_img.reshape(model.height, model.width)
    return depth.reshape(model.height, model.width), label_img


def _rgb(path: Path) -> np.ndarray:
    pixels = decode_image_bytes(path.read_bytes())
    if pixels.ndim == 2:
        if pixels.dtype != np.uint8:
            raise DatasetError(f"{path} is a {pixels.dtype} grey image; image_2 holds 8-bit colour images")
        pixels = np.repeat(pixels[:, :, None], 3, axis=2)
    return pixels


def convert_kitti(
    sequence: str | Path,
    out: str | Path,
    *,
    poses: str | Path | None = None,
    start_time: float = 0.0,
    depth: bool = False,
    limit: int | None = None,
    topics: Topics = KITTI_TOPICS,
    storage: str = "sqlite3",
    overwrite: bool = False,
    show_progress: bool = False,
) -> KittiReport:
    """Convert the sequence folder ``sequence`` (first ``limit`` scans when given) into the bag ``out``."""
    seq = KittiSequence.open(Path(sequence), poses=None if poses is None else Path(poses))
    count = len(seq.stems) if limit is None else max(0, min(limit, len(seq.stems)))
    start_ns = sec_to_stamp(start_time).ns
    velo_poses = None if seq.camera_poses is None else seq.calibration.velodyne_poses(seq.camera_poses)
    report = KittiReport(with_pose=velo_poses is not None, with_labels=seq.has_labels, with_depth=depth)
    model: CameraModel | None = None
    with BagWriter(out, storage=storage, overwrite=overwrite) as writer:  # type: ignore[arg-type]
        for i in progress_iter(range(count), total=count, enabled=show_progress, unit="scan"):
            stem = seq.stems[i]
            stamp = Stamp.from_ns(start_ns + seq.times_ns[i])
            rgb = _rgb(seq.root / "image_2" / f"{stem}.png")
            if model is None:
                model = CameraModel("camera_left", CAMERA_FRAME, rgb.shape[1], rgb.shape[0],
                                    seq.calibration.K, seq.calibration.velo_T_cam2)
                writer.write_static_transforms([model], LIDAR_FRAME, np.eye(4), stamp=stamp, topic=topics.tf_static)
            elif (rgb.shape[1], rgb.shape[0]) != (model.width, model.height):
                raise DatasetError(f"image_2/{stem}.png is {rgb.shape[1]} x {rgb.shape[0]}, "
                                   f"the sequence's first image {model.width} x {model.height}")
            points = read_scan(seq.root / "velodyne" / f"{stem}.bin")
            labels = read_labels(seq.root / "labels" / f"{stem}.label", len(points)) if seq.has_labels else None
            writer.write_image(topics.cameras[0], rgb, encoding="rgb8", frame_id=CAMERA_FRAME, stamp=stamp)
            writer.write_camera_info(topics.camera_info[0], model, stamp=stamp)
            if depth:
                depth_img, label_img = project_scan(points, labels, model)
                writer.write_image(topics.depth[0], depth_img, encoding="32FC1", frame_id=CAMERA_FRAME, stamp=stamp)
                if label_img is not None:
                    pixels, encoding = label_image(label_img)
                    writer.write_image(topics.labels[0], pixels, encoding=encoding, frame_id=CAMERA_FRAME, stamp=stamp)
            writer.write_cloud(topics.lidar, kitti_cloud(points, labels), frame_id=LIDAR_FRAME, stamp=stamp)
            if velo_poses is not None:
                writer.write_odometry(topics.odom, velo_poses[i], stamp=stamp)
            report.scans += 1
    return report


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="msg_tools_kitti2bag", description=DESCRIPTION)
    parser.add_argument("sequence", type=Path, help="sequence folder (velodyne/, image_2/, calib.txt, times.txt)")
    parser.add_argument("--poses", type=Path, default=None,
                        help="ground-truth poses file (default: <sequence>/poses.txt when present)")
    parser.add_argument("--start-time", type=float, default=0.0,
                        help="stamp of times.txt's 0, in seconds (default: %(default)s)")
    parser.add_argument("--depth", action="store_true",
                        help="also write sparse depth (and label) images projected from the scans")
    parser.add_argument("--limit", type=int, default=None, help="convert only the first N scans")
    add_output_options(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_conversion("msg_tools_kitti2bag", args.out, lambda: convert_kitti(
        args.sequence, args.out, poses=args.poses, start_time=args.start_time, depth=args.depth,
        limit=args.limit, storage=args.storage, overwrite=args.overwrite, show_progress=not args.no_progress,
    ))


if __name__ == "__main__":
    raise SystemExit(main())
