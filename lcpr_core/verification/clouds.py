"""Compact keyframe clouds: what the verifier registers, and what a map keeps per keyframe.

A cloud is cropped by range, voxel-downsampled (the centroid of each voxel, small_gicp's
voxel grid: smoother surfaces than keeping one raw point per voxel, which registers and
discriminates worse), capped at ``max_points`` (an evenly spaced subset) and quantised
to int16 centimetres: 6 bytes a point, at most 6 * max_points bytes per keyframe
(48 KiB at the defaults) plus 16 bytes of bookkeeping. A 1-hour drive with a 360-degree
LiDAR and a keyframe a second keeps at most ~170 MiB of clouds; a 70-degree Livox keeps
1-3 thousand points a keyframe (6-18 KiB).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import small_gicp

from ..errors import VerificationError
from ..growable import GrowableArray
from ..points import finite_xyz
from .config import CloudConfig

SCALE = 0.01  # m per int16 unit
_LIMIT = 32767


def compact_cloud(points: np.ndarray, config: CloudConfig | None = None) -> np.ndarray:
    """N x (>=3) points -> M x 3 float32 (M <= max_points), on the int16 centimetre grid.

    Non-finite points and points outside [min_range, max_range] are dropped. The
    result is what :class:`CloudStore` keeps (bit-identical when read back). Compacting
    a compact cloud again moves a few points (centroids of centimetre-rounded centroids):
    registration code uses the stored cloud as it is.
    """
    cfg = config if config is not None else CloudConfig()
    xyz = finite_xyz(points, error=VerificationError)
    dist = np.linalg.norm(xyz, axis=1)
    xyz = xyz[(dist >= cfg.min_range) & (dist <= cfg.max_range)]
    if len(xyz) == 0:
        return np.zeros((0, 3), np.float32)
    return dequantise(quantise(voxel_cap(xyz, cfg.voxel, cfg.max_points)))


def voxel_cap(xyz: np.ndarray, voxel: float, max_points: int) -> np.ndarray:
    """N x 3 points -> the centroids of their ``voxel`` grid (float64), at most ``max_points`` of them (an
    evenly spaced subset): a cloud's size bounded whatever the sensor."""
    down = small_gicp.voxelgrid_sampling(np.ascontiguousarray(xyz, np.float64), voxel,
                                         num_threads=1).points()[:, :3]  # 1 thread: deterministic
    if len(down) > max_points:
        down = down[np.linspace(0, len(down) - 1, max_points).round().astype(np.int64)]
    return down


def quantise(xyz: np.ndarray) -> np.ndarray:
    """M x 3 metres -> M x 3 int16 centimetres (clipped to +-327.67 m)."""
    return np.clip(np.round(np.asarray(xyz, np.float64) / SCALE), -_LIMIT, _LIMIT).astype(np.int16)


def dequantise(q: np.ndarray) -> np.ndarray:
    return (np.asarray(q, np.float32) * np.float32(SCALE)).astype(np.float32)


class CloudStore:
    """Compact clouds by keyframe id (int16 centimetres in one growing array).

    Not thread-safe (lives beside the descriptor map, behind the same lock).
    """

    def __init__(self) -> None:
        self._points = GrowableArray(np.int16, (3,))
        self._ids = GrowableArray(np.int64)
        self._counts = GrowableArray(np.int64)
        self._rows: dict[int, tuple[int, int]] = {}  # id -> (start, count)

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, keyframe_id: object) -> bool:
        return keyframe_id in self._rows

    @property
    def nbytes(self) -> int:
        """Bytes of the stored points and bookkeeping (what the clouds add to a map)."""
        return 6 * len(self._points) + 16 * len(self._ids)

    def add(self, keyframe_id: int, xyz: np.ndarray) -> None:
        """Keep the compact cloud (M x 3 metres, from :func:`compact_cloud`) of one keyframe."""
        key = int(keyframe_id)
        if key in self._rows:
            raise VerificationError(f"keyframe {key} already has a cloud; ids must be unique")
        q = quantise(np.asarray(xyz).reshape(-1, 3))
        self._rows[key] = (len(self._points), len(q))
        self._points.extend(q)
        self._ids.extend(np.array([key], np.int64))
        self._counts.extend(np.array([len(q)], np.int64))

    def get(self, keyframe_id: int) -> np.ndarray | None:
        """M x 3 float32 metres, or None when the keyframe has no cloud."""
        row = self._rows.get(int(keyframe_id))
        if row is None:
            return None
        start, count = row
        return dequantise(self._points.view()[start:start + count])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The arrays a map file stores: cloud_ids (K,), cloud_counts (K,), cloud_points (P x 3 int16)."""
        return {"cloud_ids": self._ids.view(), "cloud_counts": self._counts.view(), "cloud_points": self._points.view()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, Any], *, where: str) -> CloudStore:
        """Rebuild a store from :meth:`to_arrays`' arrays, checking their shapes and consistency."""
        ids, counts, points = (np.asarray(arrays[k]) for k in ("cloud_ids", "cloud_counts", "cloud_points"))
        if ids.ndim != 1 or ids.dtype.kind not in "iu" or counts.shape != ids.shape or counts.dtype.kind not in "iu":
            raise VerificationError(f"{where}: cloud_ids {ids.shape} {ids.dtype} / cloud_counts {counts.shape} "
                                    f"{counts.dtype}; expected two (K,) integer arrays")
        if points.ndim != 2 or points.shape[1] != 3 or points.dtype != np.int16:
            raise VerificationError(f"{where}: cloud_points {points.shape} {points.dtype}; expected P x 3 int16")
        if len(counts) and (counts.min() < 0 or int(counts.sum()) != len(points)):
            raise VerificationError(f"{where}: cloud_counts add up to {int(counts.sum())} but cloud_points holds "
                                    f"{len(points)} points")
        if len(np.unique(ids)) != len(ids):
            raise VerificationError(f"{where}: cloud_ids repeat; expected one cloud per keyframe")
        store = cls()
        store._points.extend(points)
        store._ids.extend(ids.astype(np.int64))
        store._counts.extend(counts.astype(np.int64))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, np.int64)
        store._rows = {int(i): (int(s), int(c)) for i, s, c in zip(ids, starts, counts, strict=True)}
        return store
