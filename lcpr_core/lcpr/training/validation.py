"""Recall@N of queries against the database on cached descriptors, as the split defines truth."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...errors import InvalidValueError
from .split import Split


@dataclass(frozen=True)
class Recall:
    recalls: dict[int, float]  # n -> fraction of evaluated queries with a positive among the top n
    queries: int  # queries evaluated (with at least one positive)

    def as_dict(self) -> dict[str, float]:
        return {f"recall@{n}": v for n, v in self.recalls.items()}


def split_recall(split: Split, descriptors: np.ndarray, queries: np.ndarray,
                 n_values: Sequence[int] = (1, 5, 10)) -> Recall:
    """Rank the database by descriptor distance for each query, skipping the entries
    :meth:`Split.excluded` names (same bag, too recent); a hit is a :meth:`Split.positives` entry."""
    ns = sorted({int(n) for n in n_values})
    if not ns or ns[0] < 1:
        raise InvalidValueError(f"n_values={list(n_values)}; accepted: positive integers")
    db = split.database
    db_desc = np.asarray(descriptors[db], np.float64)
    hits = {n: 0 for n in ns}
    evaluated = 0
    for q in np.asarray(queries, np.int64):
        positives = split.positives(int(q))
        if len(positives) == 0:
            continue
        evaluated += 1
        d = np.linalg.norm(db_desc - descriptors[q], axis=1)
        d[split.excluded(int(q))] = np.inf
        order = np.argsort(d, kind="stable")[:ns[-1]]
        found = np.isin(db[order], positives)
        for n in ns:
            hits[n] += bool(found[:n].any())
    return Recall(recalls={n: hits[n] / evaluated if evaluated else float("nan") for n in ns}, queries=evaluated)
