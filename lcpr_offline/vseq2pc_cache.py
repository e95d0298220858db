"""``vseq2pc_cache``: a KITTI-like rosbag2 read into a VSeq2PC feature cache (:mod:`lcpr_core.vseq2pc.dataset`).

The bag's labelled clouds give the LiDAR structure features; its first camera's depth and label
images, back-projected with the CameraInfo intrinsics and moved into the LiDAR frame by
/tf_static, give the camera features; odometry gives the poses (frames without one are left out).
"""
from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from lcpr_core.errors import InvalidValueError
from lcpr_core.vseq2pc.dataset import FeatureCache, summary
from lcpr_core.vseq2pc.preprocess import camera_feature, structure_feature
from msg_tools import KITTI_TOPICS, SensorFrame, Topics, read_camera_models, read_frames
from msg_tools.bags import read_static_transforms
from msg_tools.errors import MsgToolsError

__all__ = ["build_cache", "cache_from_frames", "camera_extrinsics", "main"]


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


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vseq2pc_cache", description="Read a KITTI-like rosbag2 (depth and label "
                                "images, labelled clouds, odometry) into a VSeq2PC feature cache (.npz).")
    p.add_argument("bag", type=Path,
                   help="rosbag2 folder (e.g. from citysim --rig kitti or msg_tools_kitti2bag)")
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
