"""The "exclude recent" rule every matcher uses (LCPR's detector and evaluation, Scan Context, VSeq2PC).

A query at time ``t`` may be matched only with places stamped at or before ``t - exclude_recent_s``:
the places just driven through look alike and would always win. (Training's positives use their own,
symmetric rule: ``|t_a - t_b| > exclude_recent_s``, see :mod:`lcpr_core.lcpr.training.split`.)
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def newest_matchable(query_stamp: float, exclude_recent_s: float) -> float:
    """The latest stamp a query at ``query_stamp`` may be matched with."""
    return float(query_stamp) - float(exclude_recent_s)


def matchable(stamps: np.ndarray | Sequence[float], query_stamp: float, exclude_recent_s: float) -> np.ndarray:
    """Boolean mask of the ``stamps`` a query at ``query_stamp`` may be matched with."""
    return np.asarray(stamps) <= newest_matchable(query_stamp, exclude_recent_s)


def matchable_prefix(sorted_stamps: np.ndarray | Sequence[float], query_stamp: float, exclude_recent_s: float) -> int:
    """With ``sorted_stamps`` non-decreasing: how many of the first ones a query may be matched with."""
    return int(np.searchsorted(sorted_stamps, newest_matchable(query_stamp, exclude_recent_s), side="right"))
