"""Where the vehicle was at a cloud's stamp: odometry interpolation, or nothing (null object)."""
from __future__ import annotations

import bisect
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from msg_tools.bags.sync import pose_at

from .stamps import NS_PER_S, StampOrder


class PoseSource(Protocol):
    frame_id: str  # frame the poses are expressed in ("" = unknown)
    expected: bool  # whether poses are expected at all (a cloud may wait for its pose)

    @property
    def newest(self) -> int | None:
        """Stamp (ns) of the newest pose, None before the first."""

    @property
    def last_arrival(self) -> float | None:
        """clock() when the newest pose arrived, None before the first."""

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        """4 x 4 world_T_base at the stamp, or None."""

    def configure(self, *, slop: float, max_gap: float) -> None:
        """Change the matching tolerances."""

    def follow_jump(self, stamp_ns: int, seen: int) -> int:
        """Another stream's header time jumped back to ``stamp_ns``; returns the timeline now current.

        ``seen`` is the timeline that stream followed until now. When odometry is still on it, poses
        stamped after ``stamp_ns`` belong to the old timeline and are forgotten; when odometry
        already jumped (or another stream already made it follow), nothing is forgotten, so poses
        of the new timeline that arrived ahead of the stream stay.
        """


class NoPoses:
    """No odometry topic: every pose is unknown."""

    frame_id = ""
    expected = False

    @property
    def newest(self) -> int | None:
        return None

    @property
    def last_arrival(self) -> float | None:
        return None

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        return None

    def configure(self, *, slop: float, max_gap: float) -> None:
        return None

    def follow_jump(self, stamp_ns: int, seen: int) -> int:
        return seen


class OdometryBuffer:
    """Recent odometry poses; a pose at any stamp by interpolation (msg_tools' rule)."""

    expected = True

    def __init__(self, *, slop: float, max_gap: float, capacity: int = 4096, jump_back: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.frame_id = ""
        self._clock = clock
        self._last_arrival: float | None = None
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._capacity = capacity
        self._order = StampOrder(round(jump_back * NS_PER_S))  # see StampOrder: a new timeline
        self.timeline = 0  # counts jumps back in header time (see follow_jump)
        self.configure(slop=slop, max_gap=max_gap)

    def configure(self, *, slop: float, max_gap: float) -> None:
        self._slop_ns = round(slop * NS_PER_S)
        self._max_gap_ns = round(max_gap * NS_PER_S)

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    @property
    def last_arrival(self) -> float | None:
        return self._last_arrival

    def offer(self, stamp_ns: int, pose: np.ndarray, frame_id: str) -> str | None:
        """Store a pose; returns why it was refused (duplicate / out-of-order stamp) or None."""
        refused = self._order.check(stamp_ns)
        if refused is not None:
            return refused
        if self._order.jumped_from is not None:
            self._forget_after(stamp_ns - 1)
            self.timeline += 1
        self.frame_id = frame_id
        self._last_arrival = self._clock()
        self._stamps.append(stamp_ns)
        self._poses.append(np.asarray(pose, dtype=np.float64))
        if len(self._stamps) > 2 * self._capacity:
            del self._stamps[: self._capacity]
            del self._poses[: self._capacity]
        return None

    def follow_jump(self, stamp_ns: int, seen: int) -> int:
        if self.timeline == seen:
            self._forget_after(stamp_ns)
            self.timeline += 1
        return self.timeline

    def _forget_after(self, after_ns: int) -> None:
        keep = bisect.bisect_right(self._stamps, after_ns)
        del self._stamps[keep:]
        del self._poses[keep:]
        self._order.last = self._stamps[-1] if self._stamps else None

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        if not self._stamps:
            return None
        i = bisect.bisect_left(self._stamps, stamp_ns)
        lo, hi = max(i - 2, 0), min(i + 2, len(self._stamps))
        return pose_at(np.asarray(self._stamps[lo:hi], dtype=np.int64), np.stack(self._poses[lo:hi]), stamp_ns,
                       slop_ns=self._slop_ns, max_gap_ns=self._max_gap_ns)
