"""Feature caches of drives: per frame the camera feature, the LiDAR structure feature and the pose.

Reading a bag (depth and label images, labelled clouds) takes minutes; training and
evaluation read the cache instead. One cache is one .npz (no pickle) holding

* ``camera`` (N, 12, 90) float32: the front camera's structure feature (depth + labels,
  back-projected with the intrinsics and moved into the LiDAR frame), zeros where the
  image was missing (``camera_valid`` False);
* ``lidar`` (N, 12, 360) float32: the labelled cloud's structure feature;
* ``poses`` (N, 4, 4) world_T_base, ``stamps`` (N,) seconds.

``vseq2pc_cache BAG --out CACHE.npz`` writes one (see :func:`main`).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msg_tools import KITTI_TOPICS, SensorFrame, Topics, read_camera_models, read_frames
from msg_tools.bags import read_static_transforms
from msg_tools.errors import MsgToolsError

from ..atomic import atomic_path
from ..errors import InputShapeError, InvalidValueError
from .preprocess import camera_feature, structure_feature
from .sequence import OFFSETS, sequence_table

__all__ = ["CACHE_SCHEMA_VERSION", "FeatureCache", "build_cache", "cache_from_frames", "camera_extrinsics", "main"]

log = logging.getLogger(__name__)
CACHE_SCHEMA_VERSION = 1
_FORMAT = "lcpr_core.vseq2pc_features"
_KEYS = ("header", "camera", "camera_valid", "lidar", "poses", "stamps")


@dataclass(frozen=True)
class FeatureCache:
    """Per-frame features of one drive, in driving order (see the module doc)."""

    camera: np.ndarray  # (N, 12, 90) float32
    camera_valid: np.ndarray  # (N,) bool
    lidar: np.ndarray  # (N, 12, 360) float32
    poses: np.ndarray  # (N, 4, 4) float64, world_T_base
    stamps: np.ndarray  # (N,) float64
    source: str = ""

    def __post_init__(self) -> None:
        n = len(self.stamps)
        want = {"camera": (n, 12, 90), "camera_valid": (n,), "lidar": (n, 12, 360), "poses": (n, 4, 4)}
        for name, shape in want.items():
            if getattr(self, name).shape != shape:
                raise InputShapeError(f"{name} has shape {getattr(self, name).shape}; expected {shape}")

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) base positions."""
        return self.poses[:, :3, 3]

    def sequences(self, *, offsets: Sequence[float] = OFFSETS) -> np.ndarray:
        """(N, 4) frame indices of each frame's query sequence, -1 rows where incomplete."""
        return sequence_table(self.positions, self.camera_valid, offsets=offsets)

    def subset(self, rows: np.ndarray) -> FeatureCache:
        r = np.asarray(rows)
        return FeatureCache(self.camera[r], self.camera_valid[r], self.lidar[r], self.poses[r], self.stamps[r],
                            self.source)

    def save(self, path: str | os.PathLike[str]) -> None:
        header = {"format": _FORMAT, "schema_version": CACHE_SCHEMA_VERSION, "count": len(self), "source": self.source}
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, header=np.array(json.dumps(header)), camera=self.camera, camera_valid=self.camera_valid,
                     lidar=self.lidar, poses=self.poses, stamps=self.stamps)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> FeatureCache:
        where = os.fspath(path)
        try:
            with np.load(where, allow_pickle=False) as npz:
                missing = [k for k in _KEYS if k not in npz.files]
                if missing:
                    raise InvalidValueError(
                        f"feature cache {where} lacks {', '.join(missing)}; expected {', '.join(_KEYS)}")
                data = {k: npz[k] for k in _KEYS}
        except FileNotFoundError as err:
            raise InvalidValueError(f"feature cache {where} does not exist (make one with vseq2pc_cache)") from err
        header = json.loads(str(data["header"].item()))
        if header.get("format") != _FORMAT or header.get("schema_version") != CACHE_SCHEMA_VERSION:
            raise InvalidValueError(
                f"{where} is not a {_FORMAT} file of schema {CACHE_SCHEMA_VERSION} (header {header})")
        return cls(camera=data["camera"].astype(np.float32), camera_valid=data["camera_valid"].astype(bool),
                   lidar=data["lidar"].astype(np.float32), poses=data["poses"].astype(np.float64),
                   stamps=data["stamps"].astype(np.float64), source=str(header.get("source", "")))


def camera_extrinsics(bag: str | os.PathLike[str], *, topics: Topics = KITTI_TOPICS, lidar_frame: str
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(K 3 x 3, lidar_T_cam 4 x 4) of the bag's first camera, from its CameraInfo and /tf_static."""
    models = read_camera_models(bag, topics=topics)
    if not models or models[0] is None:
        raise InvalidValueError(f"{os.fspath(bag)} has no CameraInfo on {topics.camera_info[:1]}; the camera "
                                "intrinsics are needed to back-project depth")
    model = models[0]
    base_T_lidar = read_static_transforms(bag, topic=topics.tf_static).lookup("base_link", lidar_frame)
    if base_T_lidar is None:
        raise InvalidValueError(f"{os.fspath(bag)}: no {topics.tf_static} transform base_link -> {lidar_frame!r}")
    return np.asarray(model.K, np.float64), np.linalg.inv(base_T_lidar) @ np.asarray(model.base_T_cam, np.float64)


def cache_from_frames(frames: Iterable[SensorFrame], *, K: np.ndarray, lidar_T_cam: np.ndarray,
                      camera: int = 0, source: str = "") -> FeatureCache:
    """Features of SensorFrames (labelled clouds; camera ``camera`` with depth and labels; poses)."""
    cams, valid, lidars, poses, stamps = [], [], [], [], []
    for frame in frames:
        if frame.pose is None:
            continue  # no ground truth: neither a query nor a database scan can be labelled
        names = frame.cloud.dtype.names or ()
        if "label" not in names:
            raise InvalidValueError(f"the cloud at {frame.stamp:.3f} s has fields {names}; VSeq2PC needs per-point "
                                    "SemanticKITTI labels ('label')")
        lidars.append(structure_feature(frame.xyz, np.asarray(frame.cloud["label"])))
        image = frame.cameras[camera] if camera < len(frame.cameras) else None
        if image is not None and image.depth is not None and image.labels is not None:
            cams.append(camera_feature(image.depth, image.labels, K, lidar_T_cam))
            valid.append(True)
        else:
            cams.append(np.zeros((12, 90), np.float32))
            valid.append(False)
        poses.append(np.asarray(frame.pose, np.float64))
        stamps.append(frame.stamp)
    if not stamps:
        raise InvalidValueError("no frame with a pose; a feature cache needs ground-truth poses")
    return FeatureCache(camera=np.stack(cams).astype(np.float32), camera_valid=np.array(valid, bool),
                        lidar=np.stack(lidars).astype(np.float32), poses=np.stack(poses),
                        stamps=np.array(stamps, np.float64), source=source)


def build_cache(bag: str | os.PathLike[str], *, topics: Topics = KITTI_TOPICS, limit: int | None = None,
                progress: bool = False) -> FeatureCache:
    """Read a KITTI-like bag (depth + label images, labelled clouds, odometry) into a FeatureCache."""
    stream = read_frames(bag, topics=topics, progress=progress, min_cameras=0)  # keep scans without an image
    first: list[SensorFrame] = []
    frames = iter(stream)
    for frame in frames:
        first.append(frame)
        break
    if not first:
        raise InvalidValueError(f"{os.fspath(bag)} holds no synchronised frame on {topics.lidar} and {topics.cameras}")
    K, lidar_T_cam = camera_extrinsics(bag, topics=topics, lidar_frame=first[0].lidar_frame_id)

    def limited() -> Iterable[SensorFrame]:
        yield first[0]
        for i, frame in enumerate(frames, start=1):
            if limit is not None and i >= limit:
                return
            yield frame

    return cache_from_frames(limited(), K=K, lidar_T_cam=lidar_T_cam, source=os.fspath(bag))


def summary(cache: FeatureCache) -> dict[str, Any]:
    seq = cache.sequences()
    complete = seq[:, 0] >= 0
    steps = np.linalg.norm(np.diff(cache.positions[:, :2], axis=0), axis=1)
    return {"frames": len(cache), "camera_missing": int((~cache.camera_valid).sum()),
            "complete_queries": int(complete.sum()), "path_m": float(steps.sum()),
            "camera_fill": float((cache.camera[cache.camera_valid] > 0).mean()) if cache.camera_valid.any() else 0.0,
            "lidar_fill": float((cache.lidar > 0).mean())}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vseq2pc_cache", description="Read a KITTI-like rosbag2 (depth and label "
                                "images, labelled clouds, odometry) into a VSeq2PC feature cache (.npz).")
    p.add_argument("bag", type=Path,
                   help="rosbag2 folder (e.g. from msg_tools_synth --rig kitti or msg_tools_kitti2bag)")
    p.add_argument("--out", type=Path, required=True, help="cache file to write (.npz)")
    p.add_argument("--limit", type=int, default=None, help="read at most this many frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    try:
        cache = build_cache(args.bag, limit=args.limit, progress=not args.no_progress)
        cache.save(args.out)
    except (MsgToolsError, ValueError, OSError) as err:
        print(f"vseq2pc_cache: error: {err}", file=sys.stderr)
        return 2
    info = summary(cache)
    print(f"{args.out}: {info['frames']} frames ({info['camera_missing']} without camera), "
          f"{info['complete_queries']} complete query sequences, path {info['path_m']:.0f} m; "
          f"non-empty cells: camera {info['camera_fill']:.1%}, lidar {info['lidar_fill']:.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
