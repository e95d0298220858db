"""Ground-truth revisits (loop closures) of a trajectory: which earlier places does each pose revisit?

A pair (query, match) is a revisit when the match is more than ``min_time_gap`` older and the two
are the same place by :func:`lcpr_core.positives.within_radius`. :func:`revisit_pairs` hashes
positions into a grid of ``radius``-sized cells and only compares poses in neighbouring cells, so
it runs in O(N log N + M) time (M = pairs) with numpy alone.
"""
from __future__ import annotations

import itertools

import numpy as np

from .errors import InputShapeError, InvalidValueError
from .positives import within_radius

_MAX_CANDIDATES = 2_000_000  # candidate pairs expanded at once (bounds memory)


def _check(
    positions: np.ndarray, stamps: np.ndarray, radius: float, min_time_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    P = np.asarray(positions, dtype=np.float64)
    t = np.asarray(stamps, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise InputShapeError(f"positions must be N x 2 or N x 3, got shape {P.shape}")
    if t.shape != (P.shape[0],):
        raise InputShapeError(f"stamps must have shape ({P.shape[0]},) to match positions, got {t.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(t))):
        raise InvalidValueError("positions and stamps must be finite")
    if not radius > 0:
        raise InvalidValueError(f"radius must be > 0 metres, got {radius}")
    if not min_time_gap >= 0:
        raise InvalidValueError(f"min_time_gap must be >= 0 seconds, got {min_time_gap}")
    return P, t


def revisit_pairs(
    positions: np.ndarray, stamps: np.ndarray, *, radius: float = 9.0, min_time_gap: float = 30.0
) -> np.ndarray:
    """All (query, match) index pairs with ``stamps[query] - stamps[match] > min_time_gap`` and
    ``|positions[query] - positions[match]| <= radius``; M x 2 int64 sorted by query, then match."""
    P, t = _check(positions, stamps, radius, min_time_gap)
    n, dims = P.shape
    if n == 0:
        return np.zeros((0, 2), dtype=np.int64)
    cells = np.floor(P / radius).astype(np.int64)
    cells -= cells.min(axis=0) - 1  # a border of empty cells keeps every neighbour index in range
    sizes = cells.max(axis=0) + 2
    if float(np.prod(sizes.astype(np.float64))) >= 2.0**62:
        raise InvalidValueError(
            f"the trajectory spans {sizes.tolist()} cells of {radius} m; accepted: fewer than 2**62 cells in all"
        )
    strides = np.ones(dims, dtype=np.int64)
    for axis in range(dims - 2, -1, -1):
        strides[axis] = strides[axis + 1] * sizes[axis + 1]
    keys = cells @ strides
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    deltas = [int(np.dot(offset, strides)) for offset in itertools.product((-1, 0, 1), repeat=dims)]
    lo = np.stack([np.searchsorted(sorted_keys, keys + d, side="left") for d in deltas])
    hi = np.stack([np.searchsorted(sorted_keys, keys + d, side="right") for d in deltas])
    per_query = (hi - lo).sum(axis=0)
    pieces: list[np.ndarray] = []
    start = 0
    cumulative = np.cumsum(per_query)
    while start < n:
        budget = (cumulative[start - 1] if start else 0) + _MAX_CANDIDATES
        stop = max(int(np.searchsorted(cumulative, budget, side="right")), start + 1)
        pieces.append(_pairs_in(slice(start, stop), lo, hi, order, P, t, radius, min_time_gap))
        start = stop
    pairs = np.concatenate(pieces) if pieces else np.zeros((0, 2), dtype=np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _pairs_in(
    queries: slice, lo: np.ndarray, hi: np.ndarray, order: np.ndarray, P: np.ndarray, t: np.ndarray,
    radius: float, min_time_gap: float,
) -> np.ndarray:
    q_all = np.arange(queries.start, queries.stop)
    found = []
    for row in range(lo.shape[0]):
        first, counts = lo[row, queries], hi[row, queries] - lo[row, queries]
        total = int(counts.sum())
        if total == 0:
            continue
        q = np.repeat(q_all, counts)
        within = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        m = order[np.repeat(first, counts) + within]
        keep = (t[q] - t[m] > min_time_gap) & within_radius(P[q] - P[m], radius)
        if keep.any():
            found.append(np.stack([q[keep], m[keep]], axis=1))
    return np.concatenate(found) if found else np.zeros((0, 2), dtype=np.int64)
