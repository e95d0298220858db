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
from .hashing import DAY_S, drive_keys, hash_uniform, rng_for
from .lidar import LidarNoise, render_lidar
from .rigs import BASE_HEIGHT, Rig, check_level, make_rig, pose_matrix
from .route import (
    Keyframes,
    Path,
    RevisitStats,
    StreetGraph,
    change_lanes,
    drive_along,
    grid_path,
    load_kitti_path,
    make_street_graph,
    plan_grid_nodes,
    revisit_stats,
    sample_keyframes,
    shared_ground,
)
from .world import Objects, World

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
    drive: int = 0  # which drive through the seed's city: K > 0 keeps the city, changes route, noise, lighting, t0
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
    start_time: float = 1.7e9  # stamp of drive 0's first keyframe, seconds (drive K starts K days later)
    city: CityConfig | None = None  # None = route default

    def __post_init__(self) -> None:
        if self.rig not in ("nuscenes", "kitti"):
            raise ValueError(f"unknown rig {self.rig!r}; accepted: nuscenes, kitti")
        if self.route not in ROUTES:
            raise ValueError(f"unknown route {self.route!r}; accepted: {', '.join(ROUTES)}")
        if self.drive < 0:
            raise ValueError(f"drive={self.drive}; it must be 0 (the city's first drive) or a positive drive number")
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

    @property
    def t0(self) -> float:
        """Stamp of this drive's first keyframe: ``start_time`` shifted by ``drive`` days."""
        return self.start_time + DAY_S * self.drive

    @property
    def spacing(self) -> float:
        """Metres between keyframes (the rig's default unless ``keyframe_spacing`` is set)."""
        return self.keyframe_spacing or make_rig(self.rig, image_size=self.image_size).default_spacing

    def city_key(self) -> tuple[object, ...]:
        """The options that make the city: drives whose configs share this key drive through one world.

        The size of a grid city and the corridor kept clear of props follow drive 0's route,
        so its length (frames x spacing) is part of the city as well as the seed.
        """
        track = (self.kitti_poses, self.lane_changes) if self.route == "kitti00" else ()
        return (self.route, self.seed, self.city, round((self.frames - 1) * self.spacing, 6), *track)


@dataclass
class FrameTiming:
    """Seconds spent on one frame, per stage (wall clock), and the CPU time of the whole frame."""

    lidar: float = 0.0
    cameras: float = 0.0
    encode: float = 0.0
    cpu: float = 0.0  # process CPU seconds (unaffected by other processes competing for the cores)


def _street_graph(cfg: SynthConfig, length: float) -> StreetGraph:
    n = int(np.clip(round(math.sqrt(max(length, 1.0) / 250.0)), 2, 8))
    return make_street_graph(seed=cfg.seed, inner=(n, n))


def _grid_route(cfg: SynthConfig, graph: StreetGraph, length: float, drive: int, variant: int = 0) -> Path:
    plan = length + 60.0
    for _ in range(4):  # rounded corners make the path a little shorter than the plan
        nodes = plan_grid_nodes(graph, length_m=plan, seed=cfg.seed, drive=drive, variant=variant)
        path = grid_path(graph, nodes, seed=cfg.seed, speed=cfg.speed, drive=drive)
        if path.length >= length:
            break
        plan += 2.0 * (length - path.length) + 100.0
    return path


def _kitti_track(cfg: SynthConfig, length: float) -> Path:
    """The stretch of the KITTI-00 trajectory the city is built around (drive 0's route before lane changes)."""
    full = load_kitti_path(cfg.kitti_poses or default_kitti_poses())
    keep = full.s <= full.s[0] + length + 150.0
    return Path(xy=full.xy[keep], yaw=full.yaw[keep], s=full.s[keep], t=full.t[keep])


def _kitti_route(cfg: SynthConfig, track: Path, length: float, drive: int, variant: int = 0) -> Path:
    path = drive_along(track, length=length, seed=cfg.seed, drive=drive, variant=variant)
    return change_lanes(path, seed=cfg.seed, drive=drive) if cfg.lane_changes else path


ROUTE_TRIES = 16  # plans of a drive K > 0 tried for one that keeps clear of the city's walls and poles
ROUTE_CLEARANCE = 1.2  # metres from the route to anything a car would hit (drive 0's corridor keeps 2.2)


def _route(cfg: SynthConfig, base: StreetGraph | Path, length: float, world: World | None) -> Path:
    def plan(variant: int) -> Path:
        if isinstance(base, StreetGraph):
            return _grid_route(cfg, base, length, cfg.drive, variant)
        return _kitti_route(cfg, base, length, cfg.drive, variant)

    if cfg.drive == 0 or world is None:
        return plan(0)
    for variant in range(ROUTE_TRIES):
        path = plan(variant)
        if world.clearance(path.xy[path.s <= path.s[0] + length]).min() >= ROUTE_CLEARANCE:
            return path
    raise ValueError(f"drive {cfg.drive} of seed {cfg.seed}: none of {ROUTE_TRIES} routes keeps {ROUTE_CLEARANCE} m "
                     f"from the city's walls and poles; take another drive number")


def route_path(config: SynthConfig, *, world: World | None = None) -> Path:
    """The path ``config``'s drive takes through its city.

    Without ``world`` the city is not built (fast); a drive K > 0 whose first plan would pass
    a wall or pole of the city closer than ROUTE_CLEARANCE is re-planned only when ``world``
    (the city, from :func:`build_city_and_route`) is given, as :class:`SyntheticDrive` does.
    """
    length = (config.frames - 1) * config.spacing
    if config.route == "grid":
        return _route(config, _street_graph(config, length), length, world)
    return _route(config, _kitti_track(config, length), length, world)


def route_keyframes(config: SynthConfig, *, world: World | None = None) -> Keyframes:
    """The keyframe poses and stamps of ``config``'s drive (see :func:`route_path`), without rendering."""
    return sample_keyframes(route_path(config, world=world), spacing=config.spacing, count=config.frames,
                            t0=config.t0)


def build_city_and_route(config: SynthConfig) -> tuple[Path, World]:
    """(the driven path, the city) of ``config``.

    The city is the one drive 0 of the same options makes (drive 0's route keeps its
    corridor clear of props and parked cars); drive K > 0 plans its own route through it.
    """
    length = (config.frames - 1) * config.spacing
    base: StreetGraph | Path
    if config.route == "grid":
        base = graph = _street_graph(config, length)
        first = _grid_route(config, graph, length, 0)
        world = grid_city(graph, seed=config.seed, config=config.city, keep_clear=first.xy[::2])
    else:
        base = track = _kitti_track(config, length)
        first = _kitti_route(config, track, length, 0)
        keep_clear = first.xy if config.lane_changes else None
        world = path_city(track, seed=config.seed, config=config.city, keep_clear=keep_clear)
    return (first if config.drive == 0 else _route(config, base, length, world)), world


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
        if path is None or world is None:
            path, world = build_city_and_route(cfg)
        self.path, self.world = path, world
        self.keyframes: Keyframes = sample_keyframes(path, spacing=self.spacing, count=cfg.frames, t0=cfg.t0)
        # drive 0's corridor has no parked cars; a later drive empties the slots along its own route
        self.empty_slots: np.ndarray | None = None
        if cfg.drive > 0:
            driven = path.xy[path.s <= self.keyframes.s[-1] + self.spacing]
            self.empty_slots = world.slots_near(driven[::2])
        self.build_seconds = time.perf_counter() - start
        n_sessions = int(math.floor(path.t[-1] / cfg.lighting_period_s)) + 1
        order = np.argsort(hash_uniform(cfg.seed, 30, np.arange(n_sessions), *drive_keys(cfg.drive)), kind="stable")
        self._nights = set(int(k) for k in order[:int(round(cfg.night_fraction * n_sessions))])

    def __len__(self) -> int:
        return len(self.keyframes)

    def night(self, i: int) -> bool:
        return self.session(i) in self._nights

    def session(self, i: int) -> int:
        return int((self.keyframes.stamps[i] - self.config.t0) // self.config.lighting_period_s)

    def pose(self, i: int) -> np.ndarray:
        """4 x 4 world_T_base of keyframe i."""
        x, y = self.keyframes.xy[i]
        return pose_matrix(float(x), float(y), BASE_HEIGHT[self.rig.name], float(self.keyframes.yaw[i]))

    def noise_rng(self, i: int) -> np.random.Generator:
        """The random stream of keyframe i's sensors (the LiDAR draws first, then the cameras)."""
        return rng_for(self.config.seed, 40, i, *drive_keys(self.config.drive))

    def objects_at(self, i: int, reach: float) -> Objects:
        """The city's objects within ``reach`` metres of keyframe i, with the cars parked then."""
        x, y = (float(v) for v in self.keyframes.xy[i])
        return self.world.objects_near(x, y, reach, stamp=float(self.keyframes.stamps[i]),
                                       empty_slots=self.empty_slots)

    def frame(self, i: int) -> SensorFrame:
        """Render keyframe i (deterministic: depends only on the config and i)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range; the drive has {len(self)} frames")
        cfg, rig = self.config, self.rig
        rng = self.noise_rng(i)
        stamp = float(self.keyframes.stamps[i])
        world_T_base = self.pose(i)
        yaw = float(self.keyframes.yaw[i])
        objects = self.objects_at(i, max(cfg.camera_range, rig.lidar.max_range) + 5.0)
        timing = FrameTiming()
        cpu0 = time.process_time()
        t0 = time.perf_counter()
        cloud = render_lidar(objects, self.world.ground, rig.lidar, world_T_base @ rig.lidar.base_T_lidar, yaw, rng,
                             noise=cfg.lidar_noise)
        t1 = time.perf_counter()
        timing.lidar = t1 - t0
        light = lighting(seed=cfg.seed, session=self.session(i), night=self.night(i), drive=cfg.drive)
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
                                            rng=rng_for(cfg.seed, 41, i, len(cameras), *drive_keys(cfg.drive)))
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

        Route and seed changes are not applied to the city or the path (they are reused as they are);
        for another drive through the city use :meth:`other_drive`.
        """
        if changes.get("drive", self.config.drive) != self.config.drive:
            raise ValueError(f"with_config(drive={changes['drive']}): a drive number changes the route; "
                             f"use other_drive({changes['drive']}) for another drive through this city")
        return SyntheticDrive(replace(self.config, **changes), world=self.world, path=self.path)

    def other_drive(self, drive: int, **changes: Any) -> SyntheticDrive:
        """Drive ``drive`` through this drive's city (the world is reused, only the route is planned).

        ``changes`` are other options for the new drive; those that make the city
        (:meth:`SynthConfig.city_key`) must stay as they are.
        """
        config = replace(self.config, drive=drive, **changes)
        if config.city_key() != self.config.city_key():
            raise ValueError(f"other_drive(**{changes}) changes the city ({self.config.city_key()} -> "
                             f"{config.city_key()}); only route-free options (rendering, noise, speed) may change")
        return SyntheticDrive(config, world=self.world, path=route_path(config, world=self.world))

    def shared_ground(self, other: SyntheticDrive, *, radius: float = 9.0) -> np.ndarray:
        """Which keyframes of ``other`` lie within ``radius`` metres of this drive's path (bool per keyframe).

        Only drives through one city compare: another seed (or size) is another world, and
        positions there mean other places even where the numbers agree.
        """
        if other.config.city_key() != self.config.city_key():
            raise ValueError(f"drives through different cities (city {self.config.city_key()} vs "
                             f"{other.config.city_key()}) do not share ground; compare drives of one seed, "
                             f"route, city and length")
        k = self.keyframes
        return shared_ground(self.path.xy[(self.path.s >= k.s[0]) & (self.path.s <= k.s[-1])] if len(k) > 1
                             else k.xy, other.keyframes, radius=radius)


_ACTIVE: SyntheticDrive | None = None


def _render(i: int) -> SensorFrame:
    assert _ACTIVE is not None
    return _ACTIVE.frame(i)


def generate(config: SynthConfig | None = None, *, workers: int = 1) -> Iterator[SensorFrame]:
    """Build the drive described by ``config`` and yield its frames."""
    yield from SyntheticDrive(config).frames(workers=workers)
