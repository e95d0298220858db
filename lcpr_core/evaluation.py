"""Offline evaluation of loop-closure detection: ground truth, two protocols, the report and its plots.

Pure numpy and matplotlib; the bag-reading driver is ``lcpr_core.lcpr.evaluate`` (command line: ``lcpr_ros.evaluate``).

Ground truth. Keyframe positions come from odometry (NaN where unknown; such
keyframes are neither queries nor counted as correct matches). Keyframe ``m`` is a
true loop of query ``q`` when ``|p_q - p_m| <= radius`` and ``m`` is at least
``exclude_recent_s`` older: the time rule the detector uses to skip recent keyframes.

Online protocol (what a SLAM back end experiences): every keyframe, in time order,
is a query against all earlier ones (recent ones excluded). Its best candidate is a
true positive when it is a true loop, a false positive otherwise; a query is
positive when it has any true loop. Sweeping the top-1 distance threshold gives the
precision-recall curve, max F1 and the recall at 100 % precision; Recall@N counts
positive queries with a true loop among their N best candidates.

Database/query protocol (the paper's): the first pass of the drive is the
database, later keyframes that revisit it are the queries. The split time ``T`` is
the stamp of the first real revisit: the first keyframe with a true loop reached
after more than ``2 * radius`` metres of driving (a vehicle standing still for
``exclude_recent_s`` does not count). Database: keyframes stamped up to
``T - exclude_recent_s``; queries: keyframes from ``T`` on with a database keyframe
within ``radius`` (others are removed, as in the paper). Every query-database pair
is thus at least ``exclude_recent_s`` apart, so no query is matched by its temporal
neighbours. Descriptors compared by L2 go through :mod:`lcpr_core.metrics`; other
distances (Scan Context) through a ranked retrieval the caller provides.

Verified loops ("LCPR + verification", :func:`evaluate_verified`): with geometric
verification on, each keyframe's loop is the verified candidate with the best
registration fitness (``Result.loop``), or none. They are scored by the rule of
:mod:`lcpr_core.loop_report` (the one the demo uses): precision over the loops,
recall over the keyframes with a true loop, relative-pose error against the ground
truth; the precision-recall sweep (max F1, recall at precision 1) uses the fitness
of each keyframe's loop as its score (higher accepts first).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msg_tools.ground_truth import revisit_pairs

from .atomic import atomic_path, save_figure
from .errors import InputShapeError, InvalidValueError
from .exclusion import matchable
from .loop_report import (
    LoopScore,
    PoseGraphProof,
    PublishedLoop,
    fitness_sweep,
    loop_correct,
    loop_pose_errors,
    score_loops,
)
from .metrics import PRResult, pr_sweep, precision_recall, recall_at_n
from .positives import within_radius

__all__ = [
    "GroundTruth", "LatencyStats", "MethodResult", "MethodRun", "OperatingPoint", "ProtocolResult",
    "EvaluationReport", "database_query_protocol", "evaluate_method", "ground_truth", "latency_stats",
    "online_protocol", "plot_latency", "plot_pr_curves", "plot_trajectory", "pr_sweep", "ranked_protocol",
    "recall_at_full_precision", "summary_table", "VerifiedLoops", "evaluate_verified", "verification_table",
]

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


# ============================================================================ latency
@dataclass(frozen=True)
class LatencyStats:
    count: int
    mean_ms: float
    p50_ms: float
    p90_ms: float
    p99_ms: float
    max_ms: float


def latency_stats(timings: Sequence[Mapping[str, float]], *, warmup: int = 0) -> dict[str, LatencyStats]:
    """Per stage (and "total", the sum of a sample's stages) percentiles in milliseconds.

    The first ``warmup`` samples are left out while more than that many exist.
    """
    samples = list(timings)
    if warmup < 0:
        raise InvalidValueError(f"warmup={warmup}; expected >= 0 samples")
    if len(samples) > warmup:
        samples = samples[warmup:]
    stages: dict[str, list[float]] = {}
    for sample in samples:
        for stage, seconds in sample.items():
            stages.setdefault(stage, []).append(seconds)
        if sample:
            stages.setdefault("total", []).append(sum(sample.values()))
    out = {}
    for stage, values in stages.items():
        ms = np.asarray(values, np.float64) * 1e3
        p50, p90, p99 = np.percentile(ms, [50, 90, 99])
        out[stage] = LatencyStats(len(ms), float(ms.mean()), float(p50), float(p90), float(p99), float(ms.max()))
    return out


# ============================================================================ per method
@dataclass
class MethodRun:
    """What one method produced on the keyframes of a run (rows in keyframe order)."""

    name: str
    ranked_ids: np.ndarray  # (N, K) keyframe rows of the online candidates, best first, -1 = none
    ranked_distances: np.ndarray  # (N, K), inf = none
    threshold: float | None  # distance under which the method accepts a loop; None = its max-F1 threshold
    timings: list[dict[str, float]] = field(default_factory=list)  # per keyframe, stage -> seconds
    descriptors: np.ndarray | None = None  # (N, D) L2 descriptors for the database/query protocol
    retrieve: Retrieve | None = None  # or a ranked search over rows, for non-L2 distances
    distance: str = "L2"  # what the distances are, for the report


@dataclass
class MethodResult:
    name: str
    distance: str
    online: ProtocolResult
    database_query: ProtocolResult | None
    latency: dict[str, LatencyStats]
    timings: list[dict[str, float]] = field(default_factory=list, repr=False)
    descriptors: np.ndarray | None = field(default=None, repr=False)  # (N, D) per keyframe; not in the JSON

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "distance": self.distance, "online": self.online.to_dict(),
            "database_query": None if self.database_query is None else self.database_query.to_dict(),
            "latency_ms": {stage: dataclasses.asdict(s) for stage, s in self.latency.items()},
        }


def evaluate_method(
    run: MethodRun, gt: GroundTruth, *, n_values: Sequence[int] = (1, 5, 10), warmup: int = 0
) -> MethodResult:
    online = online_protocol(gt, run.ranked_ids, run.ranked_distances, n_values=n_values, threshold=run.threshold)
    if run.threshold is None and online.pr is not None:
        point = operating_point(online.top1_distance, online.top1_correct, online.num_positives,
                                online.pr.max_f1_threshold, source="max F1")
        online = dataclasses.replace(online, operating_point=point)
    has_split = len(gt.database) > 0 and len(gt.queries) > 0
    dbq = None
    if has_split and (run.descriptors is not None or run.retrieve is not None):
        dbq = database_query_protocol(
            gt, descriptors=run.descriptors, retrieve=None if run.descriptors is not None else run.retrieve,
            n_values=n_values,
        )
    return MethodResult(name=run.name, distance=run.distance, online=online, database_query=dbq,
                        latency=latency_stats(run.timings, warmup=warmup), timings=list(run.timings),
                        descriptors=run.descriptors)


# ============================================================================ verified loops
@dataclass(frozen=True)
class VerifiedLoops:
    """"LCPR + verification": each keyframe's verified loop, scored like a published loop.

    ``pr`` sweeps the loops' fitness (a loop is accepted when its fitness is at least
    the threshold); its ``thresholds`` are the negated fitness values (pr_sweep accepts
    at or below a threshold), :attr:`max_f1_min_fitness` gives the fitness itself.
    """

    name: str
    score: LoopScore  # lcpr_core.loop_report.score_loops of all loops
    pr: PRResult | None  # None: no loop or no positive keyframe
    loops: tuple[PublishedLoop, ...] = field(default=(), repr=False)  # keyframe rows, one loop per query at most
    fitness: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # (L,)
    correct: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)  # (L,)
    pose_errors: tuple[tuple[float, float] | None, ...] = field(default=(), repr=False)  # (m, deg) or None
    pose_graph: PoseGraphProof | None = None  # the loops in a pose graph over drifted odometry
    pose_graph_note: str = ""  # why there is no pose graph
    base_T_lidar: np.ndarray | None = None  # the extrinsic the ground truth LiDAR poses used
    base_T_lidar_source: str = ""  # where it came from

    @property
    def max_f1(self) -> float | None:
        return None if self.pr is None else self.pr.max_f1

    @property
    def max_f1_min_fitness(self) -> float | None:
        return None if self.pr is None else -self.pr.max_f1_threshold

    @property
    def recall_at_full_precision(self) -> float | None:
        return recall_at_full_precision(self.pr)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, **self.score.to_dict(),
            "max_f1": self.max_f1, "max_f1_min_fitness": self.max_f1_min_fitness,
            "recall_at_full_precision": self.recall_at_full_precision,
            "pr_curve": None if self.pr is None else {
                "min_fitness": -self.pr.thresholds, "precision": self.pr.precision,
                "recall": self.pr.recall, "f1": self.pr.f1,
            },
            "accepted_loops": [
                {"query": loop.query, "match": loop.match, "fitness": float(f), "correct": bool(ok),
                 "trans_err_m": None if err is None else err[0], "yaw_err_deg": None if err is None else err[1]}
                for loop, f, ok, err in zip(self.loops, self.fitness, self.correct, self.pose_errors, strict=True)
            ],
            "pose_graph": None if self.pose_graph is None else self.pose_graph.to_dict(),
            "pose_graph_note": self.pose_graph_note,
            "base_T_lidar": self.base_T_lidar, "base_T_lidar_source": self.base_T_lidar_source,
        }


def evaluate_verified(
    gt: GroundTruth,
    loops: Sequence[PublishedLoop],
    fitness: Sequence[float],
    *,
    world_T_lidar: np.ndarray | None = None,
    name: str = "LCPR + verification",
) -> VerifiedLoops:
    """Score verified loops (keyframe rows of ``gt``, at most one per query) against ``gt``.

    ``world_T_lidar`` (N, 4, 4) true LiDAR poses (NaN rows: unknown) give the pose errors.
    The sweep counts as positive every keyframe with a true loop and every query of a
    correct loop, as the online protocol does.
    """
    loops = tuple(loops)
    fit = np.asarray(fitness, np.float64).reshape(-1)
    if len(fit) != len(loops):
        raise InputShapeError(f"{len(fit)} fitness values for {len(loops)} loops; expected one per loop")
    queries = [loop.query for loop in loops]
    if len(set(queries)) != len(queries):
        raise InvalidValueError("several loops share a query; expected at most one verified loop per keyframe")
    score = score_loops(loops, positions=gt.positions, world_T_lidar=world_T_lidar, has_revisit=gt.has_loop,
                        radius=gt.radius)
    correct = loop_correct(loops, gt.positions, gt.radius)
    positive = gt.has_loop.copy()
    positive[[q for q, ok in zip(queries, correct, strict=True) if ok]] = True
    pr = fitness_sweep(fit, correct, num_positives=int(positive.sum()), num_queries=len(gt.stamps))
    return VerifiedLoops(name=name, score=score, pr=pr, loops=loops, fitness=fit, correct=correct,
                         pose_errors=tuple(loop_pose_errors(loops, world_T_lidar)))


def verification_table(report: EvaluationReport) -> str:
    """The verified loops beside the retrieval LCPR's online numbers, and the pose-graph line."""
    v = report.verified
    if v is None:
        return ""
    retrieval = next((m for m in report.methods if m.name == "LCPR"), report.methods[0] if report.methods else None)
    left = "LCPR (retrieval)" if retrieval is None else f"{retrieval.name} (retrieval)"
    width = max(22, len(v.name) + 2, len(left) + 2)
    s = v.score
    out = [f"{'':<34}{left:>{width}}{v.name:>{width}}"]

    def row(label: str, a: str, b: str) -> None:
        out.append(f"{label:<34}{a:>{width}}{b:>{width}}")

    point = None if retrieval is None else retrieval.online.operating_point
    row("online     loops (correct/wrong)", "-" if point is None else
        f"{point.true_positives + point.false_positives} ({_op(point)})",
        f"{s.loops} ({s.correct}/{s.loops - s.correct})")
    row("online     precision / recall",
        "-" if point is None else f"{_fmt(point.precision, '.2f')} / {_fmt(point.recall, '.2f')}",
        f"{_fmt(s.precision, '.2f')} / {_fmt(s.recall, '.2f')}")
    row("online     max F1 (R at P=1)",
        "-" if retrieval is None else
        f"{_fmt(retrieval.online.max_f1)} ({_fmt(retrieval.online.recall_at_full_precision, '.2f')})",
        f"{_fmt(v.max_f1)} ({_fmt(v.recall_at_full_precision, '.2f')})")
    row("           swept over", "descriptor distance", "fitness")
    row("loop pose error median m / deg", "-", _err(s.trans_err_median, s.yaw_err_median))
    row("loop pose error p95    m / deg", "-", _err(s.trans_err_p95, s.yaw_err_p95))
    verify = None if retrieval is None else retrieval.latency.get("verify")
    row("latency    p50 / p90 ms (verify)", "-", _lat(verify))
    g = v.pose_graph
    if g is not None:
        out.append(f"pose graph (seeded odometry drift, {g.loops_used} verified loops as between-factors, {g.robust} "
                   f"kernel): ATE {g.ate_drifted:.2f} m drifted -> {g.ate_corrected:.2f} m optimised ({g.ratio:.0%})")
    elif v.pose_graph_note:
        out.append(f"pose graph: {v.pose_graph_note}")
    if v.base_T_lidar_source:
        out.append(f"loop poses vs ground truth: base_T_lidar from {v.base_T_lidar_source}")
    return "\n".join(out)


def _err(metres: float | None, degrees: float | None) -> str:
    return "-" if metres is None or degrees is None else f"{metres:.3f} / {degrees:.2f}"


# ============================================================================ the report
@dataclass
class EvaluationReport:
    source: str  # what was evaluated (a bag path)
    settings: dict[str, Any]
    counts: dict[str, Any]  # frames, keyframes, reasons, degraded, reader statistics
    ground_truth: GroundTruth
    methods: list[MethodResult]
    wall_time_s: float = 0.0
    setup_time_s: float = 0.0  # of wall_time_s: building the detector (loading, auto's measurement, graph capture)
    verified: VerifiedLoops | None = None  # LCPR + verification; None when verification was off

    def to_dict(self) -> dict[str, Any]:
        return _jsonable({
            "source": self.source, "settings": self.settings, "counts": self.counts,
            "ground_truth": self.ground_truth.summary(), "wall_time_s": self.wall_time_s,
            "methods": [m.to_dict() for m in self.methods],
            "verified": None if self.verified is None else self.verified.to_dict(),
        })

    def write_json(self, path: str | os.PathLike[str]) -> None:
        """Write the report (atomically: readers see the old file or the whole new one)."""
        text = json.dumps(self.to_dict(), indent=1, allow_nan=False)
        with atomic_path(path) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(dataclasses.asdict(value))
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def _fmt(value: float | None, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def summary_table(report: EvaluationReport, *, n_values: Sequence[int] = (1, 5, 10)) -> str:
    """A few lines for the console: both protocols and latency, one column per method."""
    gt = report.ground_truth.summary()
    c = report.counts
    lines = [
        f"{c.get('frames', '?')} frames, {c.get('keyframes', '?')} keyframes ({c.get('degraded_keyframes', 0)} with a "
        f"missing camera), {c.get('dropped_clouds', 0)} clouds dropped by the reader; "
        f"{gt['queries_with_true_loop']} keyframes with a true loop (<= {gt['radius']:g} m, >= "
        f"{gt['exclude_recent_s']:g} s older); path {gt['path_length_m']:.0f} m",
    ]
    if gt["split_time"] is None:
        lines.append("database/query: no revisit after more than 2 x radius of driving; protocol not applicable")
    else:
        lines.append(f"database/query: {gt['database_size']} database keyframes (first pass), "
                     f"{gt['query_count']} queries from {gt['split_offset_s']:.1f} s on")
    ns = "/".join(f"@{n}" for n in n_values)
    width = max(14, *(len(m.name) + 2 for m in report.methods))
    head = f"{'':<34}" + "".join(f"{m.name:>{width + 8}}" for m in report.methods)
    rows = [head]

    def row(label: str, cell: Callable[[MethodResult], str]) -> None:
        rows.append(f"{label:<34}" + "".join(f"{cell(m):>{width + 8}}" for m in report.methods))

    def recalls(p: ProtocolResult | None) -> str:
        if p is None or not p.recall_at:
            return "-"
        return " / ".join(_fmt(p.recall_at.get(n), ".2f") for n in n_values)

    row(f"online     Recall{ns}", lambda m: recalls(m.online))
    row("online     max F1 (R at P=1)",
        lambda m: f"{_fmt(m.online.max_f1)} ({_fmt(m.online.recall_at_full_precision, '.2f')})")
    row("online     TP/FP at threshold", lambda m: _op(m.online.operating_point))
    row(f"db/query   Recall{ns}", lambda m: recalls(m.database_query))
    row("db/query   max F1", lambda m: _fmt(None if m.database_query is None else m.database_query.max_f1))
    row("latency    p50 / p90 ms (total)", lambda m: _lat(m.latency.get("total")))
    lines.append("\n".join(rows))
    if report.verified is not None:
        lines.append(verification_table(report))
    return "\n".join(lines)


def throughput_line(report: EvaluationReport) -> str:
    """Keyframes per second of the whole run and where a keyframe's time went (the first method's stages)."""
    keyframes = int(report.counts.get("keyframes", 0))
    if not keyframes or report.wall_time_s <= 0:
        return "throughput: no keyframe"
    stages = {k: v for k, v in report.methods[0].latency.items() if k != "total"} if report.methods else {}
    staged = sum(v.mean_ms for v in stages.values()) * keyframes / 1e3
    run = report.wall_time_s - report.setup_time_s
    parts = ", ".join(f"{k} {v.mean_ms:.2f}" for k, v in stages.items())
    return (f"throughput: {keyframes} keyframes in {run:.1f} s = {keyframes / run:.1f} keyframes/s (after "
            f"{report.setup_time_s:.1f} s of setup); per keyframe (mean ms) {parts}; the other {run - staged:.1f} s: "
            "reading the bag, frames that were not keyframes, the evaluation")


def _op(point: OperatingPoint | None) -> str:
    if point is None:
        return "-"
    where = "max F1 " if point.source == "max F1" else ""
    return f"{point.true_positives}/{point.false_positives} @ {where}{point.threshold:.3g}"


def _lat(stats: LatencyStats | None) -> str:
    return "-" if stats is None else f"{stats.p50_ms:.1f} / {stats.p90_ms:.1f}"


# ============================================================================ plots
def _figure(size: tuple[float, float]) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)  # Agg without touching pyplot's global backend
    return fig


def plot_pr_curves(methods: Sequence[MethodResult], path: str | os.PathLike[str]) -> None:
    """Top-1 PR curves of every method, online protocol left, database/query right."""
    fig = _figure((10, 4.5))
    for col, (attr, title) in enumerate((("online", "online loop closure"), ("database_query", "database / query"))):
        ax = fig.add_subplot(1, 2, col + 1)
        for k, m in enumerate(methods):
            p: ProtocolResult | None = getattr(m, attr)
            color = f"C{k}"
            if p is None or p.pr is None:
                ax.plot([], [], color=color, label=f"{m.name}: n/a")
                continue
            ax.plot(p.pr.recall, p.pr.precision, color=color, lw=1.5, drawstyle="steps-post",
                    label=f"{m.name}: max F1 {p.pr.max_f1:.3f}")
            best = int(np.argmax(p.pr.f1))
            ax.plot(p.pr.recall[best], p.pr.precision[best], "o", color=color)
        ax.set(xlabel="recall", ylabel="precision", title=title, xlim=(0, 1.02), ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(loc="lower left", fontsize=8)
    save_figure(fig, path)


def plot_latency(methods: Sequence[MethodResult], path: str | os.PathLike[str], *, warmup: int = 0) -> None:
    """Histograms of per-keyframe stage times (ms, log axis), one panel per method."""
    fig = _figure((5 * max(1, len(methods)), 4))
    for k, m in enumerate(methods):
        ax = fig.add_subplot(1, max(1, len(methods)), k + 1)
        samples = m.timings[warmup:] if len(m.timings) > warmup else m.timings
        stages: dict[str, list[float]] = {}
        for sample in samples:
            for stage, seconds in sample.items():
                stages.setdefault(stage, []).append(seconds * 1e3)
            if sample:
                stages.setdefault("total", []).append(sum(sample.values()) * 1e3)
        values = [v for vs in stages.values() for v in vs if v > 0]
        if values:
            bins = np.geomspace(max(min(values), 1e-4), max(max(values), 1e-3) * 1.01, 40)
            for stage, vs in stages.items():
                style = dict(color="k", ls="--") if stage == "total" else {}
                ax.hist(np.maximum(vs, bins[0]), bins=bins, histtype="step", lw=1.5, label=stage, **style)
            ax.set_xscale("log")
            ax.legend(fontsize=8)
        total = m.latency.get("total")
        extra = "" if total is None else f" (total p50 {total.p50_ms:.1f} ms, p90 {total.p90_ms:.1f} ms)"
        ax.set(xlabel="ms per keyframe", ylabel="keyframes", title=f"{m.name}{extra}")
        ax.title.set_fontsize(9)
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def plot_trajectory(gt: GroundTruth, methods: Sequence[MethodResult], path: str | os.PathLike[str]) -> None:
    """The keyframe trajectory (x, y), keyframes with a true loop (orange), and each method's
    accepted online loops at its threshold: a dot on the query and a segment to the match, green
    when correct, red when not (an orange ring around a dot: that query had a true loop)."""
    from matplotlib.collections import LineCollection

    fig = _figure((5.5 * max(1, len(methods)), 5.5))
    xy = gt.positions[:, :2]
    for k, m in enumerate(methods):
        ax = fig.add_subplot(1, max(1, len(methods)), k + 1)
        ax.plot(xy[:, 0], xy[:, 1], "-", color="0.7", lw=1, zorder=1)
        if len(xy) and np.isfinite(xy).any():
            first = np.flatnonzero(np.isfinite(xy).all(axis=1))[0]
            ax.plot(*xy[first], "k^", ms=7, label="start", zorder=4)
        loops = np.flatnonzero(gt.has_loop)
        ax.scatter(xy[loops, 0], xy[loops, 1], s=60, color="tab:orange", label="true loop", zorder=2)
        p = m.online
        point = p.operating_point
        title = m.name
        if point is not None:
            accepted = np.flatnonzero(p.top1_distance <= point.threshold)
            for ok, color, label in ((True, "tab:green", "TP"), (False, "tab:red", "FP")):
                sel = accepted[p.top1_correct[accepted] == ok]
                if len(sel):
                    segs = np.stack([xy[p.query_rows[sel]], xy[p.top1_rows[sel]]], axis=1)
                    ax.add_collection(LineCollection(list(segs), colors=color, lw=1.2, zorder=3))
                ax.scatter(xy[p.query_rows[sel], 0], xy[p.query_rows[sel], 1], s=16, color=color,
                           label=f"{label} ({len(sel)})", zorder=3)
            where = " (its max-F1 threshold)" if point.source == "max F1" else ""
            title += f": loops accepted at distance <= {point.threshold:.3g}{where}"
        ax.set(xlabel="x (m)", ylabel="y (m)", title=title)
        ax.title.set_fontsize(9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    save_figure(fig, path)
