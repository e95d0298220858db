"""Place labels and (query sequence, LiDAR scan) pairs, as the release and the paper define them.

Label of a pair whose poses lie d metres apart (bird's-eye): y = 1 for d < 3 m, else
1 - 1 / (1 + exp((10 - d) / 1.5)). Training samples positives (d < 3 m) and negatives
(d > 20 m); evaluation takes every positive with a frame gap above 50 and 100
random negatives per positive.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidValueError

__all__ = ["PairSet", "TrainPairConfig", "evaluation_pairs", "place_label", "planar_distances", "training_pairs"]

POSITIVE_RADIUS = 3.0
NEGATIVE_RADIUS = 20.0


def place_label(d: np.ndarray) -> np.ndarray:
    """Soft same-place label of bird's-eye distances (metres)."""
    d = np.asarray(d, np.float64)
    y = 1.0 - 1.0 / (1.0 + np.exp(np.clip((10.0 - d) / 1.5, -60.0, 60.0)))
    return np.where(d < POSITIVE_RADIUS, 1.0, y)


def planar_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) bird's-eye distances between positions (A, >=2) and (B, >=2)."""
    d = np.asarray(a, np.float64)[:, None, :2] - np.asarray(b, np.float64)[None, :, :2]
    return np.sqrt((d * d).sum(axis=2))


@dataclass(frozen=True)
class PairSet:
    """Pairs of a query frame (its sequence) and a scan frame, with their distance and label."""

    query: np.ndarray  # (P,) query frame indices
    scan: np.ndarray  # (P,) scan frame indices
    distance: np.ndarray  # (P,) metres
    label: np.ndarray  # (P,) soft labels

    def __len__(self) -> int:
        return len(self.query)

    @property
    def positive(self) -> np.ndarray:
        return self.distance < POSITIVE_RADIUS


@dataclass(frozen=True)
class TrainPairConfig:
    """Per query: ``positives`` scans within 3 m (with probability ``revisit_fraction`` one from a later or
    earlier pass, more than ``revisit_gap`` frames away, when there is one) and ``negatives`` per positive
    beyond 20 m; with ``negative_max_radius`` set, the negatives come from 20 m..that radius (places of the
    same drive that can look alike) where the query has any there, else from all beyond 20 m."""

    positives: int = 1
    negatives: int = 1
    revisit_fraction: float = 0.5
    revisit_gap: int = 50
    negative_max_radius: float | None = None

    def __post_init__(self) -> None:
        if self.positives < 1 or self.negatives < 0:
            raise InvalidValueError(f"positives={self.positives}, negatives={self.negatives}; expected >= 1 and >= 0")
        if not 0.0 <= self.revisit_fraction <= 1.0:
            raise InvalidValueError(f"revisit_fraction={self.revisit_fraction}; expected a share in [0, 1]")
        if self.negative_max_radius is not None and not self.negative_max_radius > NEGATIVE_RADIUS:
            raise InvalidValueError(f"negative_max_radius={self.negative_max_radius}; expected None or more than "
                                    f"{NEGATIVE_RADIUS:g} m (negatives lie beyond {NEGATIVE_RADIUS:g} m)")

    @property
    def scans_per_query(self) -> int:
        return self.positives * (1 + self.negatives)


def training_pairs(positions: np.ndarray, queries: np.ndarray, scans: np.ndarray, *, config: TrainPairConfig,
                   rng: np.random.Generator) -> PairSet:
    """``config.scans_per_query`` pairs per query, grouped by query (positives first, then negatives).

    queries, scans: frame indices that may be used. A query without a scan beyond 20 m gets
    negatives from its farthest scans instead.
    """
    q = np.asarray(queries, np.int64)
    s = np.asarray(scans, np.int64)
    out_q, out_s = [], []
    for i in q.tolist():
        d = planar_distances(positions[i : i + 1], positions[s])[0]
        pos = s[d < POSITIVE_RADIUS]
        if len(pos) == 0:
            pos = s[np.argsort(d)[:1]]
        revisit = pos[np.abs(pos - i) > config.revisit_gap]
        neg = s[d > NEGATIVE_RADIUS]
        if config.negative_max_radius is not None:
            near = s[(d > NEGATIVE_RADIUS) & (d <= config.negative_max_radius)]
            neg = near if len(near) else neg
        if len(neg) == 0:
            neg = s[np.argsort(-d)[: max(1, config.negatives)]]
        for _ in range(config.positives):
            pool = revisit if len(revisit) and rng.random() < config.revisit_fraction else pos
            out_q.append(i)
            out_s.append(int(rng.choice(pool)))
        for _ in range(config.positives * config.negatives):
            out_q.append(i)
            out_s.append(int(rng.choice(neg)))
    qa, sa = np.array(out_q, np.int64), np.array(out_s, np.int64)
    dist = np.sqrt(((positions[qa, :2] - positions[sa, :2]) ** 2).sum(axis=1)) if len(qa) else np.zeros(0)
    return PairSet(qa, sa, dist, place_label(dist))


def evaluation_pairs(positions: np.ndarray, queries: np.ndarray, *, min_frame_gap: int = 50,
                     negatives_per_positive: int = 100, rng: np.random.Generator,
                     scans: np.ndarray | None = None) -> PairSet:
    """Every (query, scan) pair closer than 3 m with a frame gap above ``min_frame_gap`` and
    ``negatives_per_positive`` random pairs per positive farther than 20 m (all of them when fewer)."""
    q = np.asarray(queries, np.int64)
    s = np.arange(len(positions)) if scans is None else np.asarray(scans, np.int64)
    d = planar_distances(positions[q], positions[s])
    gap = np.abs(q[:, None] - s[None, :]) > min_frame_gap
    pi, pj = np.nonzero((d < POSITIVE_RADIUS) & gap)
    ni, nj = np.nonzero(d > NEGATIVE_RADIUS)
    want = negatives_per_positive * len(pi)
    if want < len(ni):
        pick = np.sort(rng.choice(len(ni), size=want, replace=False))
        ni, nj = ni[pick], nj[pick]
    qi = np.concatenate([q[pi], q[ni]])
    sj = np.concatenate([s[pj], s[nj]])
    dist = np.concatenate([d[pi, pj], d[ni, nj]])
    return PairSet(qi, sj, dist, place_label(dist))
