"""Local submaps: a keyframe's compact cloud with its neighbours' stitched in by the odometry.

Why: a narrow-field sensor (a Livox Avia sees about 70 deg) sees so little in one keyframe that two
visits of a place often share too few surfaces to register, even at the true pose. The keyframes
around it, placed by the odometry the detector already receives (``Frame.pose``, world_T_base, kept
in the map per keyframe), widen what each side of a candidate holds.

- the **match**: its neighbours on both sides along the keyframe sequence (one session: the walk stops
  where the source changes, time goes back or the pose is unknown);
- the **query**: only the keyframes before it (online, its future is not known yet).

Neighbours are taken nearest first (path length along the odometry) while within ``travel_m`` of
the centre on their side, at most ``max_keyframes`` keyframes in all; the stitched cloud, in the centre
keyframe's LiDAR frame, is voxelised again (``voxel``) and capped (``max_points``) so that its cost
stays bounded. ``mode``: "off", "on", or "auto" (on for a keyframe whose own cloud covers less than
``auto_fov_deg`` of azimuth, a narrow field of view; a 360 deg scan is verified alone).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lcpr_common.params import check_fields, param

from ..errors import VerificationError
from ..geometry import invert, pose_from_xyz_rpy
from .clouds import compact_cloud
from .config import CloudConfig

__all__ = ["SUBMAP_MODES", "Submap", "SubmapConfig", "azimuth_coverage_deg", "build_submap", "neighbour_rows",
           "stitch", "submap_rows"]

SUBMAP_MODES: tuple[str, ...] = ("off", "on", "auto")
_AZIMUTH_BINS = 72  # 5 deg each
_STITCHED_RANGE = 327.0  # m: no crop of the stitched cloud beyond the int16 centimetre grid's reach


@dataclass(frozen=True, kw_only=True)
class SubmapConfig:
    """Whether and how far keyframe clouds are stitched into local submaps before verification."""

    mode: str = param("auto", "verify local submaps instead of single scans: the query with its previous "
                              "keyframes, each match with its neighbours, stitched by the odometry; auto = on for a "
                              "keyframe whose cloud covers less than submap.auto_fov_deg of azimuth (a narrow field "
                              "of view such as a Livox Avia's), off for 360 deg scans", choices=SUBMAP_MODES,
                      dynamic=True)
    # travel_m / max_keyframes: chosen on the Livox validation halves (docs/verification.md, "Local submaps"):
    # the most true pairs accepted with at most 0.1 % of the far pairs
    travel_m: float = param(2.0, "m of odometry path a neighbour may be from the centre keyframe, on each side",
                            lo=0.01, hi=1000.0, dynamic=True)
    max_keyframes: int = param(5, "keyframes stitched into one submap at most, the centre included (nearest by "
                                  "path first)", lo=1, hi=1000, dynamic=True)
    max_gap_s: float = param(30.0, "s between consecutive keyframes beyond which they are not stitched (another "
                                   "run)", lo=0.001, hi=1e6, dynamic=True)
    voxel: float = param(0.4, "m, voxel grid of the stitched cloud", lo=0.05, hi=5.0, dynamic=True)
    max_points: int = param(8192, "points of a stitched cloud at most (registration time grows with them)", lo=100,
                            hi=1_000_000, dynamic=True)
    auto_fov_deg: float = param(180.0, "deg of azimuth under which submap.mode auto counts a keyframe's field of "
                                       "view as narrow", lo=0.0, hi=360.0, lo_open=True, dynamic=True)
    lidar_xyz: tuple[float, ...] = param((0.0, 0.0, 0.0), "m: the LiDAR (the clouds' frame) in the odometry's "
                                                          "child frame (base_T_lidar), to place neighbours' clouds",
                                         dynamic=True)
    lidar_rpy: tuple[float, ...] = param((0.0, 0.0, 0.0), "rad: roll, pitch, yaw of the LiDAR in the odometry's "
                                                          "child frame (R = Rz Ry Rx)", dynamic=True)

    def __post_init__(self) -> None:
        check_fields(self, error=VerificationError, prefix="submap.")
        for name in ("lidar_xyz", "lidar_rpy"):
            value = tuple(getattr(self, name))
            if len(value) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value):
                raise VerificationError(f"submap.{name}={list(value)}; accepted: 3 finite numbers")

    def base_T_lidar(self) -> np.ndarray:
        """4 x 4: the LiDAR (the clouds' frame) in the odometry's base frame."""
        return pose_from_xyz_rpy(self.lidar_xyz, self.lidar_rpy)

    def applies(self, xyz: np.ndarray) -> bool:
        """Whether a keyframe with this cloud (M x 3, its LiDAR frame) gets a submap."""
        if self.mode == "auto":
            return azimuth_coverage_deg(xyz) < self.auto_fov_deg
        return self.mode == "on"


@dataclass(frozen=True)
class Submap:
    """A stitched cloud (M x 3 float32, the centre keyframe's LiDAR frame) and the rows it holds, in order."""

    xyz: np.ndarray
    rows: tuple[int, ...]


def azimuth_coverage_deg(xyz: np.ndarray) -> float:
    """Degrees of azimuth (about the LiDAR's z) a cloud covers: 5 deg bins holding at least a tenth of an even
    share of its points (a few stray returns do not widen a narrow field of view)."""
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0
    azimuth = np.arctan2(pts[:, 1], pts[:, 0])
    counts = np.histogram(azimuth, bins=_AZIMUTH_BINS, range=(-math.pi, math.pi))[0]
    least = max(2.0, len(pts) / _AZIMUTH_BINS / 10.0)
    return float((counts >= least).sum()) * 360.0 / _AZIMUTH_BINS


def neighbour_rows(world_T_base: np.ndarray, stamps: np.ndarray, centre: int, *, config: SubmapConfig,
                   before_only: bool) -> tuple[int, ...]:
    """Rows of the keyframes stitched around ``centre`` (itself included), ascending.

    ``world_T_base`` (N, 4, 4; NaN where unknown) and ``stamps`` (N,) are one session's keyframes in
    sequence order (the caller cuts them where the session ends). From the centre the walk goes back and,
    unless ``before_only``, forward, adding up the path between consecutive positions; it stops at an
    unknown pose, at a stamp that does not move on or jumps by more than ``max_gap_s`` (another run), or
    beyond ``travel_m``. The nearest ``max_keyframes - 1`` by path are kept.
    """
    poses = np.asarray(world_T_base, np.float64)
    t = np.asarray(stamps, np.float64)
    if not 0 <= centre < len(poses) or len(t) != len(poses):
        raise VerificationError(f"centre row {centre} of {len(poses)} poses and {len(t)} stamps; expected a row "
                                "of equally many poses and stamps")
    if not np.isfinite(poses[centre]).all():
        return (centre,)
    found: list[tuple[float, int]] = []
    for step in (-1,) if before_only else (-1, 1):
        travel, row = 0.0, centre
        while 0 <= row + step < len(poses):
            nxt = row + step
            gap = (t[nxt] - t[row]) * step
            if not np.isfinite(poses[nxt]).all() or not 0 < gap <= config.max_gap_s:
                break
            travel += float(np.linalg.norm(poses[nxt, :3, 3] - poses[row, :3, 3]))
            if travel > config.travel_m:
                break
            found.append((travel, nxt))
            row = nxt
    found.sort()
    return tuple(sorted([centre, *(r for _, r in found[: config.max_keyframes - 1])]))


def stitch(clouds: list[np.ndarray], world_T_base: np.ndarray, centre: int, *, config: SubmapConfig) -> np.ndarray:
    """One cloud (M x 3 float32, on the centre keyframe's LiDAR frame) of keyframe clouds (each M_i x 3 in its
    own LiDAR frame) placed by their world_T_base (K, 4, 4); voxelised and capped by ``config``. A single
    cloud comes back unchanged."""
    if len(clouds) != len(world_T_base):
        raise VerificationError(f"{len(clouds)} clouds but {len(world_T_base)} poses; expected one pose per cloud")
    if len(clouds) == 1:
        return np.asarray(clouds[0], np.float32).reshape(-1, 3)
    ext = config.base_T_lidar()
    world_T_lidar = np.asarray(world_T_base, np.float64) @ ext
    centre_T = invert(world_T_lidar[centre]) @ world_T_lidar  # (K, 4, 4): each LiDAR frame in the centre's
    moved = [np.asarray(c, np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
             for c, T in zip(clouds, centre_T, strict=True)]
    merged = np.concatenate(moved)
    cloud = CloudConfig(voxel=config.voxel, max_points=config.max_points, min_range=0.0, max_range=_STITCHED_RANGE)
    return compact_cloud(merged, cloud)


def submap_rows(centre: int, *, world_T_base: np.ndarray, stamps: np.ndarray,
                cloud: Callable[[int], np.ndarray | None], config: SubmapConfig, before_only: bool
                ) -> tuple[int, ...] | None:
    """The rows :func:`build_submap` stitches (ascending, the centre included), without stitching them: what a
    cache of prepared submaps is keyed by. None when the centre has no cloud."""
    own = cloud(centre)
    if own is None:
        return None
    if not config.applies(own):
        return (centre,)
    rows = neighbour_rows(world_T_base, stamps, centre, config=config, before_only=before_only)
    return tuple(r for r in rows if r == centre or cloud(r) is not None)


def build_submap(centre: int, *, world_T_base: np.ndarray, stamps: np.ndarray,
                 cloud: Callable[[int], np.ndarray | None], config: SubmapConfig, before_only: bool,
                 rows: tuple[int, ...] | None = None) -> Submap | None:
    """The submap of keyframe ``centre``: what the detector verifies with, and what the benchmarks measure.

    ``world_T_base``, ``stamps``: one session's keyframes in order (see :func:`neighbour_rows`); ``cloud(row)``:
    a row's compact cloud, or None (the row is left out). None when the centre has no cloud; the centre's
    cloud alone when ``config`` does not apply to it (mode, field of view) or it has no usable neighbour.
    ``rows``: :func:`submap_rows`' answer when the caller has it already.
    """
    kept = rows if rows is not None else submap_rows(centre, world_T_base=world_T_base, stamps=stamps, cloud=cloud,
                                                     config=config, before_only=before_only)
    own = cloud(centre)
    if kept is None or own is None:
        return None
    if kept == (centre,):
        return Submap(own, kept)
    parts = [own if r == centre else cloud(r) for r in kept]
    xyz = stitch([c for c in parts if c is not None], np.asarray(world_T_base)[list(kept)], kept.index(centre),
                 config=config)
    return Submap(xyz, kept)
