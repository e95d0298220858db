"""Pure synchronisation logic on header stamps (integer nanoseconds); no bag access here."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry import interpolate_pose


@dataclass
class MonotonicFilter:
    """Keeps messages whose stamps strictly increase; counts the others.

    ``kept`` holds (ordinal, stamp_ns) of kept messages, where ordinal is the message's
    position among all messages of its topic in bag order.
    """

    kept_ordinals: list[int]
    kept_stamps: list[int]
    duplicates: int = 0
    out_of_order: int = 0

    @classmethod
    def new(cls) -> MonotonicFilter:
        return cls([], [])

    def offer(self, ordinal: int, stamp_ns: int) -> bool:
        if self.kept_stamps:
            last = self.kept_stamps[-1]
            if stamp_ns == last:
                self.duplicates += 1
                return False
            if stamp_ns < last:
                self.out_of_order += 1
                return False
        self.kept_ordinals.append(ordinal)
        self.kept_stamps.append(stamp_ns)
        return True

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.kept_ordinals, dtype=np.int64), np.asarray(self.kept_stamps, dtype=np.int64)


def nearest_within(stamps: np.ndarray, targets: np.ndarray, slop_ns: int) -> np.ndarray:
    """Index of the nearest of sorted ``stamps`` to each target, -1 where none lies within ``slop_ns``.

    Ties go to the earlier stamp.
    """
    targets = np.asarray(targets, dtype=np.int64)
    if stamps.size == 0:
        return np.full(targets.shape, -1, dtype=np.int64)
    right = np.searchsorted(stamps, targets, side="left").clip(0, stamps.size - 1)
    left = (right - 1).clip(0, stamps.size - 1)
    d_left = np.abs(targets - stamps[left])
    d_right = np.abs(stamps[right] - targets)
    best = np.where(d_left <= d_right, left, right)
    best_d = np.minimum(d_left, d_right)
    return np.where(best_d <= slop_ns, best, -1)


def pose_at(
    stamps: np.ndarray, poses: np.ndarray, target_ns: int, *, slop_ns: int, max_gap_ns: int
) -> np.ndarray | None:
    """Pose at ``target_ns``: exact, interpolated between neighbours at most ``max_gap_ns`` apart,
    else the nearest within ``slop_ns``, else None."""
    if stamps.size == 0:
        return None
    i = int(np.searchsorted(stamps, target_ns, side="left"))
    if i < stamps.size and stamps[i] == target_ns:
        return poses[i].copy()
    if 0 < i < stamps.size and stamps[i] - stamps[i - 1] <= max_gap_ns:
        alpha = (target_ns - int(stamps[i - 1])) / (int(stamps[i]) - int(stamps[i - 1]))
        return interpolate_pose(poses[i - 1], poses[i], alpha)
    j = int(nearest_within(stamps, np.array([target_ns]), slop_ns)[0])
    return None if j < 0 else poses[j].copy()


@dataclass(frozen=True)
class FramePlan:
    """What one output frame is made of: ordinals (per topic) of its messages."""

    cloud_ordinal: int
    stamp_ns: int
    cameras: tuple[int, ...]  # ordinal on the camera topic, -1 = none
    depth: tuple[int, ...]
    labels: tuple[int, ...]


def plan_frames(
    clouds: tuple[np.ndarray, np.ndarray],
    cameras: Sequence[tuple[np.ndarray, np.ndarray]],
    depth: Sequence[tuple[np.ndarray, np.ndarray] | None],
    labels: Sequence[tuple[np.ndarray, np.ndarray] | None],
    *,
    slop_ns: int,
    min_cameras: int,
) -> tuple[list[FramePlan], int, list[int]]:
    """Match every kept cloud with the nearest image of each camera (and depth/labels to that image).

    Returns (plans, clouds dropped for having fewer than ``min_cameras`` images,
    per-camera count of kept frames without that camera).
    """
    cloud_ordinals, cloud_stamps = clouds
    matches = [nearest_within(stamps, cloud_stamps, slop_ns) for _ords, stamps in cameras]
    plans: list[FramePlan] = []
    dropped = 0
    missing = [0] * len(cameras)
    for n, (ordinal, stamp) in enumerate(zip(cloud_ordinals.tolist(), cloud_stamps.tolist(), strict=True)):
        picks = [int(m[n]) for m in matches]
        if sum(p >= 0 for p in picks) < min_cameras:
            dropped += 1
            continue
        cam_ords, depth_ords, label_ords = [], [], []
        for k, pick in enumerate(picks):
            if pick < 0:
                missing[k] += 1
                cam_ords.append(-1)
                depth_ords.append(-1)
                label_ords.append(-1)
                continue
            image_stamp = int(cameras[k][1][pick])
            cam_ords.append(int(cameras[k][0][pick]))
            depth_ords.append(_companion(depth[k] if k < len(depth) else None, image_stamp, slop_ns))
            label_ords.append(_companion(labels[k] if k < len(labels) else None, image_stamp, slop_ns))
        plans.append(FramePlan(ordinal, stamp, tuple(cam_ords), tuple(depth_ords), tuple(label_ords)))
    return plans, dropped, missing


def _companion(track: tuple[np.ndarray, np.ndarray] | None, stamp_ns: int, slop_ns: int) -> int:
    if track is None:
        return -1
    ordinals, stamps = track
    j = int(nearest_within(stamps, np.array([stamp_ns]), slop_ns)[0])
    return -1 if j < 0 else int(ordinals[j])
