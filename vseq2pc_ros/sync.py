"""Pairing depth and label images by stamp, and holding clouds / camera frames until their pose is known.

Pure Python (no ROS): the node calls these on its callback thread only.
"""
from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ros_common.poses import PoseSource
from ros_common.stamps import NS_PER_S, StampOrder

NO_PAIR = "camera: depth or labels image without partner"
SIZE_MISMATCH = "camera: image sizes differ"  # depth vs labels, or images vs camera_info
NO_POSE = "no pose: odometry does not cover the stamp"
POSE_TIMEOUT = "no pose: odometry did not arrive in time"
NO_CAMERA_INFO = "camera: no camera_info"
QUEUE_FULL = "sync: too many items waiting for poses"
TIME_JUMPED = "time jumped back: new session"
OLD_TIMELINE = "sync: waiting when time jumped back"


class ImagePairs:
    """Depth and label images of one camera; a pair comes out once both stamps agree within ``slop``."""

    def __init__(self, *, slop: float, capacity: int, jump_back: float = 0.0) -> None:
        self.slop_ns = round(slop * NS_PER_S)
        self.capacity = capacity
        self._buffers: dict[str, deque[tuple[int, Any]]] = {"depth": deque(), "labels": deque()}
        jump_back_ns = round(jump_back * NS_PER_S)
        self.orders = {"depth": StampOrder(jump_back_ns), "labels": StampOrder(jump_back_ns)}
        self.unpaired = 0  # images given up without a partner

    def offer(self, kind: str, stamp_ns: int, image: Any) -> tuple[str | None, tuple[int, Any, Any] | None]:
        """(refusal reason or None, (stamp_ns, depth, labels) when a pair completed or None).

        ``orders[kind].jumped_from`` then says whether this image started a new timeline (see StampOrder).
        """
        refused = self.orders[kind].check(stamp_ns)
        if refused is not None:
            return refused, None
        if self.orders[kind].jumped_from is not None:  # buffered after this stamp: the old timeline, never pairs
            for buffer in self._buffers.values():
                kept = [item for item in buffer if item[0] <= stamp_ns + self.slop_ns]
                self.unpaired += len(buffer) - len(kept)
                buffer.clear()
                buffer.extend(kept)
        other_kind = "labels" if kind == "depth" else "depth"
        other = self._buffers[other_kind]
        best = None
        for i, (ns, _) in enumerate(other):
            if abs(ns - stamp_ns) <= self.slop_ns and (
                best is None or abs(ns - stamp_ns) < abs(other[best][0] - stamp_ns)
            ):
                best = i
        if best is None:
            mine = self._buffers[kind]
            mine.append((stamp_ns, image))
            while len(mine) > self.capacity:
                mine.popleft()
                self.unpaired += 1
            return None, None
        ns, partner = other[best]
        for _ in range(best + 1):  # older unpaired partners will never pair (stamps increase)
            other.popleft()
        self.unpaired += best
        mine = self._buffers[kind]
        while mine and mine[0][0] < stamp_ns:
            mine.popleft()
            self.unpaired += 1
        stamp = min(ns, stamp_ns)
        pair = (stamp, image, partner) if kind == "depth" else (stamp, partner, image)
        return None, pair


@dataclass
class Waiting:
    stamp_ns: int
    payload: Any
    arrival: float


class PoseQueue:
    """Items (clouds, camera frames) in stamp order, released with their pose once odometry covers them.

    An item whose pose cannot come (odometry already newer, no pose within the tolerances) or
    does not come within ``max_wait`` s of wall time is dropped with a reason.
    """

    def __init__(self, poses: PoseSource, *, max_wait: float, capacity: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.poses = poses
        self.max_wait = max_wait
        self.capacity = capacity
        self._clock = clock
        self._items: deque[Waiting] = deque()
        self.drops: Counter[str] = Counter()

    def __len__(self) -> int:
        return len(self._items)

    def put(self, stamp_ns: int, payload: Any) -> None:
        self._items.append(Waiting(stamp_ns, payload, self._clock()))
        while len(self._items) > self.capacity:
            self._items.popleft()
            self.drops[QUEUE_FULL] += 1

    def forget_after(self, stamp_ns: int) -> None:
        """Time jumped back to ``stamp_ns``: items stamped after it belong to the old timeline."""
        kept = [item for item in self._items if item.stamp_ns <= stamp_ns]
        self.drops[OLD_TIMELINE] += len(self._items) - len(kept)
        self._items = deque(kept)

    def ready(self, extra_ready: Callable[[Any], bool] = lambda payload: True,
              extra_reason: str = NO_CAMERA_INFO) -> list[tuple[Waiting, np.ndarray]]:
        """Items whose pose is known (and ``extra_ready``), in order; items past hope are dropped."""
        out = []
        now = self._clock()
        while self._items:
            item = self._items[0]
            pose = self.poses.pose_at(item.stamp_ns)
            if pose is not None and extra_ready(item.payload):
                self._items.popleft()
                out.append((item, pose))
                continue
            newest = self.poses.newest
            if pose is None and newest is not None and newest > item.stamp_ns:
                self._items.popleft()
                self.drops[NO_POSE] += 1
                continue
            if now - item.arrival > self.max_wait:
                self._items.popleft()
                self.drops[POSE_TIMEOUT if pose is None else extra_reason] += 1
                continue
            break  # later items are newer: they wait too
        return out
