"""Query sequences: a query frame plus the first camera frames 5, 10 and 15 m further on.

Distances are horizontal (x, y) path lengths, summed frame to frame. Frames without a
camera feature (a dropped image) count for the distance but are never picked: the
query frame and each later member are the first frames *with* a feature at least the
offset further on. :func:`sequence_table` (offline, every frame at once) and
:class:`SequenceBuilder` (online, one frame at a time) apply the same rule with the
same arithmetic, so they pick the same frames.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from ..errors import InputShapeError, InvalidValueError
from .preprocess import camera_feature

__all__ = ["OFFSETS", "SequenceBatch", "SequenceBuilder", "SequenceConfig", "sequence_table", "travelled_distance"]

OFFSETS: tuple[float, ...] = (5.0, 10.0, 15.0)
FEATURE_SHAPE = (12, 90)


def travelled_distance(xy: np.ndarray) -> np.ndarray:
    """(N, >=2) positions in driving order -> (N,) horizontal path length from the first one."""
    p = np.asarray(xy, np.float64)[:, :2]
    if len(p) == 0:
        return np.zeros(0)
    d = np.diff(p, axis=0)
    steps = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    out = np.empty(len(p))
    out[0] = 0.0
    acc = 0.0
    for i, s in enumerate(steps.tolist(), start=1):  # sequential sums: the builder adds the same way
        acc += s
        out[i] = acc
    return out


def _members(travelled: np.ndarray, query: int, offsets: Sequence[float]) -> list[int] | None:
    """Positions in ``travelled`` (valid frames only, non-decreasing) of the query and its later members."""
    rel = travelled[query:] - travelled[query]
    picks = [query]
    for offset in offsets:
        j = int(np.searchsorted(rel, offset, side="left"))
        if j >= len(rel):
            return None
        picks.append(query + j)
    return picks


def sequence_table(positions: np.ndarray, valid: np.ndarray | None = None, *,
                   offsets: Sequence[float] = OFFSETS) -> np.ndarray:
    """(N, 1 + len(offsets)) frame indices of every frame's sequence; -1 rows where incomplete or invalid."""
    pos = np.asarray(positions, np.float64)
    if pos.ndim != 2 or pos.shape[1] < 2:
        raise InputShapeError(f"positions have shape {pos.shape}; expected (N, 2|3)")
    ok = np.ones(len(pos), bool) if valid is None else np.asarray(valid, bool)
    if ok.shape != (len(pos),):
        raise InputShapeError(f"valid has shape {ok.shape}; expected ({len(pos)},)")
    out = np.full((len(pos), 1 + len(offsets)), -1, np.int64)
    rows = np.flatnonzero(ok)
    t = travelled_distance(pos)[rows]
    for q in range(len(rows)):
        picks = _members(t, q, offsets)
        if picks is None:
            break  # later queries cannot be complete either
        out[rows[q]] = rows[picks]
    return out


@dataclass(frozen=True)
class SequenceConfig:
    """offsets: metres after the query frame (ascending, > 0); min_query_spacing_m: metres between query
    frames (0 = every frame with a feature); max_pending: queries waiting to complete (oldest dropped)."""

    offsets: tuple[float, ...] = OFFSETS
    min_query_spacing_m: float = 0.0
    max_pending: int = 4096

    def __post_init__(self) -> None:
        offs = tuple(self.offsets)
        if not offs or any(not (o > 0) for o in offs) or any(b <= a for a, b in zip(offs, offs[1:], strict=False)):
            raise InvalidValueError(f"offsets={offs}; expected ascending positive metres, e.g. (5.0, 10.0, 15.0)")
        if not self.min_query_spacing_m >= 0:
            raise InvalidValueError(f"min_query_spacing_m={self.min_query_spacing_m}; expected metres >= 0")
        if self.max_pending < 1:
            raise InvalidValueError(f"max_pending={self.max_pending}; expected at least 1")


@dataclass(frozen=True)
class SequenceBatch:
    """Completed queries: frames B x K x 12 x 90 (query frame first) and, per member, its frame index,
    stamp and 4 x 4 pose (NaN when none was given)."""

    frames: np.ndarray  # (B, K, 12, 90) float32
    indices: np.ndarray  # (B, K) int64
    stamps: np.ndarray  # (B, K) float64
    poses: np.ndarray  # (B, K, 4, 4) float64

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def query_indices(self) -> np.ndarray:
        return self.indices[:, 0]

    @property
    def query_stamps(self) -> np.ndarray:
        return self.stamps[:, 0]

    @property
    def query_poses(self) -> np.ndarray:
        return self.poses[:, 0]


@dataclass
class _Frame:
    index: int
    stamp: float
    travelled: float
    pose: np.ndarray
    feature: np.ndarray | None


@dataclass
class SequenceBuilder:
    """Feed camera frames in driving order; a query comes out once the vehicle is the last offset further on.

    >>> builder = SequenceBuilder()
    >>> batch = builder.push(feature_12x90, stamp=t, pose=world_T_base)   # SequenceBatch or None
    """

    config: SequenceConfig = field(default_factory=SequenceConfig)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget every frame (e.g. after a relocalisation jump)."""
        self._frames: deque[_Frame] = deque()
        self._pending: deque[int] = deque()  # frame indices of queries waiting for their last member
        self._last_xy: np.ndarray | None = None
        self._travelled = 0.0
        self._last_query_at = -math.inf
        self._next_index = 0
        self.dropped = 0  # pending queries given up because of max_pending

    @property
    def pending(self) -> int:
        return len(self._pending)

    def push(self, feature: np.ndarray | None, *, stamp: float, pose: np.ndarray,
             index: int | None = None) -> SequenceBatch | None:
        """Add one frame: its 12 x 90 camera feature (None: no image), header stamp and pose.

        pose: 4 x 4 world_T_base, or a position (x, y[, z]). index: the frame's number
        (default: one more than the last). Returns the queries this frame completed.
        """
        T = _pose_matrix(pose)
        f = None
        if feature is not None:
            f = np.asarray(feature, np.float32)
            if f.shape != FEATURE_SHAPE:
                raise InputShapeError(f"feature has shape {f.shape}; expected 12 x 90 (camera_feature)")
        idx = self._next_index if index is None else int(index)
        if self._frames and idx <= self._frames[-1].index:
            raise InvalidValueError(f"frame index {idx} is not after the last one ({self._frames[-1].index})")
        self._next_index = idx + 1
        xy = T[:2, 3].copy()
        if self._last_xy is not None:
            dx, dy = float(xy[0] - self._last_xy[0]), float(xy[1] - self._last_xy[1])
            self._travelled += float(np.sqrt(np.float64(dx * dx + dy * dy)))
        self._last_xy = xy
        self._frames.append(_Frame(idx, float(stamp), self._travelled, T, f))
        spacing = self.config.min_query_spacing_m
        if f is not None and (spacing == 0 or self._travelled - self._last_query_at >= spacing):
            self._pending.append(idx)
            self._last_query_at = self._travelled
            while len(self._pending) > self.config.max_pending:
                self._pending.popleft()
                self.dropped += 1
        if f is None:
            self._trim()
            return None
        return self._complete()

    def push_camera(self, depth: np.ndarray | None, labels: np.ndarray | None, K: np.ndarray,
                    lidar_T_cam: np.ndarray, *, stamp: float, pose: np.ndarray,
                    index: int | None = None) -> SequenceBatch | None:
        """:meth:`push` from a metric depth image and a label image (None: the image is missing)."""
        feature = None if depth is None or labels is None else camera_feature(depth, labels, K, lidar_T_cam)
        return self.push(feature, stamp=stamp, pose=pose, index=index)

    def _complete(self) -> SequenceBatch | None:
        valid = [fr for fr in self._frames if fr.feature is not None]
        travelled = np.array([fr.travelled for fr in valid])
        position = {fr.index: i for i, fr in enumerate(valid)}
        done: list[list[_Frame]] = []
        while self._pending:
            picks = _members(travelled, position[self._pending[0]], self.config.offsets)
            if picks is None:
                break  # later queries are no further on
            self._pending.popleft()
            done.append([valid[p] for p in picks])
        self._trim()
        if not done:
            return None
        # done holds frames of valid only: their features are not None
        features = [np.stack([cast(np.ndarray, fr.feature) for fr in seq]) for seq in done]
        return SequenceBatch(
            frames=np.stack(features).astype(np.float32),
            indices=np.array([[fr.index for fr in seq] for seq in done], np.int64),
            stamps=np.array([[fr.stamp for fr in seq] for seq in done], np.float64),
            poses=np.stack([np.stack([fr.pose for fr in seq]) for seq in done]),
        )

    def _trim(self) -> None:
        """Drop frames older than the oldest pending query (keep the newest for distances)."""
        oldest = self._pending[0] if self._pending else None
        while len(self._frames) > 1 and (oldest is None or self._frames[0].index < oldest):
            self._frames.popleft()


def _pose_matrix(pose: np.ndarray) -> np.ndarray:
    p = np.asarray(pose, np.float64)
    if p.shape == (4, 4):
        return p
    if p.shape in ((2,), (3,)):
        T = np.eye(4)
        T[: len(p), 3] = p
        return T
    raise InputShapeError(f"pose has shape {p.shape}; expected a 4 x 4 world_T_base or a position (x, y[, z])")
