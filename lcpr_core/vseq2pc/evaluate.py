"""Evaluating VSeq2PC on a held-out drive as the paper does (``vseq2pc_eval``).

* Place recognition (pairs): every (query sequence, scan) pair closer than 3 m with a
  frame gap above 50 is a positive; 100 random pairs farther than 20 m per positive are
  the negatives. Score: the max-slice logit. Max F1 over all thresholds, and the PR curve.
* Loop closure (retrieval): a query whose frame has an earlier scan within 5 m and more
  than 50 frames back is a loop query; it searches every scan more than 50 frames back
  (the exact batched head of :class:`ScanDatabase`); Recall@N counts loop queries with a
  scan within 5 m among the N best.

Methods: the trained weights (the bundled set without weight files), the seeded untrained
initialisation (``--untrained``), with ``--single-frame`` each network fed the query frame four times instead of a
sequence, with ``--sequence-lengths L ...`` the first L frames of each sequence (the last
repeated), and with ``--feature-match`` a reference without a network (the query frame's
camera feature against each scan's 8 windows, mean absolute difference). Writes
``eval.json`` and ``pr.png``; prints a table.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..atomic import save_figure
from ..errors import InvalidValueError
from ..evaluation import pr_sweep, ranked_protocol
from ..metrics import PRResult
from .dataset import FeatureCache
from .net import Vseq2pcNet, slice_tensor
from .pairs import evaluation_pairs, planar_distances
from .preprocess import CAMERA_SECTORS
from .retrieval import ScanDatabase, SearchConfig, head_logits

__all__ = ["EvalConfig", "MethodEval", "evaluate", "evaluate_feature_match", "plot_pr", "table"]


@dataclass(frozen=True)
class EvalConfig:
    min_frame_gap: int = 50
    negatives_per_positive: int = 100
    loop_radius: float = 5.0
    n_values: tuple[int, ...] = (1, 5, 10)
    seed: int = 0
    single_frame: bool = False  # feed the query frame 4 times (no sequence); the same as sequence_length=1
    sequence_length: int = 4  # sequence frames used (query, +5 m, +10 m, +15 m); the last one repeats to fill 4

    def __post_init__(self) -> None:
        if self.min_frame_gap < 0 or self.negatives_per_positive < 1 or not self.loop_radius > 0:
            raise InvalidValueError(f"min_frame_gap={self.min_frame_gap} (>= 0), negatives_per_positive="
                                    f"{self.negatives_per_positive} (>= 1), loop_radius={self.loop_radius} (> 0)")
        if not 1 <= self.sequence_length <= 4:
            raise InvalidValueError(f"sequence_length={self.sequence_length}; expected 1 to 4 frames")
        if not self.n_values or min(self.n_values) < 1:
            raise InvalidValueError(f"n_values={self.n_values}; expected positive integers")


@dataclass
class MethodEval:
    name: str
    num_positive_pairs: int
    num_negative_pairs: int
    pairs_pr: PRResult | None
    num_loop_queries: int
    recall_at: dict[int, float]
    seconds: float
    pair_scores: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    @property
    def max_f1(self) -> float | None:
        return None if self.pairs_pr is None else self.pairs_pr.max_f1

    def to_dict(self) -> dict[str, Any]:
        pr = self.pairs_pr
        return {
            "name": self.name, "positive_pairs": self.num_positive_pairs, "negative_pairs": self.num_negative_pairs,
            "max_f1": self.max_f1,
            "max_f1_probability": None if pr is None else float(1.0 / (1.0 + np.exp(pr.max_f1_threshold))),
            "loop_queries": self.num_loop_queries, "recall_at": {str(n): r for n, r in self.recall_at.items()},
            "seconds": self.seconds,
            "pr_curve": None if pr is None else {"precision": pr.precision.tolist(), "recall": pr.recall.tolist()},
        }


#: (query frames (P,), scan frames (P,)) -> (P,) scores, higher = more likely the same place
PairScorer = Callable[[np.ndarray, np.ndarray], np.ndarray]
#: (loop query frames (L,), k) -> (L, k) scan frames best first (-1 = none) and their scores
Ranker = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray]]


def evaluate(net: Vseq2pcNet, cache: FeatureCache, *, name: str, config: EvalConfig = EvalConfig()) -> MethodEval:
    """Both protocols of one network on one drive (loop retrieval through :class:`ScanDatabase`)."""
    start = time.perf_counter()
    queries = _queries(cache)
    members = cache.sequences()[queries]
    length = 1 if config.single_frame else config.sequence_length
    d_seq = net.query_descriptors(cache.camera[members[:, [min(i, length - 1) for i in range(4)]]])
    slices = net.slice_descriptors(cache.lidar)  # (N, 8, 288)
    row_of = np.full(len(cache), -1, np.int64)
    row_of[queries] = np.arange(len(queries))
    db = ScanDatabase(weights_id=net.weights_id)
    db.add(slices, stamps=cache.stamps, poses=cache.poses)

    def pair_scores(q: np.ndarray, s: np.ndarray) -> np.ndarray:
        return chunked_pair_logits(net, d_seq, row_of[q], slices, s)

    def ranked(q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        search = SearchConfig(k=k, exclude_recent_s=None, exclude_recent_rows=config.min_frame_gap)
        found = db.search(d_seq[row_of[q]], net.descriptor, config=search, rows=q)
        return _table([[(m.row, m.logit) for m in matches] for matches in found], k)

    return _protocols(cache, queries, name=name, config=config, pair_scores=pair_scores, ranked=ranked, start=start)


def evaluate_feature_match(cache: FeatureCache, *, config: EvalConfig = EvalConfig()) -> MethodEval:
    """A reference without a network: score = minus the mean |F_img - window| of the best of the 8 slice
    windows (the query frame's camera feature against the scan's structure feature)."""
    start = time.perf_counter()
    queries = _queries(cache)
    windows = slice_tensor(torch.from_numpy(cache.lidar))[..., CAMERA_SECTORS].numpy()  # (N, 8, 12, 90)
    camera = cache.camera

    def scores_against(q: int, scans: np.ndarray) -> np.ndarray:
        return -np.abs(windows[scans] - camera[q][None, None]).mean(axis=(2, 3)).min(axis=1)

    def pair_scores(q: np.ndarray, s: np.ndarray) -> np.ndarray:
        out = np.empty(len(q), np.float32)
        for lo in range(0, len(q), 4096):
            qq, ss = q[lo : lo + 4096], s[lo : lo + 4096]
            out[lo : lo + 4096] = -np.abs(windows[ss] - camera[qq][:, None]).mean(axis=(2, 3)).min(axis=1)
        return out

    def ranked(q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        rows = []
        for i in q.tolist():
            allowed = np.arange(max(0, i - config.min_frame_gap))
            sc = scores_against(i, allowed)
            order = np.argsort(-sc, kind="stable")[:k]
            rows.append([(int(allowed[j]), float(sc[j])) for j in order])
        return _table(rows, k)

    return _protocols(cache, queries, name="feature match (no network)", config=config, pair_scores=pair_scores,
                      ranked=ranked, start=start)


def _queries(cache: FeatureCache) -> np.ndarray:
    queries = np.flatnonzero(cache.sequences()[:, 0] >= 0)
    if len(queries) == 0:
        raise InvalidValueError(f"{cache.source or 'the cache'} has no complete query sequence")
    return queries


def _table(rows: list[list[tuple[int, float]]], k: int) -> tuple[np.ndarray, np.ndarray]:
    ids = np.full((len(rows), k), -1, np.int64)
    scores = np.full((len(rows), k), -np.inf)
    for i, row in enumerate(rows):
        for rank, (scan, score) in enumerate(row):
            ids[i, rank], scores[i, rank] = scan, score
    return ids, scores


def _protocols(cache: FeatureCache, queries: np.ndarray, *, name: str, config: EvalConfig, pair_scores: PairScorer,
               ranked: Ranker, start: float) -> MethodEval:
    pos = cache.positions
    pairs = evaluation_pairs(pos, queries, min_frame_gap=config.min_frame_gap,
                             negatives_per_positive=config.negatives_per_positive,
                             rng=np.random.default_rng(config.seed))
    scores = pair_scores(pairs.query, pairs.scan)
    positive = pairs.positive
    pr = pr_sweep(-scores, positive, num_positives=int(positive.sum()), num_queries=len(pairs))

    # loop queries: an earlier scan within loop_radius, more than min_frame_gap frames back
    dist = planar_distances(pos[queries], pos)
    earlier = np.arange(len(cache))[None, :] < (queries[:, None] - config.min_frame_gap)
    loop = ((dist <= config.loop_radius) & earlier).any(axis=1)
    recall: dict[int, float] = {}
    if loop.any():
        ids, best = ranked(queries[loop], max(config.n_values))
        result = ranked_protocol(protocol="loop closure", ranked_ids=ids, ranked_distances=-best,
                                 query_positions=pos[queries[loop]], database_positions=pos,
                                 has_match=np.ones(int(loop.sum()), bool), radius=config.loop_radius,
                                 n_values=config.n_values)
        recall = dict(result.recall_at)
    return MethodEval(name=name, num_positive_pairs=int(positive.sum()), num_negative_pairs=int((~positive).sum()),
                      pairs_pr=pr, num_loop_queries=int(loop.sum()), recall_at=recall,
                      seconds=time.perf_counter() - start, pair_scores=scores)


@torch.inference_mode()
def chunked_pair_logits(net: Vseq2pcNet, d_seq: np.ndarray, query_rows: np.ndarray, slices: np.ndarray,
                scan_rows: np.ndarray, *, chunk: int = 8192) -> np.ndarray:
    """Max-slice logits of the pairs (d_seq[query_rows[i]], slices[scan_rows[i]]), gathered chunk by chunk."""
    out = np.empty(len(query_rows), np.float32)
    for lo in range(0, len(query_rows), chunk):
        q = torch.from_numpy(d_seq[query_rows[lo : lo + chunk]])[:, None, :]
        s = torch.from_numpy(slices[scan_rows[lo : lo + chunk]])
        out[lo : lo + chunk] = head_logits(net.descriptor, q, s)[0].numpy()
    return out


def table(results: Sequence[MethodEval], *, n_values: Sequence[int]) -> str:
    heads = ["method", "pos/neg pairs", "max F1"] + [f"R@{n}" for n in n_values] + ["loop queries", "s"]
    rows = [heads]
    for r in results:
        rows.append([r.name, f"{r.num_positive_pairs}/{r.num_negative_pairs}",
                     "-" if r.max_f1 is None else f"{r.max_f1:.3f}"]
                    + [f"{r.recall_at[n]:.3f}" if n in r.recall_at else "-" for n in n_values]
                    + [str(r.num_loop_queries), f"{r.seconds:.1f}"])
    widths = [max(len(row[i]) for row in rows) for i in range(len(heads))]
    return "\n".join("  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                               for i, (c, w) in enumerate(zip(row, widths, strict=True)))
                     for row in rows)


def plot_pr(results: Sequence[MethodEval], path: str | os.PathLike[str], *, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for k, r in enumerate(results):
        if r.pairs_pr is None:
            continue
        ax.plot(r.pairs_pr.recall, r.pairs_pr.precision, color=f"C{k}", lw=1.5,
                label=f"{r.name}: max F1 {r.pairs_pr.max_f1:.3f}")
        best = int(np.argmax(r.pairs_pr.f1))
        ax.plot(r.pairs_pr.recall[best], r.pairs_pr.precision[best], "o", color=f"C{k}")
    ax.set(xlabel="recall", ylabel="precision", title=title, xlim=(0, 1.02), ylim=(0, 1.02))
    ax.title.set_fontsize(9)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path)
