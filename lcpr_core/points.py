"""Point-array rules every part shares: reading N x (>=3) numbers (the finite x, y, z rows) and turning them about z."""
from __future__ import annotations

import numpy as np

from .errors import InputShapeError, LcprError


def finite_xyz(points: object, *, error: type[LcprError] = InputShapeError, name: str = "points") -> np.ndarray:
    """N x (>=3) array -> M x 3 float64 of the rows whose x, y and z are finite.

    A wrong shape or a non-numeric array raises ``error`` naming the shape found.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3 or pts.dtype.kind not in "fiu":
        raise error(f"{name} has shape {pts.shape} and dtype {pts.dtype}; expected an N x 3 (or more columns: "
                    "x, y, z, ...) array of numbers")
    xyz = pts[:, :3].astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


def turn_cos_sin(angle_deg: float) -> tuple[float, float]:
    """cos and sin of a turn about z in degrees; quarter turns exact (no cos(90 deg) = 6e-17 residue)."""
    t = np.deg2rad(angle_deg)
    c, s = float(np.cos(t)), float(np.sin(t))
    if angle_deg % 90 == 0:
        c, s = float(round(c)), float(round(s))
    return c, s


def rotate_z(points: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotate the x, y, z columns about z (counter-clockwise seen from above); other columns stay.

    Quarter turns are exact (no cos(90 deg) = 6e-17 residue).
    """
    if angle_deg == 0:
        return points
    c, s = turn_cos_sin(angle_deg)
    out = points.copy()
    x, y = points[:, 0], points[:, 1]
    out[:, 0], out[:, 1] = c * x - s * y, s * x + c * y
    return out
