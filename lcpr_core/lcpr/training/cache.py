"""Preprocess bags once into memory-mapped arrays, so training epochs never decode JPEGs again.

Layout of a cache folder (numpy .npy files, opened with ``mmap_mode='r'``):

* ``images.npy``  N x C x H x W x 3 uint8, each camera resized (PIL bilinear) to the
  training resolution, exactly as :func:`lcpr_core.lcpr.preprocess.camera_tensor` does
  before normalising;
* ``cameras.npy`` N x C bool, False where the camera sent nothing (its input is zeros);
* ``ranges.npy``  N x h x w float16 range images (metres, -1 = empty);
* ``poses.npy``   N x 4 x 4 float64 world_T_base; ``stamps.npy`` N float64;
  ``groups.npy``  N int32, the index of the bag a sample came from;
* ``meta.json``   the inputs configuration, the bags (path, size, mtime) it was built from and
  ``samples``, the number of filled rows (frames without a pose leave rows unused).

Frames are written straight into the memory maps, so building needs memory for one frame.

A cache whose meta.json matches the request is reused as is.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msg_tools.progress import progress_bar

from ...errors import CacheError
from ..preprocess import lidar_preset, range_image
from ..preprocess.camera import to_pil
from .config import InputConfig

CACHE_VERSION = 1
ARRAYS = ("images", "cameras", "ranges", "poses", "stamps", "groups")


@dataclass(frozen=True)
class SampleCache:
    """The arrays of a cache folder (memory-mapped, read-only)."""

    folder: Path
    images: np.ndarray
    cameras: np.ndarray
    ranges: np.ndarray
    poses: np.ndarray
    stamps: np.ndarray
    groups: np.ndarray
    meta: dict[str, Any]

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        """N x 2 planar positions (x, y) in each bag's world frame."""
        return np.asarray(self.poses[:, :2, 3], np.float64)


def bag_signature(bag: str | os.PathLike[str]) -> dict[str, Any]:
    """Path, total size and newest mtime of a bag folder or file (detects a changed bag)."""
    path = Path(bag)
    if not path.exists():
        raise CacheError(f"bag {str(path)!r} does not exist")
    files = [p for p in path.rglob("*") if p.is_file()] if path.is_dir() else [path]
    return {"path": str(path.resolve()), "bytes": sum(p.stat().st_size for p in files),
            "mtime": max((p.stat().st_mtime for p in files), default=0.0)}


def cache_meta(bags: Sequence[str | os.PathLike[str]], inputs: InputConfig) -> dict[str, Any]:
    return {"version": CACHE_VERSION, "inputs": dataclasses.asdict(inputs) | {"width": None},
            "bags": [bag_signature(b) for b in bags]}


def _same_meta(a: dict[str, Any], b: dict[str, Any]) -> bool:
    return json.loads(json.dumps(a)) == json.loads(json.dumps(b))


def open_cache(folder: str | os.PathLike[str]) -> SampleCache:
    """Open an existing cache folder (memory-mapped)."""
    root = Path(folder)
    meta_path = root / "meta.json"
    if not meta_path.is_file():
        raise CacheError(f"{str(root)!r} is not a training cache (no meta.json)")
    meta = json.loads(meta_path.read_text())
    arrays = {name: np.load(root / f"{name}.npy", mmap_mode="r") for name in ARRAYS}
    count = int(meta.get("samples", len(arrays["stamps"])))  # rows past the count were never filled
    arrays = {name: array[:count] for name, array in arrays.items()}
    return SampleCache(folder=root, meta=meta, **arrays)


def build_cache(
    bags: Sequence[str | os.PathLike[str]],
    folder: str | os.PathLike[str],
    *,
    inputs: InputConfig,
    progress: bool = True,
    rebuild: bool = False,
    workers: int = 1,
) -> SampleCache:
    """Preprocess every synchronised frame with a pose of ``bags`` into ``folder`` (reused when up to date).

    ``workers`` > 1 preprocesses that many bags at a time in separate processes, each into a
    one-bag cache, then joins them in the order given: the same arrays as one process makes.
    """
    if not bags:
        raise CacheError("no bags given; expected at least one rosbag2 with cameras, LiDAR and odometry")
    if workers < 1:
        raise CacheError(f"workers={workers}; it must be at least 1 (processes preprocessing bags at a time)")
    root = Path(folder)
    meta = cache_meta(bags, inputs)
    if not rebuild and (root / "meta.json").is_file():
        cache = open_cache(root)
        if _same_meta({k: v for k, v in cache.meta.items() if k in meta}, meta):
            return cache
    if workers > 1 and len(bags) > 1:
        return _build_in_parts(bags, root, meta, inputs=inputs, progress=progress, workers=workers)
    # Import here: msg_tools is only needed to build a cache, not to train from one.
    from msg_tools.bags import read_frames
    from msg_tools.frames import KITTI_TOPICS, NUSCENES_TOPICS

    topics = NUSCENES_TOPICS if inputs.num_cameras == len(NUSCENES_TOPICS.cameras) else KITTI_TOPICS
    if inputs.num_cameras != len(topics.cameras):
        raise CacheError(f"num_cameras={inputs.num_cameras}; accepted: 6 (nuScenes topics) or 1 (KITTI topics)")
    preset = dataclasses.replace(lidar_preset(inputs.lidar), height=inputs.range_size[0],
                                 width=inputs.range_size[1])
    start = time.perf_counter()
    tmp = _partial_folder(root)
    streams = [read_frames(bag, topics=topics, decode_compressed=False) for bag in bags]
    capacity = sum(len(s) for s in streams)  # frames without a pose are skipped: rows past the count stay unused
    (h, w), (rh, rw), c = inputs.image_size, inputs.range_size, inputs.num_cameras
    arrays = {
        "images": np.lib.format.open_memmap(tmp / "images.npy", "w+", np.uint8, (capacity, c, h, w, 3)),
        "cameras": np.lib.format.open_memmap(tmp / "cameras.npy", "w+", np.bool_, (capacity, c)),
        "ranges": np.lib.format.open_memmap(tmp / "ranges.npy", "w+", np.float16, (capacity, rh, rw)),
        "poses": np.lib.format.open_memmap(tmp / "poses.npy", "w+", np.float64, (capacity, 4, 4)),
        "stamps": np.lib.format.open_memmap(tmp / "stamps.npy", "w+", np.float64, (capacity,)),
        "groups": np.lib.format.open_memmap(tmp / "groups.npy", "w+", np.int32, (capacity,)),
    }
    count, frames, without_pose = 0, 0, 0
    per_bag: list[int] = []
    for group, (bag, stream) in enumerate(zip(bags, streams, strict=True)):
        bar = progress_bar(len(stream), desc=f"cache {Path(bag).name}", unit="frame", enabled=progress)
        first = count
        try:
            for frame in stream:
                bar.update(1)
                frames += 1
                if frame.pose is None or not np.isfinite(frame.pose).all():
                    without_pose += 1
                    continue
                arrays["images"][count], arrays["cameras"][count] = _camera_slots(frame.cameras, inputs)
                arrays["ranges"][count] = range_image(frame.xyz, preset=preset)
                arrays["poses"][count] = frame.pose
                arrays["stamps"][count] = frame.stamp
                arrays["groups"][count] = group
                count += 1
        finally:
            stream.close()
            bar.close()
        per_bag.append(count - first)
    for array in arrays.values():
        array.flush()
    del arrays
    if count == 0:
        shutil.rmtree(tmp, ignore_errors=True)
        raise CacheError(f"no frame with a pose in {', '.join(map(str, bags))} ({frames} frames read); "
                         f"training needs odometry (ground-truth poses)")
    meta |= {"samples": count, "samples_per_bag": per_bag, "frames_read": frames, "without_pose": without_pose,
             "build_seconds": round(time.perf_counter() - start, 1)}
    return _publish(tmp, root, meta)


def _partial_folder(root: Path) -> Path:
    """An empty folder beside ``root`` to build into (a leftover of an interrupted build is removed)."""
    tmp = root.with_name(root.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    return tmp


def _publish(tmp: Path, root: Path, meta: dict[str, Any]) -> SampleCache:
    """Write ``meta`` into the finished ``tmp`` folder, put it in place of ``root`` and open it."""
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    shutil.rmtree(root, ignore_errors=True)
    os.replace(tmp, root)
    return open_cache(root)


def _build_in_parts(bags: Sequence[str | os.PathLike[str]], root: Path, meta: dict[str, Any], *,
                    inputs: InputConfig, progress: bool, workers: int) -> SampleCache:
    """One-bag caches built ``workers`` at a time, joined into ``root`` (bag k's rows are group k)."""
    from concurrent.futures import ProcessPoolExecutor

    start = time.perf_counter()
    tmp = _partial_folder(root)
    folders = [tmp / f"bag{k}" for k in range(len(bags))]
    with ProcessPoolExecutor(max_workers=min(workers, len(bags))) as pool:
        jobs = [pool.submit(build_cache, [bag], part, inputs=inputs, progress=False)
                for bag, part in zip(bags, folders, strict=True)]
        bar = progress_bar(len(jobs), desc="cache bags", unit="bag", enabled=progress)
        parts: list[SampleCache] = []
        for job in jobs:  # in order: the first error raised is the first bag's
            parts.append(job.result())
            bar.update(1)
        bar.close()
    count = sum(len(p) for p in parts)
    joined = {name: np.lib.format.open_memmap(tmp / f"{name}.npy", "w+", getattr(parts[0], name).dtype,
                                              (count, *getattr(parts[0], name).shape[1:])) for name in ARRAYS}
    row = 0
    for group, part in enumerate(parts):
        rows = slice(row, row + len(part))
        for name in ARRAYS:
            joined[name][rows] = group if name == "groups" else getattr(part, name)
        row += len(part)
    for array in joined.values():
        array.flush()
    del joined
    part_meta = [p.meta for p in parts]
    del parts
    for folder in folders:
        shutil.rmtree(folder)
    meta |= {"samples": count, "samples_per_bag": [m["samples"] for m in part_meta],
             "frames_read": sum(m["frames_read"] for m in part_meta),
             "without_pose": sum(m["without_pose"] for m in part_meta),
             "build_seconds": round(time.perf_counter() - start, 1)}
    return _publish(tmp, root, meta)


def _camera_slots(cameras: Sequence[Any], inputs: InputConfig) -> tuple[np.ndarray, np.ndarray]:
    """Camera images of one frame -> C x H x W x 3 uint8 (resized) and C presence flags."""
    h, w = inputs.image_size
    out = np.zeros((inputs.num_cameras, h, w, 3), np.uint8)
    present = np.zeros(inputs.num_cameras, bool)
    for k, cam in enumerate(list(cameras)[:inputs.num_cameras]):
        data = None if cam is None else (cam.jpeg if cam.jpeg is not None else cam.rgb)
        if data is None:
            continue
        from PIL import Image

        out[k] = np.asarray(to_pil(data).resize((w, h), Image.Resampling.BILINEAR), dtype=np.uint8)
        present[k] = True
    return out, present


