"""Hard-example mining on cached descriptors (the paper's Sec. III-D).

For each training query: the positive is the potential positive whose descriptor is
closest to the query's; negatives are drawn at random from the potential negatives
(a pool of ``pool``), and only those *inside the margin* are kept, hardest first, up to
``negatives``. "Inside the margin" is ``d(q, n) < d(q, p) + m`` (rule ``violating``: the
negatives whose hinge is active) or the paper's literal Eq. 7 ``d(q, n) < m`` (rule
``absolute``). A query left with no negative is skipped for the epoch.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ...errors import InvalidValueError
from .config import MiningConfig
from .split import Split


@dataclass(frozen=True)
class Triplet:
    """One training tuple: sample indices of a query, its positive and its negatives."""

    query: int
    positive: int
    negatives: tuple[int, ...]


@dataclass
class MiningStats:
    queries: int = 0
    tuples: int = 0
    no_positive: int = 0
    no_negative: int = 0  # every pooled negative was outside the margin: nothing to learn
    negatives: int = 0  # negatives kept, in all

    @property
    def mean_negatives(self) -> float:
        return self.negatives / self.tuples if self.tuples else 0.0


@dataclass
class MiningResult:
    triplets: list[Triplet] = field(default_factory=list)
    stats: MiningStats = field(default_factory=MiningStats)


def closest_positive(query_desc: np.ndarray, positive_ids: np.ndarray, positive_desc: np.ndarray) -> tuple[int, float]:
    """(sample index, descriptor distance) of the positive closest to the query in descriptor space."""
    if len(positive_ids) == 0:
        raise InvalidValueError("no positives given; a query needs at least one to be mined")
    d = np.linalg.norm(positive_desc - query_desc, axis=1)
    best = int(np.argmin(d))
    return int(positive_ids[best]), float(d[best])


def negatives_inside_margin(
    query_desc: np.ndarray,
    positive_dist: float,
    negative_ids: np.ndarray,
    negative_desc: np.ndarray,
    config: MiningConfig,
) -> np.ndarray:
    """The given negatives inside the margin (see the module doc), hardest first, at most ``config.negatives``."""
    d = np.linalg.norm(negative_desc - query_desc, axis=1)
    limit = positive_dist + config.margin if config.rule == "violating" else config.margin
    inside = np.flatnonzero(d < limit)
    inside = inside[np.argsort(d[inside], kind="stable")][:config.negatives]
    return np.asarray(negative_ids, np.int64)[inside]


def mine(
    queries: Iterable[int],
    split: Split,
    descriptors: np.ndarray,
    config: MiningConfig,
    rng: np.random.Generator,
) -> MiningResult:
    """Triplets for ``queries`` from descriptors of every sample (N x D; rows of unused samples are ignored)."""
    result = MiningResult()
    stats = result.stats
    for q in queries:
        stats.queries += 1
        pos = split.positives(int(q))
        if len(pos) == 0:
            stats.no_positive += 1
            continue
        positive, d_pos = closest_positive(descriptors[q], pos, descriptors[pos])
        neg = split.negatives(int(q))
        if len(neg) > config.pool:
            neg = rng.choice(neg, size=config.pool, replace=False)
        chosen = negatives_inside_margin(descriptors[q], d_pos, neg, descriptors[neg], config)
        if len(chosen) == 0:
            stats.no_negative += 1
            continue
        result.triplets.append(Triplet(query=int(q), positive=positive, negatives=tuple(int(n) for n in chosen)))
        stats.tuples += 1
        stats.negatives += len(chosen)
    return result
