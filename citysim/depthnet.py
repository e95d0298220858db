"""The depth a monocular depth network would publish, made from the renderer's exact depth.

VSeq2PC estimates each image's dense depth with a network. Such depth is trusted only to some
range and its error is smooth over the image (a whole facade is too near or too far together), not
independent per pixel. The KITTI rig therefore publishes, by default, depth cut at ``max_depth``
metres along the optical axis (0 = no estimate beyond it) with a smooth relative error of ``noise``
(one sigma, every pixel), correlated over about ``cell`` pixels.
"""
from __future__ import annotations

import numpy as np

#: KITTI rig defaults: about where a monocular depth network's error passes 10 % on KITTI.
DEPTH_RANGE = 25.0
DEPTH_NOISE = 0.1
NOISE_CELL = 32  # pixels between the smooth error field's lattice points


def smooth_field(shape: tuple[int, int], *, cell: int, rng: np.random.Generator) -> np.ndarray:
    """H x W float64 field, N(0, 1) at every pixel, bilinear between lattice points ``cell`` pixels apart."""
    H, W = shape
    lattice = rng.standard_normal((H // cell + 2, W // cell + 2))
    v, u = np.arange(H) / cell, np.arange(W) / cell
    v0, u0 = np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)
    b, a = (v - v0)[:, None], (u - u0)[None, :]
    field = ((1 - b) * (1 - a) * lattice[v0][:, u0] + (1 - b) * a * lattice[v0][:, u0 + 1]
             + b * (1 - a) * lattice[v0 + 1][:, u0] + b * a * lattice[v0 + 1][:, u0 + 1])
    # bilinear weights shrink the variance between lattice points; give every pixel unit variance again
    return field / np.sqrt(((1 - b) ** 2 + b ** 2) * ((1 - a) ** 2 + a ** 2))


def estimated_depth(depth: np.ndarray, *, max_depth: float, noise: float, rng: np.random.Generator,
                    cell: int = NOISE_CELL) -> np.ndarray:
    """H x W exact depth (m along the optical axis, 0 = none) -> what a depth network would give.

    ``max_depth`` <= 0 keeps every range; ``noise`` 0 keeps the exact values.
    """
    if noise < 0 or noise >= 1:
        raise ValueError(f"depth noise {noise}; it must lie in [0, 1)")
    d = np.asarray(depth, dtype=np.float32)
    out = d.copy()
    if max_depth > 0:
        out[out > max_depth] = 0.0  # the network's estimate is not trusted beyond its range
    if noise > 0:
        scale = np.maximum(1.0 + noise * smooth_field(d.shape, cell=cell, rng=rng), 0.05)
        out = np.where(out > 0, out * scale, 0.0).astype(np.float32)
    return out
