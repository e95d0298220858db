"""nuScenes v1.0 keyframes -> rosbag2 (``msg_tools_nuscenes2bag``; ``python -m msg_tools.convert.nuscenes``).

For each keyframe (sample) of the chosen scenes, on :data:`~msg_tools.frames.NUSCENES_TOPICS`:

* the six cameras as ``CompressedImage`` carrying the dataset's original JPEG bytes,
  frame ``<CHANNEL>`` (e.g. ``CAM_FRONT``), with a ``CameraInfo`` (camera_intrinsic) each;
* LIDAR_TOP as ``PointCloud2`` (x, y, z, intensity float32, ring uint16) in its own
  sensor frame ``LIDAR_TOP``;
* the ego pose of every keyframe sample_data as ``nav_msgs/Odometry`` (``map`` ->
  ``base_link``; ego_pose translation and w, x, y, z rotation);
* the extrinsics (calibrated_sensor translation/rotation, sensor in ``base_link``) on
  ``/tf_static``, at the start of each scene whose calibration differs from the last.

Stamps are the dataset's microsecond timestamps, exactly. All scenes go into one bag,
ordered by time (nuScenes poses of one location share a map frame).
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image as PILImage

from lcpr_common.progress import progress_iter

from ..bags import BagWriter
from ..compressed import compressed_jpeg_bytes
from ..errors import DatasetError
from ..frames import NUSCENES_CAMERAS, NUSCENES_TOPICS, CameraModel, Topics
from ..geometry import pose_from_parts
from ..types import Stamp
from .cli import add_output_options, run_conversion
from .nuscenes_tables import NuScenesTables, Record
from .point_files import NUSCENES_COLUMNS, read_points

LIDAR = "LIDAR_TOP"
DESCRIPTION = "Convert nuScenes v1.0 keyframes (six cameras, LIDAR_TOP, ego poses, calibration) to a rosbag2."


@dataclass
class NuScenesReport:
    scenes: list[str] = field(default_factory=list)
    samples: int = 0
    skipped_no_lidar: int = 0  # samples without a LIDAR_TOP keyframe (not written)
    missing_cameras: int = 0  # camera images absent from written samples

    def lines(self) -> list[str]:
        return [
            f"scenes:   {len(self.scenes)} ({', '.join(self.scenes)})",
            f"samples:  {self.samples} written, {self.skipped_no_lidar} skipped without {LIDAR}",
            f"cameras missing from written samples: {self.missing_cameras}",
        ]


def _us_stamp(microseconds: int) -> Stamp:
    return Stamp.from_ns(int(microseconds) * 1000)


def _pose(record: Record) -> np.ndarray:
    """nuScenes translation + rotation (w, x, y, z) -> 4 x 4."""
    w, x, y, z = (float(v) for v in record["rotation"])
    return pose_from_parts(np.asarray(record["translation"], dtype=np.float64), np.array([x, y, z, w]))


def read_lidar(path: Path) -> np.ndarray:
    """``*.pcd.bin`` (float32 x, y, z, intensity, ring) -> structured cloud with ring as uint16."""
    points = read_points(path, columns=NUSCENES_COLUMNS)
    ring = points[:, 4]
    if np.any(ring != np.round(ring)) or np.any(ring < 0) or np.any(ring > np.iinfo(np.uint16).max):
        raise DatasetError(f"{path} has ring values that are not whole numbers in [0, 65535]")
    cloud = np.zeros(len(points),
                     dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2")])
    for column, name in enumerate(("x", "y", "z", "intensity")):
        cloud[name] = points[:, column]
    cloud["ring"] = ring.astype(np.uint16)
    return cloud


class _SceneWriter:
    """Writes the samples of nuScenes scenes into one open bag."""

    def __init__(self, tables: NuScenesTables, writer: BagWriter, topics: Topics, report: NuScenesReport) -> None:
        self.tables = tables
        self.writer = writer
        self.topics = topics
        self.report = report
        self._last_calibration: list[tuple[str, list[float], list[float]]] | None = None
        self._last_odom_us = -1

    def camera_model(self, sd: Record, channel: str) -> CameraModel:
        calibrated = self.tables.calibrated_sensors[sd["calibrated_sensor_token"]]
        K = np.asarray(calibrated.get("camera_intrinsic") or [], dtype=np.float64)
        if K.shape != (3, 3):
            raise DatasetError(f"calibrated_sensor {calibrated['token']!r} of {channel} has no 3 x 3 camera_intrinsic")
        width, height = int(sd.get("width") or 0), int(sd.get("height") or 0)
        if not width or not height:
            with PILImage.open(self.tables.root / sd["filename"]) as img:
                width, height = img.size
        return CameraModel(channel, channel, width, height, K, _pose(calibrated))

    def write_sample(self, sample: Record, first_of_scene: bool) -> None:
        frames = self.tables.keyframes.get(sample["token"], {})
        lidar = frames.get(LIDAR)
        if lidar is None:
            self.report.skipped_no_lidar += 1
            return
        models: list[CameraModel | None] = []
        for channel in NUSCENES_CAMERAS:
            sd = frames.get(channel)
            models.append(None if sd is None else self.camera_model(sd, channel))
        if first_of_scene:
            self._write_calibration(models, lidar, _us_stamp(min(r["timestamp"] for r in frames.values())))
        for index, (channel, model) in enumerate(zip(NUSCENES_CAMERAS, models, strict=True)):
            if model is None:
                self.report.missing_cameras += 1
                continue
            sd = frames[channel]
            stamp = _us_stamp(sd["timestamp"])
            data = self._read(sd)
            self.writer.write(self.topics.cameras[index], compressed_jpeg_bytes(data, frame_id=channel, stamp=stamp))
            self.writer.write_camera_info(self.topics.camera_info[index], model, stamp=stamp)
        self.writer.write_cloud(self.topics.lidar, read_lidar(self.tables.root / lidar["filename"]),
                                frame_id=LIDAR, stamp=_us_stamp(lidar["timestamp"]))
        for sd in sorted(frames.values(), key=lambda r: r["timestamp"]):
            ego = self.tables.ego_poses.get(sd["ego_pose_token"])
            if ego is None:
                raise DatasetError(f"sample_data {sd['token']!r} refers to missing ego_pose {sd['ego_pose_token']!r}")
            if ego["timestamp"] <= self._last_odom_us:
                continue  # shared or repeated ego pose
            self.writer.write_odometry(self.topics.odom, _pose(ego), stamp=_us_stamp(ego["timestamp"]))
            self._last_odom_us = ego["timestamp"]
        self.report.samples += 1

    def _read(self, sd: Record) -> bytes:
        path = self.tables.root / sd["filename"]
        try:
            return path.read_bytes()
        except OSError as err:
            raise DatasetError(f"cannot read {path} (sample_data {sd['token']!r}): {err}") from err

    def _write_calibration(self, models: Sequence[CameraModel | None], lidar: Record, stamp: Stamp) -> None:
        calibrated = self.tables.calibrated_sensors[lidar["calibrated_sensor_token"]]
        key = [(m.frame_id, m.base_T_cam.ravel().tolist(), m.K.ravel().tolist()) for m in models if m is not None]
        key.append((LIDAR, list(calibrated["translation"]), list(calibrated["rotation"])))
        if key == self._last_calibration:
            return
        self._last_calibration = key
        self.writer.write_static_transforms(
            [m for m in models if m is not None], LIDAR, _pose(calibrated), stamp=stamp,
            topic=self.topics.tf_static,
        )


def convert_nuscenes(
    dataroot: str | Path,
    out: str | Path,
    *,
    version: str = "v1.0-trainval",
    scenes: Sequence[str] = (),
    locations: Sequence[str] = (),
    storage: str = "sqlite3",
    overwrite: bool = False,
    show_progress: bool = False,
) -> NuScenesReport:
    """Write the keyframes of the chosen scenes (by name and/or location) into the bag ``out``."""
    tables = NuScenesTables.load(dataroot, version)
    chosen = tables.select(names=scenes, locations=locations)
    report = NuScenesReport(scenes=[s["name"] for s in chosen])
    work = [(sample, i == 0) for scene in chosen for i, sample in enumerate(tables.scene_samples(scene))]
    with BagWriter(out, storage=storage, overwrite=overwrite) as writer:  # type: ignore[arg-type]
        scene_writer = _SceneWriter(tables, writer, NUSCENES_TOPICS, report)
        for sample, first in progress_iter(work, total=len(work), enabled=show_progress, unit="sample"):
            scene_writer.write_sample(sample, first)
    return report


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="msg_tools_nuscenes2bag", description=DESCRIPTION)
    parser.add_argument("--dataroot", required=True, type=Path, help="nuScenes root (holds samples/ and <version>/)")
    parser.add_argument("--version", default="v1.0-trainval",
                        help="table folder, e.g. v1.0-mini (default: %(default)s)")
    parser.add_argument("--scene", action="append", default=[], help="scene name, e.g. scene-0061 (repeatable)")
    parser.add_argument("--location", action="append", default=[],
                        help="every scene of a location, e.g. boston-seaport (repeatable)")
    add_output_options(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_conversion("msg_tools_nuscenes2bag", args.out, lambda: convert_nuscenes(
        args.dataroot, args.out, version=args.version, scenes=args.scene, locations=args.location,
        storage=args.storage, overwrite=args.overwrite, show_progress=not args.no_progress,
    ))


if __name__ == "__main__":
    raise SystemExit(main())
