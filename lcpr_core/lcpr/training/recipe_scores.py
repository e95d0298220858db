"""Online figures of keyframe descriptors, computed without running the detector again.

The whitening and turn-averaging recipes score many variants of the same keyframes' descriptors:
each variant is ranked by the detector's own rule (nearest older keyframes outside the exclusion
window) and scored by the online protocol, and the recipes check that the unchanged descriptors
give the detector's reported figures. :func:`gate_counts` says what a verification gate
(``match.max_distance``) lets through.
"""
from __future__ import annotations

import numpy as np

from ...evaluation import GroundTruth, online_protocol
from ...exclusion import matchable_prefix

#: Candidates ranked per keyframe (the detector's top k).
TOP_K = 10
#: Verification gates (``match.max_distance``) reported by :func:`gate_counts`; the node's default is 1.0.
GATES = (1.0, 1.1, 1.2)


def online_ranking(descriptors: np.ndarray, stamps: np.ndarray, *, exclude_recent_s: float,
                   k: int = TOP_K) -> tuple[np.ndarray, np.ndarray]:
    """(N, k) keyframe rows and L2 distances of each keyframe's nearest older keyframes (the detector's rule)."""
    n = len(descriptors)
    ids, dist = np.full((n, k), -1, np.int64), np.full((n, k), np.inf)
    for i in range(n):
        older = matchable_prefix(stamps, float(stamps[i]), exclude_recent_s)
        if older:
            d = np.linalg.norm(descriptors[:older] - descriptors[i], axis=1)
            top = np.argsort(d, kind="stable")[:k]
            ids[i, :len(top)], dist[i, :len(top)] = top, d[top]
    return ids, dist


def score(descriptors: np.ndarray, gt: GroundTruth) -> dict[str, float]:
    """Online Recall@1 and max F1 of keyframe descriptors (the detector's online protocol)."""
    ids, dist = online_ranking(descriptors, gt.stamps, exclude_recent_s=gt.exclude_recent_s)
    result = online_protocol(gt, ids, dist)
    pr = result.pr
    return {"recall@1": result.recall_at.get(1, 0.0), "max_f1": 0.0 if pr is None else pr.max_f1}


def gate_counts(descriptors: np.ndarray, gt: GroundTruth, gates: tuple[float, ...] = GATES) -> dict[str, dict]:
    """Per verification gate (``match.max_distance``): the revisiting keyframes whose correct top-10 candidate
    lies under it (what verification can still close) and the keyframes without a revisit whose nearest
    candidate does (verification work that finds nothing)."""
    ids, dist = online_ranking(descriptors, gt.stamps, exclude_recent_s=gt.exclude_recent_s)
    p = gt.positions
    correct = (ids >= 0) & (np.linalg.norm(p[np.maximum(ids, 0)] - p[:, None], axis=2) <= gt.radius)
    best = np.where(correct, dist, np.inf).min(axis=1)
    reachable, lonely = correct.any(axis=1), ~gt.has_loop & (ids[:, 0] >= 0)
    return {f"{g:g}": {"correct_under": int((best[reachable] <= g).sum()), "correct_in_top10": int(reachable.sum()),
                       "no_revisit_under": int((dist[lonely, 0] <= g).sum()), "no_revisit": int(lonely.sum())}
            for g in gates}
