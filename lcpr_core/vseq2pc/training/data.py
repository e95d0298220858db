"""Training data: feature caches laid side by side, split into training and validation frames."""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..dataset import FeatureCache
from ..preprocess import CAMERA_SECTORS
from .config import DRIVE_SPACING_M

log = logging.getLogger("lcpr_core.vseq2pc.training")

# ---------------------------------------------------------------------- data
@dataclass
class TrainData:
    """Tensors of a cache and which frames are training / validation queries and scans."""

    camera: torch.Tensor  # (N, 12, 90)
    lidar: torch.Tensor  # (N, 12, 360)
    positions: np.ndarray  # (N, 3)
    sequences: np.ndarray  # (N, 4), -1 = incomplete
    queries: np.ndarray  # frame indices with a complete sequence
    scans: np.ndarray  # frame indices usable as scans

    @classmethod
    def from_cache(cls, cache: FeatureCache, rows: np.ndarray | None = None) -> TrainData:
        seq = cache.sequences()
        complete = np.flatnonzero(seq[:, 0] >= 0)
        scans = np.arange(len(cache))
        if rows is not None:
            keep = np.zeros(len(cache), bool)
            keep[rows] = True
            complete, scans = complete[keep[complete]], scans[keep]
        return cls(torch.from_numpy(cache.camera), torch.from_numpy(cache.lidar), cache.positions, seq, complete, scans)

    @classmethod
    def concat(cls, drives: Sequence[TrainData]) -> TrainData:
        """One dataset of several drives: frame indices renumbered, drive k moved k x ``DRIVE_SPACING_M`` in x."""
        if len(drives) == 1:
            return drives[0]
        starts = np.cumsum([0] + [len(d.positions) for d in drives[:-1]])
        positions = [d.positions + np.array([k * DRIVE_SPACING_M, 0.0, 0.0]) for k, d in enumerate(drives)]
        sequences = [np.where(d.sequences >= 0, d.sequences + s, -1) for d, s in zip(drives, starts, strict=True)]
        return cls(torch.cat([d.camera for d in drives]), torch.cat([d.lidar for d in drives]),
                   np.concatenate(positions), np.concatenate(sequences),
                   np.concatenate([d.queries + s for d, s in zip(drives, starts, strict=True)]),
                   np.concatenate([d.scans + s for d, s in zip(drives, starts, strict=True)]))

    def frames(self, queries: np.ndarray) -> torch.Tensor:
        """B x 4 x 12 x 90 camera-feature sequences of the query frames."""
        return self.camera[torch.from_numpy(self.sequences[queries])]

    def target(self, queries: np.ndarray) -> torch.Tensor:
        """B x 12 x 90: the forward 90 degrees of each query frame's LiDAR feature."""
        return self.lidar[torch.from_numpy(np.asarray(queries))][:, :, CAMERA_SECTORS]


def split(caches: Sequence[FeatureCache], val_fraction: float) -> tuple[TrainData, TrainData | None]:
    """Of each drive, the first frames train and the last ``val_fraction`` give validation queries (against
    every scan of every drive)."""
    if val_fraction == 0:
        return TrainData.concat([TrainData.from_cache(c) for c in caches]), None
    train, val = [], []
    for cache in caches:
        cut = int(round(len(cache) * (1.0 - val_fraction)))
        train.append(TrainData.from_cache(cache, np.arange(cut)))
        whole = TrainData.from_cache(cache)
        whole.queries = whole.queries[whole.queries >= cut]
        val.append(whole)
    return TrainData.concat(train), TrainData.concat(val)
