"""Approximate time synchronisation of N camera streams with one LiDAR stream (no ROS here).

Each cloud becomes one frame. For every camera, the image whose header stamp is
nearest the cloud's within ``slop`` is used (``msg_tools.bags.sync.nearest_within``,
the rule the bag reader applies offline). A cloud is released as soon as every camera
is *decided*:

* the camera has an image stamped at or after the cloud (later images can only be
  farther away), or
* the camera is *stopped*: its newest image is more than ``camera_timeout`` older
  than the newest cloud (or it never sent one, and clouds have arrived for longer
  than that) and nothing came from it for ``max_wait`` seconds of wall time: its slot
  is None (unless an old image still lies within the slop), the frame is degraded.

With odometry, the pose is decided the same way: a pose stamped at or after the
cloud, or odometry stopped by the same rule (odometry computed from the cloud itself
arrives after it). A cloud whose cameras or pose are not all decided waits at most
``max_wait`` seconds of wall time (messages in flight), then goes with what is there.
An image that arrives after its frame went without it is counted per camera (``late``):
the mark of samples lost in transport and repaired seconds later (a process that
publishes images and clouds through Fast DDS's default 512 KiB shared-memory segment).
Waiting longer for such repairs does not help (docs/limitations.md;
benchmarks/tools/single_process_publisher.py): frames then arrive in bursts and the worker drops them.
At most ``max_pending`` clouds wait; the oldest is dropped beyond that. Duplicate and
out-of-order stamps are refused per stream.
"""
from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_tools.bags.sync import nearest_within
from ros_common.poses import NoPoses, PoseSource
from ros_common.stamps import NS_PER_S, StampOrder

from .config import SyncConfig

NO_CAMERA = "frame: no camera"
LATE_IMAGE = "image: arrived after its frame"
BACKLOG = "frame: sync backlog"
TIME_JUMPED = "cloud: time jumped back, new session"


@dataclass
class SyncedFrame:
    """One synchronised frame; camera payloads are whatever the caller offered (None = none)."""

    stamp_ns: int
    cameras: list[Any | None]
    points: np.ndarray
    pose: np.ndarray | None
    arrival: float  # clock() when its cloud arrived
    stopped: tuple[int, ...]  # cameras counted as stopped for this frame
    new_session: bool = False  # the first frame after header time jumped back (see StampOrder)


@dataclass
class _Cloud:
    stamp_ns: int
    points: np.ndarray
    arrival: float
    new_session: bool = False


class Synchroniser:
    def __init__(
        self,
        config: SyncConfig,
        num_cameras: int,
        *,
        poses: PoseSource | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._clock = clock
        self._poses: PoseSource = poses if poses is not None else NoPoses()
        self._images: list[deque[tuple[int, Any]]] = [deque() for _ in range(num_cameras)]
        self._arrivals: list[float | None] = [None] * num_cameras  # clock() of each camera's newest image
        self._image_order = [StampOrder() for _ in range(num_cameras)]
        self._cloud_order = StampOrder()
        self.restarts = 0  # times header time jumped back on the cloud stream
        self._timeline = 0  # the odometry timeline this stream follows (PoseSource.follow_jump)
        self._carry_session = False  # a new-session frame was dropped: the next released frame starts it
        self._released_without: deque[tuple[int, frozenset[int]]] = deque(maxlen=64)  # (stamp, cameras missing)
        self.late = [0] * num_cameras  # images that came after their frame was released without them
        self._pending: deque[_Cloud] = deque()
        self._first_cloud: int | None = None
        self.drops: Counter[str] = Counter()  # frames dropped by the synchroniser, by reason
        self.missing = [0] * num_cameras  # released frames without each camera
        self.released = 0
        self.config = config

    @property
    def config(self) -> SyncConfig:
        return self._config

    @config.setter
    def config(self, config: SyncConfig) -> None:
        self._config = config
        self._slop_ns = round(config.slop * NS_PER_S)
        self._timeout_ns = round(config.camera_timeout * NS_PER_S)
        for order in (*self._image_order, self._cloud_order):
            order.jump_back_ns = round(config.jump_back * NS_PER_S)
        for k, images in enumerate(self._images):
            if images.maxlen != config.image_buffer:
                self._images[k] = deque(images, maxlen=config.image_buffer)

    @property
    def num_cameras(self) -> int:
        return len(self._images)

    @property
    def newest_stamp(self) -> int | None:
        """Header stamp (ns) of the newest accepted cloud."""
        return self._cloud_order.last

    @property
    def pending(self) -> int:
        return len(self._pending)

    # -- input ------------------------------------------------------------------------------
    def offer_image(self, camera: int, stamp_ns: int, payload: Any) -> str | None:
        """Buffer one camera image; returns why it was refused, or None."""
        refused = self._image_order[camera].check(stamp_ns)
        if refused is None:
            if self._image_order[camera].jumped_from is not None:
                self._forget_images(camera, after_ns=stamp_ns - 1)
                self._image_order[camera].last = stamp_ns
            if any(camera in missing and abs(stamp_ns - released) <= self._slop_ns
                   for released, missing in self._released_without):
                self.late[camera] += 1
            self._images[camera].append((stamp_ns, payload))
            self._arrivals[camera] = self._clock()
        return refused

    def offer_cloud(self, stamp_ns: int, points: np.ndarray) -> str | None:
        """Queue one cloud for release by :meth:`ready`; returns why it was refused, or None."""
        refused = self._cloud_order.check(stamp_ns)
        if refused is not None:
            return refused
        new_session = self._cloud_order.jumped_from is not None
        if new_session:  # another timeline: what was buffered after this stamp belongs to the old one
            self.restarts += 1
            self._first_cloud = None
            self._pending = deque(c for c in self._pending if c.stamp_ns < stamp_ns)
            for k in range(self.num_cameras):
                self._forget_images(k, after_ns=stamp_ns + self._slop_ns)
            self._timeline = self._poses.follow_jump(stamp_ns + self._slop_ns, self._timeline)
        if self._first_cloud is None:
            self._first_cloud = stamp_ns
        self._pending.append(_Cloud(stamp_ns, points, self._clock(), new_session))
        while len(self._pending) > self._config.max_pending:
            self._carry_session |= self._pending.popleft().new_session
            self.drops[BACKLOG] += 1
        return None

    # -- output -----------------------------------------------------------------------------
    def ready(self) -> list[SyncedFrame]:
        """Frames whose cameras are all decided, or whose cloud waited ``max_wait``; in stamp order."""
        out: list[SyncedFrame] = []
        now = self._clock()
        while self._pending:
            cloud = self._pending[0]
            picks = [self._pick(k, cloud.stamp_ns, now) for k in range(self.num_cameras)]
            decided = all(d for d, _, _ in picks) and self._pose_decided(cloud.stamp_ns, now)
            if not decided and now - cloud.arrival < self._config.max_wait:
                break
            self._pending.popleft()
            cameras = [payload for _, payload, _ in picks]
            if sum(c is not None for c in cameras) < self._config.min_cameras:
                self.drops[NO_CAMERA] += 1
                self._carry_session |= cloud.new_session
                continue
            missing = frozenset(k for k, payload in enumerate(cameras) if payload is None)
            for k in missing:
                self.missing[k] += 1
            if missing:
                self._released_without.append((cloud.stamp_ns, missing))
            stopped = tuple(k for k, (_, _, is_stopped) in enumerate(picks) if is_stopped)
            self.released += 1
            new_session = cloud.new_session or self._carry_session
            self._carry_session = False
            out.append(SyncedFrame(cloud.stamp_ns, cameras, cloud.points, self._poses.pose_at(cloud.stamp_ns),
                                   cloud.arrival, stopped, new_session))
        return out

    def _forget_images(self, camera: int, *, after_ns: int) -> None:
        """Drop one camera's images stamped after ``after_ns``; its order check restarts from what is left."""
        images = self._images[camera]
        kept = [item for item in images if item[0] <= after_ns]
        images.clear()
        images.extend(kept)
        self._image_order[camera].last = kept[-1][0] if kept else None

    def _pick(self, camera: int, stamp_ns: int, now: float) -> tuple[bool, Any | None, bool]:
        """(decided, payload or None, stopped) of one camera for a cloud stamp."""
        stopped = self._stopped(camera, now)
        images = self._images[camera]
        if not images:
            return stopped, None, stopped
        stamps = np.fromiter((s for s, _ in images), dtype=np.int64, count=len(images))
        j = int(nearest_within(stamps, np.array([stamp_ns]), self._slop_ns)[0])
        payload = images[j][1] if j >= 0 else None
        return images[-1][0] >= stamp_ns or stopped, payload, stopped

    def _pose_decided(self, stamp_ns: int, now: float) -> bool:
        if not self._poses.expected:
            return True
        newest = self._poses.newest
        if newest is not None and newest >= stamp_ns:
            return True
        return self._silent(newest, self._poses.last_arrival, now)

    def _silent(self, last_stamp: int | None, last_arrival: float | None, now: float) -> bool:
        """A stream is silent when its newest stamp lies ``camera_timeout`` before the newest cloud's
        (header time; the first cloud's if it never sent) and it sent nothing for ``max_wait`` wall seconds.

        The wall-time half keeps a live stream from looking silent across a jump in header time.
        """
        newest_cloud = self._cloud_order.last
        last = last_stamp if last_stamp is not None else self._first_cloud
        if newest_cloud is None or last is None or newest_cloud - last <= self._timeout_ns:
            return False
        return last_arrival is None or now - last_arrival >= self._config.max_wait

    def _stopped(self, camera: int, now: float) -> bool:
        images = self._images[camera]
        return self._silent(images[-1][0] if images else None, self._arrivals[camera], now)

    def stopped_cameras(self) -> tuple[int, ...]:
        """Cameras silent for ``camera_timeout`` of header time (and ``max_wait`` of wall time)."""
        now = self._clock()
        return tuple(k for k in range(self.num_cameras) if self._stopped(k, now))
