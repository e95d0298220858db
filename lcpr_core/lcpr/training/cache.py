"""The training cache: bags preprocessed once into memory-mapped arrays, so epochs never decode JPEGs again.

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

This module is the format and its reading; building one from bags is :mod:`lcpr_offline.lcpr_cache`
(frames are written straight into the memory maps, so building needs memory for one frame; a cache
whose meta.json matches the request is reused as is).
"""
from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import CacheError
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
    """What a cache of ``bags`` at ``inputs`` records in its meta.json: a cache is reused when these agree."""
    return {"version": CACHE_VERSION, "inputs": dataclasses.asdict(inputs) | {"width": None},
            "bags": [bag_signature(b) for b in bags]}


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


def same_meta(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two meta.json contents agree once both went through JSON (tuples and lists compare equal)."""
    return json.loads(json.dumps(a)) == json.loads(json.dumps(b))
