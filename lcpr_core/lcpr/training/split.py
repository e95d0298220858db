"""The paper's data organisation: a database and train / val / test queries, from poses alone.

Samples are taken in time order within each bag (group). A sample whose position lies
within ``positive_radius`` of a database sample recorded more than ``exclude_recent_s``
earlier is a revisit and becomes a query; every other sample joins the database (so
the database covers the whole area and queries always have ground truth). Queries are
then shuffled (seeded) into train / val / test by ``fractions``.

For a query, *positives* are database samples of its bag within ``positive_radius`` and
more than ``exclude_recent_s`` away in time; *negatives* are database samples at least
``negative_radius`` away, or from another bag (another place altogether).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InvalidValueError
from ...positives import within_radius
from .config import SplitConfig

QUERY_SETS = ("train", "val", "test")


@dataclass(frozen=True)
class Split:
    """Sample indices of each set, and the geometry to find positives and negatives."""

    database: np.ndarray  # sample indices, ascending
    train: np.ndarray
    val: np.ndarray
    test: np.ndarray
    positions: np.ndarray  # N x 2 (x, y) of every sample
    stamps: np.ndarray  # N
    groups: np.ndarray  # N bag index
    config: SplitConfig

    def queries(self, name: str) -> np.ndarray:
        if name not in QUERY_SETS:
            raise InvalidValueError(f"query set {name!r}; accepted: {', '.join(QUERY_SETS)}")
        return getattr(self, name)

    def positives(self, query: int) -> np.ndarray:
        """Database sample indices that are positives of sample ``query`` (may be empty)."""
        return self.database[self._near(query, self.config.positive_radius) & self._not_recent(query)]

    def negatives(self, query: int) -> np.ndarray:
        """Database sample indices that are negatives of sample ``query``."""
        db = self.database
        other = self.groups[db] != self.groups[query]
        far = np.linalg.norm(self.positions[db] - self.positions[query], axis=1) >= self.config.negative_radius
        return db[other | far]

    def excluded(self, query: int) -> np.ndarray:
        """Boolean mask over the database: entries retrieval must skip (same bag, too recent)."""
        return ~self._not_recent(query)

    def _near(self, query: int, radius: float) -> np.ndarray:
        db = self.database
        same = self.groups[db] == self.groups[query]
        return same & within_radius(self.positions[db] - self.positions[query], radius)

    def _not_recent(self, query: int) -> np.ndarray:
        db = self.database
        same = self.groups[db] == self.groups[query]
        return ~same | (np.abs(self.stamps[db] - self.stamps[query]) > self.config.exclude_recent_s)

    def summary(self) -> dict[str, int]:
        return {"samples": len(self.stamps), "database": len(self.database),
                **{name: len(self.queries(name)) for name in QUERY_SETS}}


def split_samples(positions: np.ndarray, stamps: np.ndarray, groups: np.ndarray,
                  config: SplitConfig = SplitConfig()) -> Split:
    """Organise N samples (N x 2|3 positions, N stamps, N bag indices) into database and query sets."""
    pos = np.asarray(positions, np.float64)[:, :2]
    t = np.asarray(stamps, np.float64)
    g = np.asarray(groups, np.int64)
    if pos.ndim != 2 or not (len(pos) == len(t) == len(g)):
        raise InvalidValueError(
            f"positions {np.shape(positions)}, stamps {np.shape(stamps)}, groups {np.shape(groups)}; "
            f"expected N x 2|3, N and N")
    if not (np.isfinite(pos).all() and np.isfinite(t).all()):
        raise InvalidValueError("positions and stamps must be finite")
    is_query = np.zeros(len(t), bool)
    for group in np.unique(g):
        members = np.flatnonzero(g == group)
        members = members[np.argsort(t[members], kind="stable")]
        is_query[members] = _revisits(pos[members], t[members], config)
    queries = np.flatnonzero(is_query)
    rng = np.random.default_rng(config.seed)
    queries = queries[rng.permutation(len(queries))]
    n_train = int(round(config.fractions[0] * len(queries)))
    n_val = int(round(config.fractions[1] * len(queries)))
    sets = np.split(queries, [n_train, n_train + n_val])
    return Split(database=np.flatnonzero(~is_query), train=np.sort(sets[0]), val=np.sort(sets[1]),
                 test=np.sort(sets[2]), positions=pos, stamps=t, groups=g, config=config)


def _revisits(pos: np.ndarray, t: np.ndarray, config: SplitConfig) -> np.ndarray:
    """Time-ordered samples of one bag -> True where a sample revisits an older database sample."""
    is_query = np.zeros(len(t), bool)
    for i in range(len(t)):
        older = (t[i] - t[:i] > config.exclude_recent_s) & ~is_query[:i]
        if older.any():
            is_query[i] = bool(within_radius(pos[:i][older] - pos[i], config.positive_radius).any())
    return is_query
