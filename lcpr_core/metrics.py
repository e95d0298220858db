"""Place-recognition metrics over a database/query split (pure numpy).

A database entry is a *true match* of a query when their positions are within
``threshold`` metres (Euclidean over all given coordinates, 2-D or 3-D).
Retrieval ranks database entries by L2 descriptor distance; ties go to the
lower database index. Queries without any true match are skipped by
recall@N and counted as negatives by the precision-recall sweep. When no query
has a true match the metrics are undefined and a ValueError is raised.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .atomic import save_figure
from .errors import InputShapeError, InvalidValueError

__all__ = ["RecallResult", "PRResult", "recall_at_n", "precision_recall", "plot_pr_curve"]

_CHUNK_ELEMENTS = 1 << 22  # bound on query-chunk x database matrices (~32 MB float64 each)


@dataclass(frozen=True)
class RecallResult:
    """recalls[n]: fraction of evaluated queries with a true match among their top n."""

    recalls: dict[int, float]
    num_queries: int  # queries evaluated (those with at least one true match)
    num_skipped: int  # queries without a true match in the database


@dataclass(frozen=True)
class PRResult:
    """Top-1 precision/recall swept over descriptor-distance thresholds (ascending).

    At threshold t a query is a predicted loop when its top-1 distance <= t;
    TP: predicted and the top-1 is a true match; FP: predicted and not;
    precision = TP / (TP + FP); recall = TP / num_positives.
    """

    thresholds: np.ndarray  # (T,) distinct top-1 distances, ascending
    precision: np.ndarray  # (T,)
    recall: np.ndarray  # (T,)
    f1: np.ndarray  # (T,)
    max_f1: float
    max_f1_threshold: float
    num_queries: int  # all queries
    num_positives: int  # queries with at least one true match


def recall_at_n(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    query_pos: np.ndarray,
    db_pos: np.ndarray,
    *,
    n_values: Sequence[int] = (1, 5, 10, 20),
    threshold: float = 9.0,
) -> RecallResult:
    """Recall@N of descriptor retrieval; queries without a true match are skipped."""
    qd, dd, qp, dp = _check_inputs(query_desc, db_desc, query_pos, db_pos, threshold)
    ns = sorted({int(n) for n in n_values})
    if not ns or ns[0] < 1:
        raise InvalidValueError(f"n_values {list(n_values)} are not accepted; expected positive integers")
    top = min(ns[-1], len(dd))
    hits = np.zeros((len(qd), top), dtype=bool)  # hits[i, r]: rank-r retrieval is a true match
    has_match = np.zeros(len(qd), dtype=bool)
    for lo, hi in _chunks(len(qd), len(dd)):
        order = _ranked(_sq_dist(qd[lo:hi], dd), top)  # (q, top)
        near = _sq_dist(qp[lo:hi], dp) <= threshold**2  # (q, M)
        has_match[lo:hi] = near.any(axis=1)
        hits[lo:hi] = np.take_along_axis(near, order, axis=1)
    evaluated = int(has_match.sum())
    if evaluated == 0:
        raise InvalidValueError(f"no query has a database entry within {threshold} m; recall@N is undefined")
    found = np.logical_or.accumulate(hits[has_match], axis=1)  # (E, top): true match within first r+1
    recalls = {n: float(found[:, min(n, top) - 1].mean()) for n in ns}
    return RecallResult(recalls=recalls, num_queries=evaluated, num_skipped=len(qd) - evaluated)


def precision_recall(
    query_desc: np.ndarray,
    db_desc: np.ndarray,
    query_pos: np.ndarray,
    db_pos: np.ndarray,
    *,
    threshold: float = 9.0,
) -> PRResult:
    """Precision/recall of each query's top-1 retrieval, swept over distance thresholds."""
    qd, dd, qp, dp = _check_inputs(query_desc, db_desc, query_pos, db_pos, threshold)
    top_dist = np.empty(len(qd))
    correct = np.zeros(len(qd), dtype=bool)
    has_match = np.zeros(len(qd), dtype=bool)
    for lo, hi in _chunks(len(qd), len(dd)):
        d2 = _sq_dist(qd[lo:hi], dd)
        best = _ranked(d2, 1)[:, 0]  # (q,)
        top_dist[lo:hi] = np.sqrt(np.maximum(d2[np.arange(hi - lo), best], 0.0))
        near = _sq_dist(qp[lo:hi], dp) <= threshold**2
        has_match[lo:hi] = near.any(axis=1)
        correct[lo:hi] = near[np.arange(hi - lo), best]
    positives = int(has_match.sum())
    if positives == 0:
        raise InvalidValueError(f"no query has a database entry within {threshold} m; recall is undefined")

    result = pr_sweep(top_dist, correct, num_positives=positives, num_queries=len(qd))
    assert result is not None  # positives > 0 and every query has a (finite) top-1 distance
    return result


def pr_sweep(distances: np.ndarray, correct: np.ndarray, *, num_positives: int, num_queries: int) -> PRResult | None:
    """Top-1 precision/recall over every distinct distance threshold.

    distances: (Q,) top-1 descriptor distances, inf where a query got no candidate;
    correct: (Q,) whether that top-1 is a true match; recall is TP / ``num_positives``.
    None when no query is positive or none got a candidate.
    """
    d = np.asarray(distances, np.float64)
    ok = np.asarray(correct, bool)
    if d.shape != ok.shape or d.ndim != 1:
        raise InvalidValueError(f"distances {d.shape} and correct {ok.shape}; expected two (Q,) arrays")
    predicted = np.isfinite(d)
    if num_positives <= 0 or not predicted.any():
        return None
    order = np.argsort(d[predicted], kind="stable")
    dist, ok = d[predicted][order], ok[predicted][order]
    tp, fp = np.cumsum(ok), np.cumsum(~ok)
    last = np.r_[np.flatnonzero(np.diff(dist) > 0), len(dist) - 1]  # last query at each distinct distance
    tp, fp, thresholds = tp[last], fp[last], dist[last]
    precision = tp / (tp + fp)
    recall = tp / num_positives
    denom = precision + recall
    f1 = np.divide(2 * precision * recall, denom, out=np.zeros_like(denom), where=denom > 0)
    best = int(np.argmax(f1))
    return PRResult(thresholds=thresholds, precision=precision, recall=recall, f1=f1, max_f1=float(f1[best]),
                    max_f1_threshold=float(thresholds[best]), num_queries=num_queries, num_positives=num_positives)


def plot_pr_curve(result: PRResult, path: str | os.PathLike[str], *, title: str = "Precision-recall (top-1)") -> None:
    """Write the PR curve as a PNG (atomically), marking the max-F1 point."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 4.5), dpi=100)
    FigureCanvasAgg(fig)  # Agg without touching pyplot's global backend
    ax = fig.add_subplot()
    ax.plot(result.recall, result.precision, lw=1.5, label="top-1")
    best = int(np.argmax(result.f1))
    ax.plot(result.recall[best], result.precision[best], "o", color="tab:red",
            label=f"max F1 {result.max_f1:.3f} @ d<={result.max_f1_threshold:.3g}")
    ax.set(xlabel="recall", ylabel="precision", title=title, xlim=(0, 1.02), ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    save_figure(fig, path)


# ---------------------------------------------------------------------- helpers
def _check_inputs(
    query_desc: np.ndarray, db_desc: np.ndarray, query_pos: np.ndarray, db_pos: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    qd, dd = np.asarray(query_desc, np.float64), np.asarray(db_desc, np.float64)
    qp, dp = np.asarray(query_pos, np.float64), np.asarray(db_pos, np.float64)
    if qd.ndim != 2 or dd.ndim != 2 or qd.shape[1] != dd.shape[1]:
        raise InputShapeError(f"descriptors of shapes query {qd.shape}, database {dd.shape}; "
                              "expected (Q, D) and (M, D)")
    if qp.ndim != 2 or dp.ndim != 2 or qp.shape[1] != dp.shape[1] or qp.shape[1] not in (2, 3):
        raise InputShapeError(f"positions of shapes query {qp.shape}, database {dp.shape}; "
                              "expected (Q, 2|3) and (M, 2|3)")
    if len(qp) != len(qd) or len(dp) != len(dd):
        raise InputShapeError(
            f"{len(qd)} query / {len(dd)} database descriptors but {len(qp)} / {len(dp)} positions; counts must agree"
        )
    if len(qd) == 0 or len(dd) == 0:
        raise InputShapeError(f"{len(qd)} queries and {len(dd)} database entries; both must be non-empty")
    if not (threshold > 0):
        raise InvalidValueError(f"threshold={threshold!r} is not accepted; expected a positive distance in metres")
    return qd, dd, qp, dp


def _chunks(q: int, m: int) -> list[tuple[int, int]]:
    step = max(1, _CHUNK_ELEMENTS // max(m, 1))
    return [(lo, min(lo + step, q)) for lo in range(0, q, step)]


def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) squared Euclidean distances (exact difference form, no cancellation)."""
    if a.shape[1] <= 3:
        return ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2)
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.maximum(d2, 0.0)


def _ranked(d2: np.ndarray, top: int) -> np.ndarray:
    """(A, top) column indices of the smallest entries per row, ascending; ties -> lower index."""
    if top < d2.shape[1]:
        part = np.argpartition(d2, top - 1, axis=1)[:, :top]
        # argpartition may cut inside a tie; widen to every column tied with the cut value
        cut = np.take_along_axis(d2, part, axis=1).max(axis=1, keepdims=True)
        if int((d2 <= cut).sum(axis=1).max()) == top:
            vals = np.take_along_axis(d2, part, axis=1)
            idx = np.lexsort((part, vals), axis=1)
            return np.take_along_axis(part, idx, axis=1)
    return np.argsort(d2, axis=1, kind="stable")[:, :top]
