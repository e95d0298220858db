"""Feature caches of drives: per frame the camera feature, the LiDAR structure feature and the pose.

Reading a bag (depth and label images, labelled clouds) takes minutes; training and
evaluation read the cache instead. One cache is one .npz (no pickle) holding

* ``camera`` (N, 12, 90) float32: the front camera's structure feature (depth + labels,
  back-projected with the intrinsics and moved into the LiDAR frame), zeros where the
  image was missing (``camera_valid`` False);
* ``lidar`` (N, 12, 360) float32: the labelled cloud's structure feature;
* ``poses`` (N, 4, 4) world_T_base, ``stamps`` (N,) seconds.

This module is the format; ``vseq2pc_cache BAG --out CACHE.npz`` (:mod:`lcpr_offline.vseq2pc_cache`)
writes one from a bag.
"""
from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..atomic import atomic_path
from ..errors import InputShapeError, InvalidValueError
from .sequence import OFFSETS, sequence_table

__all__ = ["CACHE_SCHEMA_VERSION", "FeatureCache", "summary"]

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


def summary(cache: FeatureCache) -> dict[str, Any]:
    """Frames, missing cameras, complete query sequences, path length and how full the features are."""
    seq = cache.sequences()
    complete = seq[:, 0] >= 0
    steps = np.linalg.norm(np.diff(cache.positions[:, :2], axis=0), axis=1)
    return {"frames": len(cache), "camera_missing": int((~cache.camera_valid).sum()),
            "complete_queries": int(complete.sum()), "path_m": float(steps.sum()),
            "camera_fill": float((cache.camera[cache.camera_valid] > 0).mean()) if cache.camera_valid.any() else 0.0,
            "lidar_fill": float((cache.lidar > 0).mean())}
