"""Building LCPR's training cache from rosbag2 drives (the format: :mod:`lcpr_core.lcpr.training.cache`).

Every synchronised frame with a pose is preprocessed once, straight into the cache's memory maps
(building needs memory for one frame): each camera resized to the training resolution as
:func:`lcpr_core.lcpr.preprocess.camera_tensor` does before normalising, the cloud as a range image
of the inputs' preset. A cache whose meta.json matches the request is reused as is.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.progress import progress_bar
from lcpr_core.errors import CacheError
from lcpr_core.lcpr.preprocess import lidar_preset, range_image
from lcpr_core.lcpr.preprocess.camera import to_pil
from lcpr_core.lcpr.training.cache import ARRAYS, SampleCache, cache_meta, open_cache, same_meta
from lcpr_core.lcpr.training.config import InputConfig
from msg_tools.bags import read_frames
from msg_tools.frames import KITTI_TOPICS, NUSCENES_TOPICS

__all__ = ["build_cache"]


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
        if same_meta({k: v for k, v in cache.meta.items() if k in meta}, meta):
            return cache
    if workers > 1 and len(bags) > 1:
        return _build_in_parts(bags, root, meta, inputs=inputs, progress=progress, workers=workers)
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


