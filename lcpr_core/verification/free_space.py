"""Free space: what a scan says is empty, and how much of another scan lies in it.

A LiDAR return at range r says the space along its beam nearer than r is empty. Two scans of one place,
rightly aligned, put almost none of their points in each other's empty space (a passing car, a post the
other scan sampled in the next bin); a look-alike place registered on the part it shares puts the parts
that differ there: a wall where the other sensor saw through to the building behind. The verifier
refuses a pair whose contradiction exceeds ``verify.max_contradiction`` (docs/verification.md, "Free
space").

    space = FreeSpace(match_xyz)                    # M x 3 in the match's sensor frame (sensor at the origin)
    bad, seen = space.contradicting(query_in_match)  # points in its free space, points in directions it saw
"""
from __future__ import annotations

import numpy as np

BIN_DEG = 2.0  # azimuth and elevation bins of the depth image (deg)
# a point contradicts a scan when it lies nearer than the scan's free depth in its direction by MARGIN_M or by
# MARGIN_SHARE of that depth, whichever is more: room for voxel centroids (0.4 m) and a pose error at range
MARGIN_M = 1.0
MARGIN_SHARE = 0.05
_AZIMUTHS = round(360.0 / BIN_DEG)
_ELEVATIONS = round(180.0 / BIN_DEG)


def _spherical(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range, azimuth bin, elevation bin) of each point (N x 3, the sensor at the origin)."""
    r = np.linalg.norm(xyz, axis=1)
    azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])) + 180.0
    elevation = np.degrees(np.arcsin(np.clip(xyz[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))) + 90.0
    ia = (azimuth / BIN_DEG).astype(np.int64) % _AZIMUTHS
    ie = np.clip((elevation / BIN_DEG).astype(np.int64), 0, _ELEVATIONS - 1)
    return r, ia, ie


class FreeSpace:
    """How far each direction is seen empty from a cloud's origin (its sensor).

    Per 2 x 2 deg bin: the nearest return in the bin and its 8 neighbours, so that a thin post or a beam
    gap sampled in the next bin does not count as seen through. A bin without a return of its own is
    unknown (inf): nothing is said about directions the sensor did not see.
    """

    def __init__(self, xyz: np.ndarray) -> None:
        r, ia, ie = _spherical(np.asarray(xyz, np.float64).reshape(-1, 3))
        nearest = np.full((_AZIMUTHS, _ELEVATIONS), np.inf)  # A x E, m (127 KiB, kept with a prepared cloud)
        np.minimum.at(nearest, (ia, ie), r)
        padded = np.pad(nearest, ((0, 0), (1, 1)), constant_values=np.inf)  # elevation does not wrap ...
        depth = nearest.copy()
        for da in (-1, 0, 1):  # ... azimuth does
            turned = np.roll(padded, da, axis=0)
            for de in (-1, 0, 1):
                depth = np.minimum(depth, turned[:, 1 + de: 1 + de + _ELEVATIONS])
        depth[~np.isfinite(nearest)] = np.inf
        self.depth = depth  # A x E, m; inf = unknown

    def contradicting(self, points: np.ndarray, *, excused: np.ndarray | None = None) -> tuple[int, int]:
        """(points lying in the free space, points in directions with a return), of ``points`` (N x 3, this
        cloud's frame). ``excused`` (N bools): points that never count as contradicting (e.g. those lying on a
        surface this cloud has, within the inlier distance)."""
        r, ia, ie = _spherical(np.asarray(points, np.float64).reshape(-1, 3))
        free = self.depth[ia, ie]
        seen = np.isfinite(free)
        inside = seen & (r < free - np.maximum(MARGIN_M, MARGIN_SHARE * np.where(seen, free, 0.0)))
        if excused is not None:
            inside &= ~excused
        return int(inside.sum()), int(seen.sum())
