"""Which way is up, from the walls a LiDAR scan sees.

Building walls, posts and tree trunks stand vertical. Their surface normals are horizontal, so the
up direction is the one axis perpendicular to all of them: the eigenvector of smallest eigenvalue of
``sum(n n^T)`` over the wall points' normals. Unlike the ground plane it holds on slopes, and unlike an
odometry's tilt it does not drift. The pose-graph back end (:meth:`lcpr_core.backend.PoseGraphBackend.add_up`)
uses it to hold the roll and pitch that loops cannot observe.

    est = estimate_up(xyz, prior_up=R_lidar.T @ [0, 0, 1])   # None: too few walls, or walls of one direction
    est.up                                                     # unit 3-vector in the cloud's frame

A scan is refused (None) when it covers less than ``min_fov_deg`` of azimuth (a narrow field of view
sees the walls of one side only, and their errors do not average out), when fewer than ``min_walls``
points lie on walls, or when the walls face one direction only (a single wall leaves the tilt about its
normal unseen): ``min_spread``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lcpr_common.params import check_fields, param

from .errors import InvalidValueError
from .geometry import unit_vector
from .verification.submap import azimuth_coverage_deg

__all__ = ["UpConfig", "UpEstimate", "estimate_up"]


@dataclass(frozen=True)
class UpConfig:
    """How walls are found and trusted."""

    enabled: bool = param(True, "measure each keyframe's up direction from the walls its cloud sees and publish it "
                                "on ~/up (lcpr_backend holds the map's roll and pitch with it)", dynamic=True)
    voxel: float = param(0.2, "m, voxel grid of the cloud before its normals are estimated; 0 = none", lo=0.0,
                         hi=5.0, dynamic=True)
    neighbours: int = param(12, "points per normal", lo=3, hi=200, dynamic=True)
    planarity: float = param(0.05, "a point lies on a plane when its smallest covariance eigenvalue is under this "
                                   "share of the middle one", lo=0.0, hi=1.0, dynamic=True)
    min_range: float = param(1.0, "m, closer points (the vehicle, the person carrying the sensor) are ignored",
                             lo=0.0, hi=1000.0, dynamic=True)
    max_range: float = param(60.0, "m, farther points are ignored", lo=0.0, hi=1000.0, dynamic=True)
    max_tilt_deg: float = param(30.0, "deg: a plane whose normal is within this of the LiDAR's horizontal plane "
                                      "counts as a wall", lo=0.0, hi=90.0, lo_open=True, hi_open=True, dynamic=True)
    inlier_deg: float = param(5.0, "deg: walls further from vertical than this (roofs, slopes) are dropped while the "
                                   "up is refined", lo=0.0, hi=90.0, dynamic=True)
    iterations: int = param(5, "refinement passes", lo=1, hi=100, dynamic=True)
    min_walls: int = param(100, "wall points needed for an up (fewer: none published)", lo=1, hi=1_000_000,
                           dynamic=True)
    min_spread: float = param(0.02, "the second wall direction's share of the first (eigenvalue ratio) needed; "
                                    "walls facing one way leave a tilt unseen", lo=0.0, hi=1.0, dynamic=True)
    # a narrow field of view sees the walls of one side, and their ups bend the heights instead of holding them
    # (docs/backend.md, "Measured up from the walls")
    min_fov_deg: float = param(180.0, "deg of azimuth a keyframe's cloud must cover for an up (a narrow field of "
                                      "view sees the walls of one side only); 0 = any", lo=0.0, hi=360.0,
                               dynamic=True)

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise InvalidValueError(f"up.enabled={self.enabled!r}; expected true or false")
        check_fields(self, error=InvalidValueError, prefix="up.")
        if self.max_range <= self.min_range:
            raise InvalidValueError(f"up.max_range={self.max_range!r} <= up.min_range={self.min_range!r}; "
                                    "expected max_range > min_range")


@dataclass(frozen=True)
class UpEstimate:
    up: np.ndarray  # (3,) unit vector in the cloud's frame
    walls: int  # wall points that voted
    spread: float  # second wall direction's eigenvalue over the first (0..1; 1: walls facing every way)
    residual_deg: float  # RMS angle of the voting normals from the horizontal plane of ``up``


def _wall_normals(xyz: np.ndarray, cfg: UpConfig) -> np.ndarray:
    """Unit normals (M x 3) of the points that lie on planes."""
    import small_gicp  # the verification dependency; imported here so the module loads without it

    r = np.linalg.norm(xyz, axis=1)
    xyz = np.ascontiguousarray(xyz[(r >= cfg.min_range) & (r <= cfg.max_range)], np.float64)
    if len(xyz) < cfg.neighbours:
        return np.zeros((0, 3))
    cloud = small_gicp.PointCloud(xyz)
    if cfg.voxel > 0:
        cloud = small_gicp.voxelgrid_sampling(cloud, cfg.voxel)
    if cloud.size() < cfg.neighbours:
        return np.zeros((0, 3))
    tree = small_gicp.KdTree(cloud)
    small_gicp.estimate_normals_covariances(cloud, tree, num_neighbors=cfg.neighbours)
    normals = np.asarray(cloud.normals())[:, :3]
    eig = np.linalg.eigvalsh(np.asarray(cloud.covs())[:, :3, :3])  # ascending, per point
    planar = eig[:, 0] < cfg.planarity * np.maximum(eig[:, 1], 1e-12)
    return np.asarray(normals[planar])


def estimate_up(xyz: np.ndarray, *, prior_up: np.ndarray | None = None,
                config: UpConfig | None = None) -> UpEstimate | None:
    """The up direction of a cloud (N x >=3, its own frame) from its walls; None when they do not fix it.

    ``prior_up`` (default: the cloud's z axis) picks which planes are walls (normals within
    ``max_tilt_deg`` of its horizontal plane) and the sign of the answer; a few degrees off is fine.
    """
    cfg = config or UpConfig()
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise InvalidValueError(f"xyz of shape {pts.shape}; expected N x 3 (or more columns)")
    pts = pts[:, :3]
    pts = pts[np.isfinite(pts).all(axis=1)]
    up0 = np.array([0.0, 0.0, 1.0]) if prior_up is None else unit_vector(prior_up)
    if up0 is None:
        raise InvalidValueError(f"prior_up={prior_up!r}; expected a finite non-zero 3-vector")
    if cfg.min_fov_deg > 0 and azimuth_coverage_deg(pts) < cfg.min_fov_deg:
        return None
    normals = _wall_normals(pts, cfg)
    normals = normals[np.abs(normals @ up0) < math.sin(math.radians(cfg.max_tilt_deg))]
    up, keep, eig = up0, normals, np.zeros(3)
    for i in range(cfg.iterations):  # the first pass votes with every wall, later ones with those near vertical
        keep = normals if i == 0 else normals[np.abs(normals @ up) < math.sin(math.radians(cfg.inlier_deg))]
        if len(keep) < cfg.min_walls:
            return None
        eig, vec = np.linalg.eigh(keep.T @ keep)  # ascending: the smallest is up
        up = vec[:, 0] if vec[:, 0] @ up0 >= 0 else -vec[:, 0]
    spread = float(eig[1] / eig[2]) if eig[2] > 0 else 0.0
    if spread < cfg.min_spread:
        return None
    residual = float(np.degrees(np.sqrt(np.mean(np.arcsin(np.clip(keep @ up, -1.0, 1.0)) ** 2))))
    return UpEstimate(up=up, walls=len(keep), spread=spread, residual_deg=residual)
