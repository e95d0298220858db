"""One rule for reading point arrays: N x (>=3) numbers in, the finite x, y, z rows out."""
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
