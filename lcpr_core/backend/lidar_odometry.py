"""LiDAR odometry with KISS-ICP (PyPI ``kiss-icp``, the ``odometry`` extra): clouds in, world_T_base out.

    odom = KissOdometry(KissConfig(), base_T_lidar=T)
    world_T_base = odom.register(points_xyz, stamp)       # one cloud after another, in stamp order
    poses = run_kiss_icp(clouds, base_T_lidar=T)            # (N, 4, 4) for a whole sequence

KISS-ICP (Vizzo et al., RA-L 2023) registers each cloud against a local voxel map with robust
point-to-point ICP, starting from a constant-velocity guess. It works in the LiDAR frame of the
first cloud; the poses returned here are the base frame's, ``world_T_base = world_T_base0 @ E @
lidar0_T_lidar @ inv(E)`` with ``E = base_T_lidar`` (the odometry a back end takes), starting at
``world_T_base0`` (identity by default). Clouds are taken as captured at one instant (no per-point
times, so no deskewing). No ROS here: the ``lcpr_kiss_icp`` node and benchmarks/tools/backend_ate.py
both drive :class:`KissOdometry`.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lcpr_common.params import check_fields, param

from ..errors import InvalidValueError, RuntimeSetupError
from ..geometry import invert

__all__ = ["KissConfig", "KissOdometry", "run_kiss_icp"]


@dataclass(frozen=True, kw_only=True)
class KissConfig:
    """KISS-ICP's settings (its defaults, except a 2 m minimum range: the vehicle's own returns)."""

    max_range: float = param(100.0, "m: farther points are dropped", lo=1.0, hi=1000.0)
    # the vehicle itself
    min_range: float = param(2.0, "m: nearer points are dropped (the vehicle itself)", lo=0.0, hi=100.0)
    # max_range / 100: KISS-ICP's rule
    voxel_size: float = param(0.0, "m of the local map's voxels; 0 = max_range / 100", lo=0.0, hi=10.0)
    max_points_per_voxel: int = param(20, "points kept per voxel of the local map", lo=1, hi=1000)
    initial_threshold: float = param(2.0, "m: correspondence distance before the adaptive threshold has data",
                                     lo=0.01, hi=100.0)
    min_motion: float = param(0.1, "m: motion below which a cloud does not update the adaptive threshold",
                              lo=0.001, hi=10.0)
    max_iterations: int = param(500, "ICP iterations per cloud at most", lo=1, hi=10000)
    threads: int = param(1, "registration threads; 0 = all cores", lo=0, hi=1024)

    def __post_init__(self) -> None:
        check_fields(self, error=InvalidValueError, prefix="KissConfig.")
        if self.min_range >= self.max_range:
            raise InvalidValueError(f"KissConfig.min_range={self.min_range!r} is not below max_range="
                                    f"{self.max_range!r}")

    def kiss_config(self) -> Any:
        """The kiss_icp.config.KISSConfig of these settings."""
        from kiss_icp.config import KISSConfig
        from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig

        return KISSConfig(
            data=DataConfig(max_range=self.max_range, min_range=self.min_range, deskew=False),
            mapping=MappingConfig(voxel_size=self.voxel_size or self.max_range / 100.0,
                                  max_points_per_voxel=self.max_points_per_voxel),
            registration=RegistrationConfig(max_num_iterations=self.max_iterations, max_num_threads=self.threads),
            adaptive_threshold=AdaptiveThresholdConfig(initial_threshold=self.initial_threshold,
                                                       min_motion_th=self.min_motion),
        )


class KissOdometry:
    """KISS-ICP over clouds handed one at a time; poses in the base frame (module docstring)."""

    def __init__(self, config: KissConfig | None = None, *, base_T_lidar: np.ndarray | None = None,
                 world_T_base0: np.ndarray | None = None) -> None:
        try:
            from kiss_icp.kiss_icp import KissICP
        except ImportError as exc:
            raise RuntimeSetupError(f"kiss-icp is not installed ({exc}); LiDAR odometry needs it: "
                              "pip install 'lcpr_loop_closure[odometry]' (or pip install kiss-icp)") from exc
        self.config = config if config is not None else KissConfig()
        self._ext = _pose(np.eye(4) if base_T_lidar is None else base_T_lidar, "base_T_lidar")
        self._start = _pose(np.eye(4) if world_T_base0 is None else world_T_base0, "world_T_base0")
        self._kiss = KissICP(self.config.kiss_config())
        self._last_stamp: float | None = None
        self.frames = 0

    def register(self, points: np.ndarray, stamp: float) -> np.ndarray:
        """Register one cloud ((N, >=3) x, y, z in the LiDAR frame; rows with NaN/inf dropped); its world_T_base."""
        if not isinstance(stamp, (int, float)) or isinstance(stamp, bool) or not math.isfinite(stamp):
            raise InvalidValueError(f"stamp={stamp!r}; expected a finite number of seconds")
        if self._last_stamp is not None and stamp <= self._last_stamp:
            raise InvalidValueError(f"stamp {stamp!r} is not after the previous cloud's {self._last_stamp!r}; "
                                    "expected clouds in stamp order")
        arr = np.asarray(points)
        if arr.ndim != 2 or arr.shape[1] < 3:
            raise InvalidValueError(f"points of shape {arr.shape}; expected (N, >=3) x, y, z")
        xyz = np.ascontiguousarray(arr[:, :3], np.float64)
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if len(xyz) < 10:
            raise InvalidValueError(f"a cloud of {len(xyz)} finite points at stamp {stamp!r}; KISS-ICP needs more")
        self._kiss.register_frame(xyz, np.zeros(len(xyz)))
        self._last_stamp = float(stamp)
        self.frames += 1
        return self.pose

    @property
    def pose(self) -> np.ndarray:
        """world_T_base of the newest cloud (``world_T_base0`` before the first)."""
        lidar0_T_lidar = np.asarray(self._kiss.last_pose, np.float64)
        return self._start @ self._ext @ lidar0_T_lidar @ invert(self._ext)


def run_kiss_icp(clouds: Iterable[np.ndarray], *, stamps: Iterable[float] | None = None,
                 config: KissConfig | None = None, base_T_lidar: np.ndarray | None = None,
                 world_T_base0: np.ndarray | None = None) -> np.ndarray:
    """(N, 4, 4) world_T_base of each cloud of a sequence (stamps default to 0.1 s apart)."""
    odom = KissOdometry(config, base_T_lidar=base_T_lidar, world_T_base0=world_T_base0)
    times = iter(stamps) if stamps is not None else (0.1 * k for k in range(1 << 62))
    poses = [odom.register(cloud, float(next(times))) for cloud in clouds]
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def _pose(value: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(value, np.float64)
    if arr.shape != (4, 4) or not np.isfinite(arr).all():
        raise InvalidValueError(f"{name} of shape {arr.shape}; expected a finite (4, 4) pose")
    return arr
