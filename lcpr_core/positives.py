"""The positive-pair rule of LCPR's ground truth, metrics and training: two places are the same place
(a true loop, a training positive) when their positions lie within ``radius`` of each other,
Euclidean in as many dimensions as the positions have (3-D keyframe positions; 2-D where only x, y
are known). VSeq2PC's pairs follow its paper instead (planar distance < 3 m, ``vseq2pc/pairs.py``).
"""
from __future__ import annotations

import numpy as np


def within_radius(offsets: np.ndarray, radius: float) -> np.ndarray:
    """``offsets`` (..., D) between two places' positions -> (...) True where they are the same place."""
    return (np.asarray(offsets) ** 2).sum(axis=-1) <= radius * radius
