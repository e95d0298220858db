"""Scan Context (Kim & Kim, IROS 2018): a training-free LiDAR place descriptor, the evaluation's baseline.

A cloud becomes a rings x sectors matrix over a polar grid around the sensor
(default 20 rings x 60 sectors out to 80 m); each bin holds the highest point in it,
measured as ``z + lidar_height`` (height above the ground when the sensor is mounted
``lidar_height`` above it), 0 for an empty bin. Points are read in the sensor's own
frame; which horizontal axis points forward does not matter, because matching
tries every column shift (a yaw rotation of the vehicle rotates the columns).

Matching, as in the paper:

1. ring key: one number per ring (the share of occupied bins, or the mean height),
   rotation invariant; the ``candidates`` nearest ring keys (L2) are kept;
2. each candidate is compared with the query under all column shifts; the distance
   is the mean over columns of (1 - cosine) of matching columns, columns empty in
   either matrix left out, minimised over shifts.

``sc_distance(a, b)`` returns that distance and the shift ``s`` for which
``np.roll(b, s, axis=1)`` best matches ``a``: a cloud turned by +psi (counter-
clockwise about z) gives ``s = psi / (360 / sectors)``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .errors import InputShapeError, InvalidValueError
from .exclusion import matchable
from .growable import GrowableArray
from .points import finite_xyz

__all__ = [
    "RING_KEYS", "ScanContextConfig", "ScanContextMatch", "ScanContextMatcher", "ScanContextResult",
    "ScanContextRows", "rank_database", "ring_key", "sc_distance", "scan_context",
]

RING_KEYS = ("occupancy", "mean")


@dataclass(frozen=True)
class ScanContextConfig:
    num_rings: int = 20
    num_sectors: int = 60
    max_range: float = 80.0  # m; points farther away (horizontally) are left out
    min_range: float = 0.0  # m; points closer (e.g. the ego vehicle) are left out
    lidar_height: float = 2.0  # m added to z so that heights above the ground are positive
    ring_key: str = "occupancy"  # occupancy | mean
    candidates: int = 10  # ring-key nearest neighbours compared in full
    exclude_recent_s: float = 30.0  # entries newer than this (by stamp) are not matched

    def __post_init__(self) -> None:
        for name in ("num_rings", "num_sectors", "candidates"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InvalidValueError(f"ScanContextConfig.{name}={value!r}; it must be a positive integer")
        if not (0.0 <= self.min_range < self.max_range):
            raise InvalidValueError(
                f"ScanContextConfig min_range={self.min_range!r}, max_range={self.max_range!r}; "
                "accepted: 0 <= min_range < max_range"
            )
        if self.ring_key not in RING_KEYS:
            raise InvalidValueError(f"ScanContextConfig.ring_key={self.ring_key!r}; accepted: {', '.join(RING_KEYS)}")
        if not self.exclude_recent_s >= 0:
            raise InvalidValueError(f"ScanContextConfig.exclude_recent_s={self.exclude_recent_s!r}; it must be >= 0")
        if not np.isfinite(self.lidar_height):
            raise InvalidValueError(f"ScanContextConfig.lidar_height={self.lidar_height!r}; it must be a finite number")

    def describing(self) -> dict[str, float | int]:
        """What makes a scan context out of a cloud (not how it is searched): equal here, equal matrices."""
        return {"num_rings": int(self.num_rings), "num_sectors": int(self.num_sectors),
                "max_range": float(self.max_range), "min_range": float(self.min_range),
                "lidar_height": float(self.lidar_height)}


def scan_context(points: np.ndarray, *, config: ScanContextConfig | None = None) -> np.ndarray:
    """N x (>=3) points (x, y, z, ...) -> num_rings x num_sectors float32 max heights (0 = empty bin).

    Ring i covers horizontal ranges [i, i + 1) * max_range / num_rings; sector j covers
    azimuths [j, j + 1) * 360 / num_sectors degrees counter-clockwise from +x.
    Heights below the ground (z + lidar_height < 0) count as 0. Non-finite points are dropped.
    """
    cfg = config if config is not None else ScanContextConfig()
    xyz = finite_xyz(points)
    rng = np.hypot(xyz[:, 0], xyz[:, 1])
    keep = (rng >= cfg.min_range) & (rng < cfg.max_range)
    xyz, rng = xyz[keep], rng[keep]
    out = np.zeros((cfg.num_rings, cfg.num_sectors), np.float32)
    if len(xyz) == 0:
        return out
    ring = np.minimum((rng * (cfg.num_rings / cfg.max_range)).astype(np.int64), cfg.num_rings - 1)
    azimuth = np.mod(np.arctan2(xyz[:, 1], xyz[:, 0]), 2.0 * np.pi)
    sector = np.minimum((azimuth * (cfg.num_sectors / (2.0 * np.pi))).astype(np.int64), cfg.num_sectors - 1)
    height = np.maximum(xyz[:, 2] + cfg.lidar_height, 0.0)
    top = np.zeros(cfg.num_rings * cfg.num_sectors)  # heights are >= 0: an empty bin stays 0
    np.maximum.at(top, ring * cfg.num_sectors + sector, height)
    out[:] = top.reshape(out.shape)  # float64 -> float32 after the maximum: the same as the maximum of the cast
    return out


def ring_key(sc: np.ndarray, *, kind: str = "occupancy") -> np.ndarray:
    """Rotation-invariant key of a scan context: per ring, the share of occupied bins or the mean height."""
    m = _check_sc(sc, "sc")
    if kind == "occupancy":
        return (m > 0).mean(axis=1).astype(np.float32)
    if kind == "mean":
        return m.mean(axis=1).astype(np.float32)
    raise InvalidValueError(f"ring key kind {kind!r}; accepted: {', '.join(RING_KEYS)}")


def sc_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """(distance in [0, 1], shift): the column-shift-aware cosine distance of two scan contexts.

    ``shift`` is the s in [0, sectors) minimising the distance between ``a`` and
    ``np.roll(b, s, axis=1)`` (the lowest such s on ties). When no shift leaves any
    column occupied in both, the distance is 1.
    """
    dist = _all_shifts(_check_sc(a, "a"), _check_sc(b, "b"))
    shift = int(np.argmin(dist))
    return float(dist[shift]), shift


def _all_shifts(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(sectors,) distance between a and np.roll(b, s, axis=1) for every s."""
    if a.shape != b.shape:
        raise InputShapeError(f"scan contexts of shapes {a.shape} and {b.shape}; they must be equal")
    sectors = a.shape[1]
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    # dots[s, j] = a[:, j] . b[:, (j - s) % sectors]: the column dot products of every shift
    cols = (np.arange(sectors)[None, :] - np.arange(sectors)[:, None]) % sectors  # (s, j)
    gram = a64.T @ b64  # (j, k) = a[:, j] . b[:, k]
    dots = gram[np.arange(sectors)[None, :], cols]
    na, nb = np.linalg.norm(a64, axis=0), np.linalg.norm(b64, axis=0)
    norms = na[None, :] * nb[cols]
    valid = norms > 0
    cos = np.divide(dots, norms, out=np.zeros_like(dots), where=valid)
    count = valid.sum(axis=1)
    mean_cos = np.divide(cos.sum(axis=1), count, out=np.zeros(sectors), where=count > 0)
    return np.clip(1.0 - mean_cos, 0.0, 1.0)


def _check_sc(sc: np.ndarray, name: str) -> np.ndarray:
    m = np.asarray(sc)
    if m.ndim != 2 or m.shape[0] < 1 or m.shape[1] < 1 or m.dtype.kind not in "fiu":
        raise InputShapeError(f"{name} is a {m.dtype} array of shape {m.shape}; expected rings x sectors numbers")
    return m


@dataclass(frozen=True)
class ScanContextMatch:
    id: int
    distance: float  # sc_distance, 0..1
    shift: int  # column shift aligning the match with the query
    stamp: float
    position: tuple[float, float, float] | None
    rank: int  # 0 = best


@dataclass
class ScanContextResult:
    id: int  # the query's own id, now in the matcher
    matches: list[ScanContextMatch]
    timings: dict[str, float] = field(default_factory=dict)  # stage -> seconds


class ScanContextMatcher:
    """A growing set of scan contexts searched like the loop detector searches its map.

    Entries whose stamp is later than ``query stamp - exclude_recent_s`` are not
    matched (the same rule as the detector). Ids count from 0 in insertion order.
    """

    def __init__(self, config: ScanContextConfig | None = None) -> None:
        self.config = cfg = config if config is not None else ScanContextConfig()
        self._scs = np.zeros((0, cfg.num_rings, cfg.num_sectors), np.float32)
        self._keys = np.zeros((0, cfg.num_rings), np.float32)
        self._stamps = np.zeros(0, np.float64)
        self._positions = np.zeros((0, 3), np.float64)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def descriptors(self) -> np.ndarray:
        """(N, rings, sectors) copy of the stored scan contexts."""
        return self._scs[: self._n].copy()

    @property
    def stamps(self) -> np.ndarray:
        return self._stamps[: self._n].copy()

    def describe(self, points: np.ndarray) -> np.ndarray:
        return scan_context(points, config=self.config)

    def add(self, sc: np.ndarray, *, stamp: float, position: np.ndarray | None = None) -> int:
        """Store one scan context; returns its id."""
        m = _check_sc(sc, "sc")
        cfg = self.config
        if m.shape != (cfg.num_rings, cfg.num_sectors):
            raise InputShapeError(f"sc has shape {m.shape}; this matcher stores {cfg.num_rings} x {cfg.num_sectors}")
        if not np.isfinite(stamp):
            raise InvalidValueError(f"stamp={stamp!r}; expected finite seconds")
        pos = np.full(3, np.nan) if position is None else np.asarray(position, np.float64).reshape(-1)[:3]
        if pos.shape != (3,):
            raise InputShapeError(f"position has {pos.size} values; expected x, y, z")
        if self._n == len(self._stamps):
            grow = max(16, 2 * self._n)
            self._scs = _grown(self._scs, grow)
            self._keys = _grown(self._keys, grow)
            self._stamps = _grown(self._stamps, grow)
            self._positions = _grown(self._positions, grow)
        i = self._n
        self._scs[i] = m
        self._keys[i] = ring_key(m, kind=cfg.ring_key)
        self._stamps[i] = float(stamp)
        self._positions[i] = pos
        self._n += 1
        return i

    def search(self, sc: np.ndarray, *, stamp: float | None = None, k: int | None = None) -> list[ScanContextMatch]:
        """The best ``k`` (default: all ``candidates``) of the ring-key candidates, by sc_distance.

        With ``stamp``, entries newer than ``stamp - exclude_recent_s`` are left out.
        """
        q = _check_sc(sc, "sc")
        cfg = self.config
        k = cfg.candidates if k is None else int(k)
        if k < 1:
            raise InvalidValueError(f"k={k}; it must be at least 1")
        n = self._n
        allowed = np.arange(n) if stamp is None else np.flatnonzero(matchable(self._stamps[:n], stamp,
                                                                                cfg.exclude_recent_s))
        if len(allowed) == 0:
            return []
        key = ring_key(q, kind=cfg.ring_key)
        key_d = ((self._keys[allowed] - key[None, :]) ** 2).sum(axis=1)
        c = min(cfg.candidates, len(allowed))
        near = np.argpartition(key_d, c - 1)[:c] if c < len(allowed) else np.arange(len(allowed))
        scored = []
        for row in allowed[near].tolist():
            d, s = sc_distance(q, self._scs[row])
            scored.append((d, row, s))
        scored.sort()
        out = []
        for rank, (d, row, s) in enumerate(scored[:k]):
            p = self._positions[row]
            pos = None if np.isnan(p).all() else (float(p[0]), float(p[1]), float(p[2]))
            out.append(ScanContextMatch(int(row), float(d), int(s), float(self._stamps[row]), pos, rank))
        return out

    def process(self, points: np.ndarray, *, stamp: float, position: np.ndarray | None = None,
                k: int | None = None) -> ScanContextResult:
        """Describe a keyframe's cloud, search (recent entries excluded), then add it; timed per stage."""
        tic = time.perf_counter()
        sc = self.describe(points)
        timings = {"describe": time.perf_counter() - tic}
        tic = time.perf_counter()
        matches = self.search(sc, stamp=stamp, k=k)
        timings["search"] = time.perf_counter() - tic
        tic = time.perf_counter()
        new_id = self.add(sc, stamp=stamp, position=position)
        timings["add"] = time.perf_counter() - tic
        return ScanContextResult(id=new_id, matches=matches, timings=timings)


class ScanContextRows:
    """Scan contexts kept in the rows of another store (the loop detector's map), searched among its first rows.

    Row ``i`` here is row ``i`` there, so the store's own exclusion (its newest rows) carries over as
    ``rows``. An empty scan context (no point in range, or a row that has none) is never proposed.
    """

    def __init__(self, config: ScanContextConfig | None = None) -> None:
        self.config = cfg = config if config is not None else ScanContextConfig()
        self._scs = GrowableArray(np.float32, (cfg.num_rings, cfg.num_sectors))
        self._keys = GrowableArray(np.float32, (cfg.num_rings,))
        self._occupied = GrowableArray(np.bool_)

    def __len__(self) -> int:
        return len(self._scs)

    def describe(self, points: np.ndarray) -> np.ndarray:
        return scan_context(points, config=self.config)

    def add(self, sc: np.ndarray | None) -> int:
        """Append one row (None: a row without a scan context); returns its row."""
        cfg = self.config
        m = np.zeros((cfg.num_rings, cfg.num_sectors), np.float32) if sc is None else _check_sc(sc, "sc")
        if m.shape != (cfg.num_rings, cfg.num_sectors):
            raise InputShapeError(f"sc has shape {m.shape}; these rows hold {cfg.num_rings} x {cfg.num_sectors}")
        self._scs.extend(m[None])
        self._keys.extend(ring_key(m, kind=cfg.ring_key)[None])
        self._occupied.extend(np.array([bool(m.any())]))
        return len(self) - 1

    def matrices(self) -> np.ndarray:
        """(N, rings, sectors) view of every row's scan context (zeros: a row without one)."""
        return self._scs.view()

    def with_config(self, config: ScanContextConfig) -> ScanContextRows:
        """The same scan contexts under another config of the same shape (its search settings, its ring keys)."""
        out = ScanContextRows(config)
        for m in self.matrices():
            out.add(m if m.any() else None)
        return out

    def search(self, sc: np.ndarray, *, rows: int, k: int, max_distance: float = 1.0,
               allowed: np.ndarray | None = None) -> list[tuple[int, float]]:
        """(row, sc_distance) of the best ``k`` among rows ``[0, rows)`` (those where the bool mask ``allowed``
        holds, when given), nearest first, distances <= max_distance.

        The ``config.candidates`` nearest ring keys (at least ``k``) are compared under every column shift.
        """
        q = _check_sc(sc, "sc")
        if k < 1:
            raise InvalidValueError(f"k={k}; it must be at least 1")
        occupied = self._occupied.view()[: max(0, min(rows, len(self)))]
        if allowed is not None:
            mask = np.zeros(len(occupied), np.bool_)
            given = np.asarray(allowed, np.bool_)[: len(occupied)]
            mask[: len(given)] = given
            occupied = occupied & mask
        allowed = np.flatnonzero(occupied)
        if len(allowed) == 0 or not q.any():
            return []
        key = ring_key(q, kind=self.config.ring_key)
        key_d = ((self._keys.view()[allowed] - key[None, :]) ** 2).sum(axis=1)
        c = min(max(self.config.candidates, k), len(allowed))
        near = allowed[np.argpartition(key_d, c - 1)[:c]] if c < len(allowed) else allowed
        scs = self._scs.view()
        scored = sorted((float(_all_shifts(q, scs[row]).min()), int(row)) for row in near.tolist())
        return [(row, d) for d, row in scored[:k] if d <= max_distance]


def rank_database(
    queries: np.ndarray, database: np.ndarray, *, k: int, config: ScanContextConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Ranked retrieval of (Q, rings, sectors) query scan contexts in a (M, rings, sectors) database.

    Returns (ids, distances), both (Q, k): database indices best first (-1 = none) and
    sc distances (inf = none); only the ``config.candidates`` nearest ring keys are ranked.
    """
    cfg = config if config is not None else ScanContextConfig()
    matcher = ScanContextMatcher(cfg)
    for sc in np.asarray(database):
        matcher.add(sc, stamp=0.0)
    ids = np.full((len(queries), k), -1, np.int64)
    dist = np.full((len(queries), k), np.inf)
    for row, sc in enumerate(np.asarray(queries)):
        for m in matcher.search(sc, k=k):
            ids[row, m.rank], dist[row, m.rank] = m.id, m.distance
    return ids, dist


def _grown(arr: np.ndarray, rows: int) -> np.ndarray:
    out = np.zeros((rows, *arr.shape[1:]), arr.dtype)
    out[: len(arr)] = arr
    return out
