"""Read synchronised :class:`~msg_tools.frames.SensorFrame` objects from a rosbag2, streaming.

Two passes over the bag, neither holding more than a small window of messages:

1. header stamps only (read from the serialised bytes; odometry is deserialised,
   it is small): drop duplicate and out-of-order stamps per topic, match each cloud
   with the nearest image of every camera within ``slop`` seconds, and depth/label
   images to the chosen camera image;
2. deserialise only the chosen messages and yield each frame as soon as its parts
   have been seen (frames come out in cloud order).

Memory is bounded by how far apart in the bag the parts of one frame lie, which for
bags logged at header time is about ``slop``.
"""
from __future__ import annotations

import os
from collections.abc import Generator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.progress import progress_bar

from ..compressed import compressed_bytes, compressed_to_array
from ..errors import BagError
from ..frames import CameraImage, SensorFrame, Topics
from ..image import depth_to_metres, image_to_array, image_to_rgb
from ..pointcloud import pointcloud2_to_array
from ..transforms import odometry_to_pose
from ..types import NS_PER_S, typestore
from .cdr import header_stamp_ns
from .open import check_topic, open_bag, topic_types
from .sync import FramePlan, MonotonicFilter, plan_frames, pose_at

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CLOUD = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"


@dataclass
class ReadStats:
    """What :func:`read_frames` found, kept and dropped (filled before the first frame is yielded)."""

    clouds: int = 0  # cloud messages in the bag
    frames: int = 0  # frames planned (= yielded when iterated to the end)
    duplicate_clouds: int = 0  # dropped: same header stamp as the previous cloud
    out_of_order_clouds: int = 0  # dropped: header stamp earlier than the previous kept cloud
    no_camera: int = 0  # dropped: fewer than ``min_cameras`` camera images within the slop
    camera_missing: list[int] = field(default_factory=list)  # per camera: kept frames with that camera None
    duplicate_images: list[int] = field(default_factory=list)  # per camera topic, images ignored
    out_of_order_images: list[int] = field(default_factory=list)
    odometry_topic: bool = False  # whether the bag has the odometry topic
    no_pose: int = 0  # kept frames without a pose (odometry absent or too far away)

    @property
    def dropped_clouds(self) -> int:
        return self.duplicate_clouds + self.out_of_order_clouds + self.no_camera

    def summary(self) -> str:
        return (
            f"{self.frames} frames from {self.clouds} clouds; dropped clouds: {self.duplicate_clouds} duplicate stamp, "
            f"{self.out_of_order_clouds} out of order, {self.no_camera} without camera; "
            f"camera missing per camera {self.camera_missing}; images ignored per camera: "
            f"duplicate {self.duplicate_images}, out of order {self.out_of_order_images}; "
            f"frames without pose {self.no_pose}" + ("" if self.odometry_topic else " (no odometry topic)")
        )


@dataclass(frozen=True)
class _Slot:
    frame: int
    kind: str  # "cloud", "camera", "depth", "labels"
    camera: int = -1


class FrameStream:
    """Iterator of synchronised frames; ``stats`` and ``len()`` are known before iterating."""

    def __init__(
        self,
        bag_path: str | os.PathLike[str],
        *,
        topics: Topics,
        slop: float = 0.05,
        min_cameras: int = 1,
        max_odom_gap: float = 1.0,
        decode_compressed: bool = False,
        progress: bool = False,
    ) -> None:
        if slop < 0 or max_odom_gap < 0:
            raise BagError(f"slop ({slop}) and max_odom_gap ({max_odom_gap}) must be >= 0 seconds")
        self.path = Path(bag_path)
        self.topics = topics
        self.decode_compressed = decode_compressed
        self.progress = progress
        self.stats = ReadStats()
        self._slop_ns = round(slop * NS_PER_S)
        self._max_gap_ns = round(max_odom_gap * NS_PER_S)
        self._min_cameras = min(max(min_cameras, 0), len(topics.cameras))
        self._plans: list[FramePlan] = []
        self._odom_stamps = np.zeros(0, dtype=np.int64)
        self._odom_poses = np.zeros((0, 4, 4))
        self._index()
        self._iterator: Generator[SensorFrame, None, None] | None = None

    def __len__(self) -> int:
        return len(self._plans)

    def close(self) -> None:
        """Stop early and release the bag (iterating to the end does this too)."""
        if self._iterator is not None:
            self._iterator.close()

    def __enter__(self) -> FrameStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> FrameStream:
        return self

    def __next__(self) -> SensorFrame:
        if self._iterator is None:
            self._iterator = self._frames()
        return next(self._iterator)

    # -- pass 1 ----------------------------------------------------------------------------
    def _index(self) -> None:
        t = self.topics
        ncam = len(t.cameras)
        with open_bag(self.path) as reader:
            types = topic_types(reader)
            check_topic(types, t.lidar, (CLOUD,), required=True)
            for topic in t.cameras:
                check_topic(types, topic, (IMAGE, COMPRESSED), required=True)
            depth_on = [check_topic(types, x, (IMAGE,), required=False) for x in t.depth]
            labels_on = [check_topic(types, x, (IMAGE,), required=False) for x in t.labels]
            self.stats.odometry_topic = bool(t.odom) and check_topic(types, t.odom, (ODOMETRY,), required=False)

            tracks: dict[str, MonotonicFilter] = {t.lidar: MonotonicFilter.new()}
            for topic in (*t.cameras, *[x for x, on in zip(t.depth, depth_on, strict=True) if on],
                          *[x for x, on in zip(t.labels, labels_on, strict=True) if on]):
                tracks[topic] = MonotonicFilter.new()
            odom = MonotonicFilter.new()
            poses: list[np.ndarray] = []
            wanted = set(tracks) | ({t.odom} if self.stats.odometry_topic else set())
            connections = [c for c in reader.connections if c.topic in wanted]
            ordinals: dict[str, int] = {}
            for connection, _log_ns, raw in reader.messages(connections=connections):
                topic = connection.topic
                ordinal = ordinals.get(topic, 0)
                ordinals[topic] = ordinal + 1
                if topic == t.odom and topic not in tracks:
                    msg = typestore().deserialize_cdr(raw, connection.msgtype)
                    if odom.offer(ordinal, header_stamp_ns(raw)):
                        poses.append(odometry_to_pose(msg))
                    continue
                tracks[topic].offer(ordinal, header_stamp_ns(raw))

        self.stats.clouds = ordinals.get(t.lidar, 0)
        cloud_track = tracks[t.lidar]
        self.stats.duplicate_clouds = cloud_track.duplicates
        self.stats.out_of_order_clouds = cloud_track.out_of_order
        self.stats.duplicate_images = [tracks[x].duplicates for x in t.cameras]
        self.stats.out_of_order_images = [tracks[x].out_of_order for x in t.cameras]

        def track_of(names: tuple[str, ...], index: int) -> tuple[np.ndarray, np.ndarray] | None:
            return tracks[names[index]].arrays() if index < len(names) and names[index] in tracks else None

        plans, no_camera, missing = plan_frames(
            cloud_track.arrays(),
            [tracks[x].arrays() for x in t.cameras],
            [track_of(t.depth, k) for k in range(ncam)],
            [track_of(t.labels, k) for k in range(ncam)],
            slop_ns=self._slop_ns,
            min_cameras=self._min_cameras,
        )
        self._plans = plans
        self.stats.no_camera = no_camera
        self.stats.camera_missing = missing
        self.stats.frames = len(plans)
        self._odom_stamps = np.asarray(odom.kept_stamps, dtype=np.int64)
        self._odom_poses = np.asarray(poses).reshape(-1, 4, 4)
        self._poses = [self._pose_for(p.stamp_ns) for p in plans]
        self.stats.no_pose = sum(p is None for p in self._poses)

    def _pose_for(self, stamp_ns: int) -> np.ndarray | None:
        return pose_at(self._odom_stamps, self._odom_poses, stamp_ns, slop_ns=self._slop_ns,
                       max_gap_ns=self._max_gap_ns)

    # -- pass 2 ----------------------------------------------------------------------------
    def _wanted(self) -> dict[str, dict[int, list[_Slot]]]:
        t = self.topics
        wanted: dict[str, dict[int, list[_Slot]]] = {}

        def want(topic: str, ordinal: int, slot: _Slot) -> None:
            wanted.setdefault(topic, {}).setdefault(ordinal, []).append(slot)

        for n, plan in enumerate(self._plans):
            want(t.lidar, plan.cloud_ordinal, _Slot(n, "cloud"))
            for k, ordinal in enumerate(plan.cameras):
                if ordinal >= 0:
                    want(t.cameras[k], ordinal, _Slot(n, "camera", k))
                if plan.depth[k] >= 0:
                    want(t.depth[k], plan.depth[k], _Slot(n, "depth", k))
                if plan.labels[k] >= 0:
                    want(t.labels[k], plan.labels[k], _Slot(n, "labels", k))
        return wanted

    def _frames(self) -> Generator[SensorFrame, None, None]:
        if not self._plans:
            return
        wanted = self._wanted()
        remaining = [sum(1 for _ in self._slots_of(plan)) for plan in self._plans]
        parts: dict[int, dict[tuple[str, int], Any]] = {}
        next_frame = 0
        bar = progress_bar(len(self._plans), desc="frames", unit="frame", enabled=self.progress)
        try:
            with open_bag(self.path) as reader:
                connections = [c for c in reader.connections if c.topic in wanted]
                ordinals: dict[str, int] = {}
                for connection, _log_ns, raw in reader.messages(connections=connections):
                    topic = connection.topic
                    ordinal = ordinals.get(topic, 0)
                    ordinals[topic] = ordinal + 1
                    slots = wanted[topic].pop(ordinal, None)
                    if slots is None:
                        continue
                    msg = typestore().deserialize_cdr(raw, connection.msgtype)
                    value = self._convert(slots[0].kind, msg)
                    for slot in slots:
                        parts.setdefault(slot.frame, {})[(slot.kind, slot.camera)] = value
                        remaining[slot.frame] -= 1
                    while next_frame < len(self._plans) and remaining[next_frame] == 0:
                        yield self._assemble(next_frame, parts.pop(next_frame, {}))
                        next_frame += 1
                        bar.update(1)
                    if next_frame == len(self._plans):
                        return
        finally:
            bar.close()
        raise BagError(f"{self.path} changed while it was read: {len(self._plans) - next_frame} frames lost parts")

    @staticmethod
    def _slots_of(plan: FramePlan) -> Iterator[None]:
        yield None
        for ordinals in (plan.cameras, plan.depth, plan.labels):
            for ordinal in ordinals:
                if ordinal >= 0:
                    yield None

    def _convert(self, kind: str, msg: Any) -> Any:
        if kind == "cloud":
            return msg.header.frame_id, pointcloud2_to_array(msg)
        if kind == "camera":
            return msg
        if kind == "depth":
            return depth_to_metres(msg)
        pixels = image_to_array(msg)
        return pixels.view(np.uint32) if pixels.dtype == np.int32 else pixels

    def _assemble(self, n: int, parts: dict[tuple[str, int], Any]) -> SensorFrame:
        plan = self._plans[n]
        lidar_frame, cloud = parts[("cloud", -1)]
        cameras: list[CameraImage | None] = []
        for k, ordinal in enumerate(plan.cameras):
            if ordinal < 0:
                cameras.append(None)
                continue
            msg = parts[("camera", k)]
            cameras.append(self._camera_image(msg, parts.get(("depth", k)), parts.get(("labels", k))))
        extras: dict[str, object] = {"stamp_ns": plan.stamp_ns}
        if cloud.ndim == 2:
            extras["cloud_shape"] = cloud.shape
        return SensorFrame(
            stamp=plan.stamp_ns / NS_PER_S,
            cameras=cameras,
            cloud=cloud.reshape(-1),
            lidar_frame_id=str(lidar_frame),
            pose=self._poses[n],
            extras=extras,
        )

    def _camera_image(self, msg: Any, depth: np.ndarray | None, labels: np.ndarray | None) -> CameraImage:
        stamp = (int(msg.header.stamp.sec) * NS_PER_S + int(msg.header.stamp.nanosec)) / NS_PER_S
        frame_id = str(msg.header.frame_id)
        if msg.__msgtype__ == COMPRESSED:
            if self.decode_compressed:
                pixels = compressed_to_array(msg)
                rgb = pixels if pixels.ndim == 3 else image_to_rgb(msg)
                return CameraImage(stamp, frame_id, rgb=rgb, depth=depth, labels=labels)
            return CameraImage(stamp, frame_id, jpeg=compressed_bytes(msg), depth=depth, labels=labels)
        return CameraImage(stamp, frame_id, rgb=image_to_rgb(msg), depth=depth, labels=labels)


def read_frames(
    bag_path: str | os.PathLike[str],
    *,
    topics: Topics,
    slop: float = 0.05,
    min_cameras: int = 1,
    max_odom_gap: float = 1.0,
    decode_compressed: bool = False,
    progress: bool = False,
) -> FrameStream:
    """Synchronised frames of a rosbag2 (sqlite3 or mcap), one per kept cloud, in cloud order.

    * each camera: the image nearest the cloud's header stamp within ``slop`` seconds,
      else None; clouds with fewer than ``min_cameras`` images (default 1) are dropped;
    * compressed images keep their encoded bytes in ``CameraImage.jpeg`` (JPEG or PNG)
      unless ``decode_compressed``; raw images become RGB;
    * depth (metres) and labels are matched to the chosen camera image within ``slop``;
    * pose: odometry at the cloud stamp, interpolated between neighbours at most
      ``max_odom_gap`` seconds apart, else the nearest within ``slop``, else None;
    * organised clouds are flattened row-major (``extras["cloud_shape"]`` keeps the
      shape); ``extras["stamp_ns"]`` is the exact cloud stamp.

    The returned :class:`FrameStream` is an iterator whose ``stats`` (a
    :class:`ReadStats`) already counts what was dropped and why.
    """
    return FrameStream(
        bag_path, topics=topics, slop=slop, min_cameras=min_cameras, max_odom_gap=max_odom_gap,
        decode_compressed=decode_compressed, progress=progress,
    )
