"""Quaternions and pose interpolation on stacks of rotations: the one home for the core and the bag tools.

Quaternions are (x, y, z, w), as geometry_msgs orders them, with w >= 0. Nothing here validates its
input (NaN in, NaN out); :mod:`msg_tools.geometry` and :mod:`lcpr_core.backend` check theirs first.
"""
from __future__ import annotations

import numpy as np

__all__ = ["interpolate_poses", "quaternions_xyzw", "rotations_from_xyzw", "slerp_xyzw"]


def quaternions_xyzw(rotations: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w; w >= 0) of (..., 3, 3) rotations.

    Shepperd's method, each matrix through its largest component, so no branch divides by a small number.
    """
    r = np.asarray(rotations, np.float64)
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    squares = np.stack([1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22, 1 + r00 + r11 + r22],
                       axis=-1) / 4.0  # x^2, y^2, z^2, w^2
    a, b, c = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]  # 4w(x, y, z)
    d, e, f = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]  # 4xy, 4xz, 4yz
    k = np.argmax(np.nan_to_num(squares, nan=-1.0), axis=-1)
    big = 4.0 * np.take_along_axis(squares, k[..., None], -1)[..., 0]  # each branch is 4 q_k (x, y, z, w)
    with np.errstate(invalid="ignore"):
        branches = np.stack([np.stack([big, d, e, a], -1), np.stack([d, big, f, b], -1),
                             np.stack([e, f, big, c], -1), np.stack([a, b, c, big], -1)], axis=-2)
        q = np.take_along_axis(branches, k[..., None, None], -2)[..., 0, :]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0, -q, q)


def rotations_from_xyzw(quaternions: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations of (..., 4) unit quaternions (x, y, z, w)."""
    q = np.asarray(quaternions, np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def slerp_xyzw(qa: np.ndarray, qb: np.ndarray, w: np.ndarray | float) -> np.ndarray:
    """(..., 4) unit quaternions between ``qa`` (w = 0) and ``qb`` (w = 1) along the shortest arc."""
    a = np.asarray(qa, np.float64)
    b = np.asarray(qb, np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    t = np.asarray(w, np.float64)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    theta = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    near = theta < 1e-6  # parallel: the weights' limit, a normalised lerp
    sin = np.where(near, 1.0, np.sin(theta))
    ca = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / sin)
    cb = np.where(near, t, np.sin(t * theta) / sin)
    q = ca * a + cb * b
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_poses(a: np.ndarray, b: np.ndarray, w: np.ndarray | float) -> np.ndarray:
    """(..., 4, 4) poses between ``a`` (w = 0) and ``b`` (w = 1): translation linearly, rotation by slerp."""
    pa, pb = np.asarray(a, np.float64), np.asarray(b, np.float64)
    t = np.broadcast_to(np.asarray(w, np.float64), pa.shape[:-2])
    out = np.zeros(np.broadcast_shapes(pa.shape, pb.shape))
    q = slerp_xyzw(quaternions_xyzw(pa[..., :3, :3]), quaternions_xyzw(pb[..., :3, :3]), t)
    out[..., :3, :3] = rotations_from_xyzw(q)
    out[..., :3, 3] = (1.0 - t)[..., None] * pa[..., :3, 3] + t[..., None] * pb[..., :3, 3]
    out[..., 3, 3] = 1.0
    return out
