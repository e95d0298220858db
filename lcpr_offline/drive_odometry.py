"""KISS-ICP on a synthetic drive's own LiDAR: the odometry of ``backend_ate.py`` and ``lcpr_demo --odometry kiss-icp``.

    dense = dense_drive(drive, spacing=1.0)                 # the same path and world, a LiDAR frame every metre
    stream = record_drive(dense, every=5, detector=det)     # KISS-ICP on every frame; the detector on every 5th

A drive rendered for the detector has keyframes 5 m apart, too far for KISS-ICP's constant-velocity
guess (it loses the 32-beam rig at 2.5 m steps), so the odometry runs on LiDAR frames rendered every
metre along the same path in the same world: keyframe ``k`` of a drive ``s`` m apart is frame
``k * s / spacing`` of the dense one, at the same stamp. KISS-ICP starts at the true first pose; the
stream (:class:`lcpr_core.backend.replay.LoopStream`) holds the truth, the odometry and, with a
detector, its verified loops, for :func:`lcpr_core.backend.replay.replay`.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from citysim import SyntheticDrive
from citysim.lidar import render_lidar
from lcpr_common.progress import progress_iter
from lcpr_core.backend.lidar_odometry import KissConfig, KissOdometry
from lcpr_core.backend.replay import LoopStream, StreamRecorder
from lcpr_core.detector import Frame, LoopDetector
from lcpr_core.errors import InvalidValueError

__all__ = ["dense_drive", "lidar_points", "record_drive"]


def dense_drive(drive: SyntheticDrive, *, spacing: float = 1.0) -> SyntheticDrive:
    """``drive``'s path and world with a frame every ``spacing`` m (its own frames among them when spacings divide)."""
    if not (math.isfinite(spacing) and spacing > 0):
        raise InvalidValueError(f"spacing={spacing!r}; expected a distance > 0 m")
    length = (len(drive) - 1) * drive.spacing
    frames = int(math.floor(length / spacing + 1e-9)) + 1
    config = dataclasses.replace(drive.config, keyframe_spacing=spacing, frames=frames)
    return SyntheticDrive(config, world=drive.world, path=drive.path)


def lidar_points(drive: SyntheticDrive, i: int) -> np.ndarray:
    """(N, 3) float64 LiDAR points of frame ``i`` in the LiDAR frame, rendered as ``SyntheticDrive.frame`` does."""
    rig = drive.rig
    objects = drive.objects_at(i, rig.lidar.max_range + 5.0)
    cloud = render_lidar(objects, drive.world.ground, rig.lidar, drive.pose(i) @ rig.lidar.base_T_lidar,
                         float(drive.keyframes.yaw[i]), drive.noise_rng(i), noise=drive.config.lidar_noise)
    return np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)


def record_drive(drive: SyntheticDrive, *, every: int = 5, detector: LoopDetector | None = None, threads: int = 1,
                 kiss: KissConfig | None = None, progress: bool = True) -> LoopStream:
    """KISS-ICP over every frame of ``drive`` (and ``detector`` on every ``every``-th, with cameras); the stream.

    Without a detector the stream has no loops and its keyframes are every ``every``-th frame; add the
    loops found elsewhere with :meth:`~lcpr_core.backend.replay.LoopStream.with_loops`.
    """
    if not (isinstance(every, int) and every >= 1):
        raise InvalidValueError(f"every={every!r}; expected an integer >= 1")
    ext = np.asarray(drive.rig.lidar.base_T_lidar, np.float64)
    stamps = np.asarray(drive.keyframes.stamps, np.float64)
    odometry = KissOdometry(kiss or KissConfig(threads=threads), base_T_lidar=ext, world_T_base0=drive.pose(0))
    recorder = StreamRecorder(base_T_lidar=ext)
    seconds = {"render": 0.0, "kiss_icp": 0.0, "detector": 0.0}
    for i in progress_iter(range(len(drive)), total=len(drive), desc="drive", unit="frame", enabled=progress):
        keyframe = i % every == 0
        tic = time.perf_counter()
        frame = drive.frame(i) if keyframe and detector is not None else None  # cameras too
        xyz = frame.xyz if frame is not None else lidar_points(drive, i)
        seconds["render"] += time.perf_counter() - tic
        tic = time.perf_counter()
        pose = odometry.register(xyz, float(stamps[i]))
        recorder.add_frame(float(stamps[i]), odometry=pose, truth=drive.pose(i))
        seconds["kiss_icp"] += time.perf_counter() - tic
        if not keyframe:
            continue
        if frame is None or detector is None:
            recorder.add_keyframe(float(stamps[i]))
            continue
        tic = time.perf_counter()
        images = [None if c is None else c.jpeg for c in frame.cameras]
        recorder.add_result(detector.process(Frame(stamp=float(stamps[i]), images=images, points=xyz, pose=pose)))
        seconds["detector"] += time.perf_counter() - tic
    return recorder.stream(seconds=seconds)
