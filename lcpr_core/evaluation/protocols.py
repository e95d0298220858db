"""Ground truth and the two protocols (online, database/query) that score a method's ranked candidates.

The rules are the package's (:mod:`lcpr_core.evaluation`): a true loop is a keyframe within
``radius`` and at least ``exclude_recent_s`` older; the database/query split starts at the first
real revisit.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputShapeError, InvalidValueError
from ..exclusion import matchable
from ..metrics import PRResult, pr_sweep, precision_recall, recall_at_n
from ..positives import within_radius
from ..revisits import revisit_pairs

#: (query_rows, database_rows, k) -> (ids, distances), both (Q, k): ranked database rows
#: (indices into ``database_rows``, -1 = none) and their distances (inf = none).
Retrieve = Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]


# ============================================================================ ground truth
@dataclass(frozen=True)
class GroundTruth:
    """Keyframe positions and the loops and split they define."""

    stamps: np.ndarray  # (N,) seconds, time order
    positions: np.ndarray  # (N, 3), NaN rows where unknown
    radius: float
    exclude_recent_s: float
    has_loop: np.ndarray  # (N,) bool: some keyframe >= exclude_recent_s older lies within radius
    num_pairs: int  # (query, match) true-loop pairs
    path_length: float  # metres along the keyframe trajectory
    split_time: float | None  # T of the database/query split; None = no real revisit
    database: np.ndarray  # (M,) keyframe rows of the database/query protocol
    queries: np.ndarray  # (Q,) keyframe rows with a database entry within radius

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.positions).all(axis=1)

    def summary(self) -> dict[str, Any]:
        return {
            "radius": self.radius, "exclude_recent_s": self.exclude_recent_s,
            "keyframes": len(self.stamps), "keyframes_with_position": int(self.valid.sum()),
            "queries_with_true_loop": int(self.has_loop.sum()), "true_loop_pairs": self.num_pairs,
            "path_length_m": self.path_length, "split_time": self.split_time,
            "split_offset_s": None if self.split_time is None or not len(self.stamps)
            else self.split_time - float(self.stamps[0]),
            "database_size": len(self.database), "query_count": len(self.queries),
        }


def ground_truth(
    stamps: np.ndarray,
    positions: np.ndarray,
    *,
    radius: float = 9.0,
    exclude_recent_s: float = 30.0,
    split_time: float | None = None,
) -> GroundTruth:
    """True loops per keyframe and the database/query split (``split_time`` overrides T)."""
    t = np.asarray(stamps, np.float64)
    p = np.asarray(positions, np.float64)
    if p.ndim != 2 or p.shape[1] not in (2, 3) or t.shape != (len(p),):
        raise InputShapeError(f"stamps of shape {t.shape} and positions of shape {p.shape}; expected (N,) and (N, 2|3)")
    if not (radius > 0):
        raise InvalidValueError(f"radius={radius!r}; expected a positive distance in metres")
    if not (exclude_recent_s >= 0):
        raise InvalidValueError(f"exclude_recent_s={exclude_recent_s!r}; expected seconds >= 0")
    if len(t) > 1 and np.any(np.diff(t) < 0):
        raise InvalidValueError("keyframe stamps are not in time order; expected non-decreasing stamps")
    if p.shape[1] == 2:
        p = np.c_[p, np.zeros(len(p))]
    valid = np.isfinite(p).all(axis=1)
    rows = np.flatnonzero(valid)
    # revisit_pairs keeps gaps strictly above min_time_gap; the next double below the
    # exclusion makes that "at least exclude_recent_s", the detector's rule.
    gap = max(float(np.nextafter(exclude_recent_s, -np.inf)), 0.0)
    pairs = np.zeros((0, 2), np.int64)
    if len(rows):
        pairs = rows[revisit_pairs(p[rows], t[rows], radius=radius, min_time_gap=gap)]
    has_loop = np.zeros(len(t), bool)
    has_loop[pairs[:, 0]] = True

    steps = np.linalg.norm(np.diff(p[rows], axis=0), axis=1) if len(rows) > 1 else np.zeros(0)
    travelled = np.full(len(t), np.nan)
    travelled[rows] = np.r_[0.0, np.cumsum(steps)]
    if split_time is None and len(pairs):
        real = pairs[travelled[pairs[:, 0]] - travelled[pairs[:, 1]] > 2.0 * radius]
        split_time = float(t[real[:, 0].min()]) if len(real) else None
    database = np.zeros(0, np.int64)
    queries = np.zeros(0, np.int64)
    if split_time is not None:
        database = np.flatnonzero(valid & matchable(t, split_time, exclude_recent_s))
        later = np.flatnonzero(valid & (t >= split_time))
        if len(database) and len(later):
            queries = later[_any_within(p[later], p[database], radius)]
    return GroundTruth(
        stamps=t, positions=p, radius=float(radius), exclude_recent_s=float(exclude_recent_s),
        has_loop=has_loop, num_pairs=len(pairs), path_length=float(steps.sum()),
        split_time=split_time, database=database, queries=queries,
    )


# ============================================================================ protocol results
@dataclass(frozen=True)
class OperatingPoint:
    """Top-1 decisions at one distance threshold (the detector's accept threshold)."""

    threshold: float
    true_positives: int
    false_positives: int
    false_negatives: int  # positive queries not detected correctly
    precision: float | None  # None when nothing was accepted
    recall: float | None  # None when no query is positive
    source: str = "configured"  # "configured" or "max F1" (the method's max-F1 threshold, chosen afterwards)


@dataclass(frozen=True)
class ProtocolResult:
    protocol: str  # "online" | "database/query"
    radius: float
    num_queries: int
    num_positives: int  # queries with a true match
    num_database: int  # online: keyframes; database/query: database entries
    recall_at: dict[int, float]  # over positive queries; empty when there are none
    pr: PRResult | None  # None: no positive query, or no query got a candidate
    operating_point: OperatingPoint | None = None
    # per query (online: every keyframe row; database/query: the query rows), for plots:
    query_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    top1_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)  # -1 = none
    top1_distance: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # inf = none
    top1_correct: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)

    @property
    def max_f1(self) -> float | None:
        return None if self.pr is None else self.pr.max_f1

    @property
    def recall_at_full_precision(self) -> float | None:
        return recall_at_full_precision(self.pr)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "protocol": self.protocol, "radius": self.radius, "num_queries": self.num_queries,
            "num_positives": self.num_positives, "num_database": self.num_database,
            "recall_at": {str(n): r for n, r in self.recall_at.items()},
            "max_f1": self.max_f1, "max_f1_threshold": None if self.pr is None else self.pr.max_f1_threshold,
            "recall_at_full_precision": self.recall_at_full_precision,
            "operating_point": None if self.operating_point is None else dataclasses.asdict(self.operating_point),
            "pr_curve": None if self.pr is None else {
                "thresholds": self.pr.thresholds, "precision": self.pr.precision,
                "recall": self.pr.recall, "f1": self.pr.f1,
            },
        }
        if self.operating_point is not None:
            accepted = np.flatnonzero(self.top1_distance <= self.operating_point.threshold)
            out["accepted_loops"] = [
                {"query": int(self.query_rows[i]), "match": int(self.top1_rows[i]),
                 "distance": float(self.top1_distance[i]), "correct": bool(self.top1_correct[i])}
                for i in accepted
            ]
        return out


def recall_at_full_precision(pr: PRResult | None) -> float | None:
    """The highest recall reached with no false positive (0 when the best match is already wrong)."""
    if pr is None:
        return None
    perfect = pr.precision >= 1.0
    return float(pr.recall[perfect].max()) if perfect.any() else 0.0


def ranked_protocol(
    *,
    protocol: str,
    ranked_ids: np.ndarray,
    ranked_distances: np.ndarray,
    query_positions: np.ndarray,
    database_positions: np.ndarray,
    has_match: np.ndarray,
    radius: float,
    n_values: Sequence[int] = (1, 5, 10),
    threshold: float | None = None,
    query_rows: np.ndarray | None = None,
    database_rows: np.ndarray | None = None,
) -> ProtocolResult:
    """Recall@N and the top-1 PR sweep from ranked candidates.

    ranked_ids (Q, K): database indices, best first, -1 = none; ranked_distances (Q, K).
    A candidate is correct within ``radius`` (NaN positions never are); a query is
    positive when ``has_match`` says so or one of its candidates is correct.
    Recall@N with N > K uses all K candidates.
    """
    ids = np.asarray(ranked_ids, np.int64)
    dist = np.asarray(ranked_distances, np.float64)
    qp = np.asarray(query_positions, np.float64)
    dp = np.asarray(database_positions, np.float64)
    if ids.ndim != 2 or dist.shape != ids.shape or qp.shape[0] != len(ids) or np.shape(has_match) != (len(ids),):
        raise InputShapeError(
            f"ranked ids {ids.shape}, distances {dist.shape}, query positions {qp.shape}, has_match "
            f"{np.shape(has_match)}; expected (Q, K), (Q, K), (Q, 2|3), (Q,)"
        )
    if ids.size and (ids.max() >= len(dp) or ids.min() < -1):
        raise InputShapeError(f"ranked ids span {ids.min()}..{ids.max()}; expected -1 or 0..{len(dp) - 1}")
    if not (radius > 0):
        raise InvalidValueError(f"radius={radius!r}; expected a positive distance in metres")
    ns = sorted({int(n) for n in n_values})
    if not ns or ns[0] < 1:
        raise InvalidValueError(f"n_values {list(n_values)} are not accepted; expected positive integers")
    dist = np.where(ids >= 0, dist, np.inf)
    if ids.shape[1] == 0:
        ids, dist = np.full((len(ids), 1), -1), np.full((len(ids), 1), np.inf)
    cand = dp[np.maximum(ids, 0)] if len(dp) else np.full((*ids.shape, qp.shape[1]), np.nan)
    with np.errstate(invalid="ignore"):
        hits = (ids >= 0) & within_radius(cand - qp[:, None, :], radius)
    positive = np.asarray(has_match, bool) | hits.any(axis=1)
    num_positives = int(positive.sum())
    recall_at: dict[int, float] = {}
    if num_positives:
        found = np.logical_or.accumulate(hits[positive], axis=1)
        recall_at = {n: float(found[:, min(n, found.shape[1]) - 1].mean()) for n in ns}
    top1_d, top1_ok = dist[:, 0], hits[:, 0]
    pr = pr_sweep(top1_d, top1_ok, num_positives=num_positives, num_queries=len(ids))
    point = None if threshold is None else operating_point(top1_d, top1_ok, num_positives, threshold)
    q_rows = np.arange(len(ids)) if query_rows is None else np.asarray(query_rows, np.int64)
    top1 = ids[:, 0]
    if database_rows is not None:  # database indices -> keyframe rows
        top1 = np.where(top1 >= 0, np.asarray(database_rows, np.int64)[np.maximum(top1, 0)], -1)
    return ProtocolResult(
        protocol=protocol, radius=float(radius), num_queries=len(ids), num_positives=num_positives,
        num_database=len(dp), recall_at=recall_at, pr=pr, operating_point=point,
        query_rows=q_rows, top1_rows=top1, top1_distance=top1_d, top1_correct=top1_ok,
    )


def operating_point(distances: np.ndarray, correct: np.ndarray, num_positives: int, threshold: float, *,
                    source: str = "configured") -> OperatingPoint:
    """Counts of top-1 decisions accepted at ``distance <= threshold``."""
    accepted = np.asarray(distances) <= threshold
    ok = np.asarray(correct, bool)
    tp, fp = int((accepted & ok).sum()), int((accepted & ~ok).sum())
    return OperatingPoint(
        threshold=float(threshold), true_positives=tp, false_positives=fp, false_negatives=num_positives - tp,
        precision=tp / (tp + fp) if tp + fp else None, recall=tp / num_positives if num_positives else None,
        source=source,
    )


def online_protocol(
    gt: GroundTruth,
    ranked_ids: np.ndarray,
    ranked_distances: np.ndarray,
    *,
    n_values: Sequence[int] = (1, 5, 10),
    threshold: float | None = None,
) -> ProtocolResult:
    """Every keyframe with a position is a query; ranked_ids are keyframe rows (-1 = none), (N, K)."""
    ids = np.asarray(ranked_ids, np.int64)
    if ids.ndim != 2 or len(ids) != len(gt.stamps):
        raise InputShapeError(f"ranked ids of shape {ids.shape}; expected ({len(gt.stamps)}, K), one row per keyframe")
    rows = np.flatnonzero(gt.valid)
    return ranked_protocol(
        protocol="online", ranked_ids=ids[rows], ranked_distances=np.asarray(ranked_distances)[rows],
        query_positions=gt.positions[rows], database_positions=gt.positions, has_match=gt.has_loop[rows],
        radius=gt.radius, n_values=n_values, threshold=threshold, query_rows=rows,
    )


def database_query_protocol(
    gt: GroundTruth,
    *,
    descriptors: np.ndarray | None = None,
    retrieve: Retrieve | None = None,
    n_values: Sequence[int] = (1, 5, 10),
) -> ProtocolResult | None:
    """The paper's protocol on ``gt``'s split; None when the drive has no real revisit.

    L2 ``descriptors`` (N, D) use :func:`lcpr_core.metrics.recall_at_n` and
    :func:`~lcpr_core.metrics.precision_recall`; otherwise ``retrieve`` ranks the database.
    """
    if (descriptors is None) == (retrieve is None):
        raise InvalidValueError("give exactly one of descriptors (L2) or retrieve (a ranked search)")
    db, q = gt.database, gt.queries
    if len(db) == 0 or len(q) == 0:
        return None
    qp, dp = gt.positions[q], gt.positions[db]
    if descriptors is not None:
        desc = np.asarray(descriptors)
        if desc.ndim != 2 or len(desc) != len(gt.stamps):
            raise InputShapeError(f"descriptors of shape {desc.shape}; expected ({len(gt.stamps)}, D)")
        rec = recall_at_n(desc[q], desc[db], qp, dp, n_values=n_values, threshold=gt.radius)
        pr = precision_recall(desc[q], desc[db], qp, dp, threshold=gt.radius)
        best, best_d = _nearest_l2(desc[q], desc[db])
        near = ((dp[best] - qp) ** 2).sum(axis=1) <= gt.radius**2
        return ProtocolResult(
            protocol="database/query", radius=gt.radius, num_queries=len(q), num_positives=rec.num_queries,
            num_database=len(db), recall_at=dict(rec.recalls), pr=pr, query_rows=q, top1_rows=db[best],
            top1_distance=best_d, top1_correct=near,
        )
    assert retrieve is not None
    k = max(int(n) for n in n_values)
    ids, dist = retrieve(q, db, k)
    return ranked_protocol(
        protocol="database/query", ranked_ids=ids, ranked_distances=dist, query_positions=qp,
        database_positions=dp, has_match=np.ones(len(q), bool), radius=gt.radius, n_values=n_values,
        query_rows=q, database_rows=db,
    )


_CHUNK = 1 << 22  # elements of a query-chunk x database matrix


def _any_within(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """(A,) bool: some row of b lies within radius of each row of a (chunked over a)."""
    out = np.zeros(len(a), bool)
    step = max(1, _CHUNK // max(len(b) * a.shape[1], 1))
    for lo in range(0, len(a), step):
        out[lo : lo + step] = within_radius(a[lo : lo + step, None, :] - b[None, :, :], radius).any(axis=1)
    return out


def _nearest_l2(q: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index (lowest on ties) and L2 distance of each query's nearest database row."""
    q64, d64 = np.asarray(q, np.float64), np.asarray(d, np.float64)
    dn = (d64 * d64).sum(axis=1)
    best = np.zeros(len(q64), np.int64)
    dist = np.zeros(len(q64))
    step = max(1, _CHUNK // max(len(d64), 1))
    for lo in range(0, len(q64), step):
        block = q64[lo : lo + step]
        d2 = np.maximum((block * block).sum(axis=1)[:, None] + dn[None, :] - 2.0 * block @ d64.T, 0.0)
        i = np.argmin(d2, axis=1)
        best[lo : lo + step] = i
        dist[lo : lo + step] = np.sqrt(d2[np.arange(len(block)), i])
    return best, dist
