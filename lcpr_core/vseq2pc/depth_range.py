"""Camera structure features as a monocular depth network would give them: range-limited and noisy.

The synthetic city's KITTI rig can publish exact depth to any range; VSeq2PC's paper estimates
each image's dense depth with a network. :func:`limited_depth` rewrites the camera features of a
feature cache the way a range-limited, noisy depth would have made them; :func:`coverage` says how
much of the LiDAR's forward structure one camera frame holds. Used by the depth study
(``benchmarks/studies/vseq2pc_depth_range.py``, ``vseq2pc_depth_study.sh``).
"""
from __future__ import annotations

import numpy as np

from .preprocess import CAMERA_SECTORS, MAX_RANGE, ROAD_CHANNEL, SECTORS


def limited_depth(camera: np.ndarray, *, max_depth: float, noise: float, rng: np.random.Generator) -> np.ndarray:
    """N x 12 x 90 camera features -> the same as seen with depth up to ``max_depth`` m and relative ``noise``."""
    sectors = np.arange(SECTORS)[CAMERA_SECTORS]
    angle = np.deg2rad(sectors + 0.5 - SECTORS / 2)  # sector 180 is straight ahead
    r = camera.astype(np.float64) * MAX_RANGE  # N x 12 x 90, 0 = empty
    seen = r > 0
    r = np.where(seen, r * np.maximum(1.0 + noise * rng.standard_normal(r.shape), 0.05), 0.0)
    forward = r * np.cos(angle)  # depth along the optical axis
    too_far = seen & (forward > max_depth)
    out = np.where(too_far, 0.0, r)
    road = out[:, ROAD_CHANNEL]
    cut = too_far[:, ROAD_CHANNEL]
    road[cut] = np.broadcast_to(max_depth / np.cos(angle), road.shape)[cut]  # road reaches the depth limit
    return (np.clip(out, 0.0, MAX_RANGE) / MAX_RANGE).astype(np.float32)


def coverage(camera: np.ndarray, lidar: np.ndarray) -> tuple[float, float]:
    """(share of the LiDAR's forward cells the camera features hold, median range error there in m).

    camera: N x 12 x 90; lidar: N x 12 x 360 structure features of the same frames.
    """
    forward = lidar[:, :, CAMERA_SECTORS]
    both = (camera > 0) & (forward > 0)
    share = float(both.sum() / max(int((forward > 0).sum()), 1))
    error = float(np.median(np.abs(camera[both] - forward[both])) * MAX_RANGE) if both.any() else float("nan")
    return share, error
