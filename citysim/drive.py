"""Synthetic drives: build the city and route, then yield one SensorFrame per keyframe."""
from __future__ import annotations

import math
import multiprocessing
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path as FsPath
from typing import Any

import numpy as np

from lcpr_common.shared_data import shared_path
from msg_tools.frames import CameraImage, SensorFrame

from .camera import encode_jpeg, lighting, render_camera
from .citygen import CityConfig, grid_city, path_city
from .depthnet import DEPTH_NOISE, DEPTH_RANGE, estimated_depth
from .hashing import hash_uniform, rng_for
from .lidar import LidarNoise, render_lidar
from .rigs import BASE_HEIGHT, Rig, check_level, make_rig, pose_matrix
from .route import (
    Keyframes,
    Path,
    RevisitStats,
    change_lanes,
    grid_path,
    load_kitti_path,
    make_street_graph,
    plan_grid_nodes,
    revisit_stats,
    sample_keyframes,
)
from .world import World

ROUTES = ("grid", "kitti00")


def default_kitti_poses() -> FsPath:
    """../shared/data/kitti00/poses.txt beside the checkout (or under $LCPR_SHARED_DIR)."""
    return shared_path("data", "kitti00", "poses.txt")


@dataclass(frozen=True)
class SynthConfig:
    """Everything that defines a synthetic drive; equal configs give identical frames."""

    rig: str = "nuscenes"  # nuscenes | kitti
    frames: int = 300  # keyframes (fewer if the route is shorter)
    seed: int = 0
    route: str = "grid"  # grid | kitti00
    kitti_poses: str | None = None  # poses.txt for route kitti00 (default: ../shared/data/kitti00/poses.txt)
    keyframe_spacing: float | None = None  # metres; None = rig default (nuscenes 5, kitti 1)
    image_size: tuple[int, int] | None = None  # (width, height); None = rig default
    night_fraction: float = 0.25  # share of lighting sessions that are night
    lighting_period_s: float = 45.0  # a lighting session (sun, haze, day/night) lasts this long
    camera_drop: float = 0.01  # chance that a camera image is missing (None)
    lidar_noise: LidarNoise = field(default_factory=LidarNoise)
    pixel_noise: bool = True
    speed: float = 10.0  # cruise speed on the grid route, m/s
    lane_changes: bool = True  # kitti00 route: drive in another lane now and then (grid routes always do)
    jpeg_quality: int = 85
    camera_range: float = 120.0  # metres rendered by the cameras
    depth_range: float = DEPTH_RANGE  # depth images (kitti rig): none beyond this along the optical axis; 0 = all
    depth_noise: float = DEPTH_NOISE  # depth images: smooth relative error, 1 sigma; 0 = the renderer's exact depth
    start_time: float = 1.7e9  # stamp of the first keyframe, seconds
    city: CityConfig | None = None  # None = route default

    def __post_init__(self) -> None:
        if self.rig not in ("nuscenes", "kitti"):
            raise ValueError(f"unknown rig {self.rig!r}; accepted: nuscenes, kitti")
        if self.route not in ROUTES:
            raise ValueError(f"unknown route {self.route!r}; accepted: {', '.join(ROUTES)}")
        if self.frames < 1:
            raise ValueError(f"frames={self.frames}; it must be at least 1")
        if self.keyframe_spacing is not None and not self.keyframe_spacing > 0:
            raise ValueError(f"keyframe_spacing={self.keyframe_spacing}; it must be positive (metres)")
        if not 0.0 <= self.night_fraction <= 1.0:
            raise ValueError(f"night_fraction={self.night_fraction}; it must lie in [0, 1]")
        if not 0.0 <= self.camera_drop < 1.0:
            raise ValueError(f"camera_drop={self.camera_drop}; it must lie in [0, 1)")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality={self.jpeg_quality}; it must lie in 1..100")
        if not self.speed > 0:
            raise ValueError(f"speed={self.speed}; it must be positive (m/s)")
        if not self.depth_range >= 0:
            raise ValueError(f"depth_range={self.depth_range}; it must be at least 0 (metres; 0 = unlimited)")
        if not 0.0 <= self.depth_noise < 1.0:
            raise ValueError(f"depth_noise={self.depth_noise}; it must lie in [0, 1)")


@dataclass
class FrameTiming:
    """Seconds spent on one frame, per stage (wall clock), and the CPU time of the whole frame."""

    lidar: float = 0.0
    cameras: float = 0.0
    encode: float = 0.0
    cpu: float = 0.0  # process CPU seconds (unaffected by other processes competing for the cores)


class SyntheticDrive:
    """A city, a route through it and a rig; ``frame(i)`` renders keyframe i.

    >>> drive = SyntheticDrive(SynthConfig(frames=20, image_size=(320, 180)))
    >>> for frame in drive.frames(workers=2): ...
    """

    def __init__(self, config: SynthConfig | None = None, *, world: World | None = None,
                 path: Path | None = None) -> None:
        self.config = cfg = config or SynthConfig()
        self.rig: Rig = make_rig(cfg.rig, image_size=cfg.image_size)
        self.camera_yaws = [check_level(c.base_T_cam, f"camera {c.name}", optical=True) for c in self.rig.cameras]
        check_level(self.rig.lidar.base_T_lidar, "the LiDAR", optical=False)
        self.spacing = cfg.keyframe_spacing or self.rig.default_spacing
        start = time.perf_counter()
        length = (cfg.frames - 1) * self.spacing
        if path is None or world is None:
            path, world = self._build(length)
        self.path, self.world = path, world
        self.keyframes: Keyframes = sample_keyframes(path, spacing=self.spacing, count=cfg.frames, t0=cfg.start_time)
        self.build_seconds = time.perf_counter() - start
        n_sessions = int(math.floor(path.t[-1] / cfg.lighting_period_s)) + 1
        order = np.argsort(hash_uniform(cfg.seed, 30, np.arange(n_sessions)), kind="stable")
        self._nights = set(int(k) for k in order[:int(round(cfg.night_fraction * n_sessions))])

    def _build(self, length: float) -> tuple[Path, World]:
        cfg = self.config
        if cfg.route == "grid":
            n = int(np.clip(round(math.sqrt(max(length, 1.0) / 250.0)), 2, 8))
            graph = make_street_graph(seed=cfg.seed, inner=(n, n))
            plan = length + 60.0
            for _ in range(4):  # rounded corners make the path a little shorter than the plan
                path = grid_path(graph, plan_grid_nodes(graph, length_m=plan, seed=cfg.seed), seed=cfg.seed,
                                 speed=cfg.speed)
                if path.length >= length:
                    break
                plan += 2.0 * (length - path.length) + 100.0
            return path, grid_city(graph, seed=cfg.seed, config=cfg.city, keep_clear=path.xy[::2])
        full = load_kitti_path(cfg.kitti_poses or default_kitti_poses())
        keep = full.s <= full.s[0] + length + 150.0
        path = Path(xy=full.xy[keep], yaw=full.yaw[keep], s=full.s[keep], t=full.t[keep])
        if not cfg.lane_changes:
            return path, path_city(path, seed=cfg.seed, config=cfg.city)
        driven = change_lanes(path, seed=cfg.seed)
        return driven, path_city(path, seed=cfg.seed, config=cfg.city, keep_clear=driven.xy)

    def __len__(self) -> int:
        return len(self.keyframes)

    def night(self, i: int) -> bool:
        return self.session(i) in self._nights

    def session(self, i: int) -> int:
        return int((self.keyframes.stamps[i] - self.config.start_time) // self.config.lighting_period_s)

    def pose(self, i: int) -> np.ndarray:
        """4 x 4 world_T_base of keyframe i."""
        x, y = self.keyframes.xy[i]
        return pose_matrix(float(x), float(y), BASE_HEIGHT[self.rig.name], float(self.keyframes.yaw[i]))

    def frame(self, i: int) -> SensorFrame:
        """Render keyframe i (deterministic: depends only on the config and i)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range; the drive has {len(self)} frames")
        cfg, rig = self.config, self.rig
        rng = rng_for(cfg.seed, 40, i)
        stamp = float(self.keyframes.stamps[i])
        world_T_base = self.pose(i)
        yaw = float(self.keyframes.yaw[i])
        x, y = (float(v) for v in self.keyframes.xy[i])
        reach = max(cfg.camera_range, rig.lidar.max_range) + 5.0
        objects = self.world.objects_near(x, y, reach, stamp=stamp)
        timing = FrameTiming()
        cpu0 = time.process_time()
        t0 = time.perf_counter()
        cloud = render_lidar(objects, self.world.ground, rig.lidar, world_T_base @ rig.lidar.base_T_lidar, yaw, rng,
                             noise=cfg.lidar_noise)
        t1 = time.perf_counter()
        timing.lidar = t1 - t0
        light = lighting(seed=cfg.seed, session=self.session(i), night=self.night(i))
        cameras: list[CameraImage | None] = []
        for cam in rig.cameras:
            if rng.uniform() < cfg.camera_drop:
                cameras.append(None)  # no image within the sync window (nothing rendered)
                continue
            t1 = time.perf_counter()
            r = render_camera(objects, self.world.ground, cam, world_T_base @ cam.base_T_cam, light, rng,
                              vehicle_yaw=yaw, max_dist=cfg.camera_range, noise=cfg.pixel_noise)
            t2 = time.perf_counter()
            timing.cameras += t2 - t1
            if rig.jpeg:
                image = CameraImage(stamp=stamp, frame_id=cam.frame_id,
                                    jpeg=encode_jpeg(r.rgb, quality=cfg.jpeg_quality))
            else:
                depth = None
                if rig.depth_and_labels:
                    depth = estimated_depth(r.depth, max_depth=cfg.depth_range, noise=cfg.depth_noise,
                                            rng=rng_for(cfg.seed, 41, i, len(cameras)))
                image = CameraImage(stamp=stamp, frame_id=cam.frame_id, rgb=r.rgb, depth=depth,
                                    labels=r.labels if rig.depth_and_labels else None)
            timing.encode += time.perf_counter() - t2
            cameras.append(image)
        timing.cpu = time.process_time() - cpu0
        return SensorFrame(stamp=stamp, cameras=cameras, cloud=cloud, lidar_frame_id=rig.lidar.frame_id,
                           pose=world_T_base, extras={"index": i, "night": self.night(i), "session": self.session(i),
                                                       "timing": timing})

    def frames(self, *, workers: int = 1, start: int = 0, stop: int | None = None) -> Iterator[SensorFrame]:
        """Frames start..stop-1 in order, rendered by ``workers`` processes (fork) when > 1."""
        stop = len(self) if stop is None else min(stop, len(self))
        indices = range(start, stop)
        if workers <= 1 or len(indices) < 2 or "fork" not in multiprocessing.get_all_start_methods():
            for i in indices:
                yield self.frame(i)
            return
        global _ACTIVE
        _ACTIVE = self
        with multiprocessing.get_context("fork").Pool(processes=workers) as pool:
            yield from pool.imap(_render, indices, chunksize=1)

    def __iter__(self) -> Iterator[SensorFrame]:
        return self.frames()

    def revisits(self, *, radius: float = 9.0, min_gap_s: float = 30.0) -> RevisitStats:
        """True revisits among the keyframes (see :func:`route.revisit_stats`)."""
        k = self.keyframes
        return revisit_stats(k.xy, k.yaw, k.stamps, radius=radius, min_gap_s=min_gap_s)

    def with_config(self, **changes: Any) -> SyntheticDrive:
        """The same city and route with other rendering options (noise, lighting, frames, image size...).

        Route and seed changes are not applied to the city or the path (they are reused as they are).
        """
        return SyntheticDrive(replace(self.config, **changes), world=self.world, path=self.path)


_ACTIVE: SyntheticDrive | None = None


def _render(i: int) -> SensorFrame:
    assert _ACTIVE is not None
    return _ACTIVE.frame(i)


def generate(config: SynthConfig | None = None, *, workers: int = 1) -> Iterator[SensorFrame]:
    """Build the drive described by ``config`` and yield its frames."""
    yield from SyntheticDrive(config).frames(workers=workers)
