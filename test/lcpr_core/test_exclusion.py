"""The "exclude recent" rule shared by every matcher (lcpr_core.exclusion)."""
from __future__ import annotations

import numpy as np

from lcpr_core.exclusion import matchable, matchable_prefix, newest_matchable


def test_a_place_exactly_exclude_recent_s_older_may_be_matched_and_a_newer_one_not() -> None:
    stamps = np.array([0.0, 69.999, 70.0, 70.001, 100.0])
    assert newest_matchable(100.0, 30.0) == 70.0
    np.testing.assert_array_equal(matchable(stamps, 100.0, 30.0), [True, True, True, False, False])


def test_the_prefix_form_counts_the_same_places_as_the_mask_on_sorted_stamps() -> None:
    rng = np.random.default_rng(0)
    stamps = np.sort(rng.uniform(0, 200, 500))
    for query in (0.0, 31.0, 120.5, 400.0):
        assert matchable_prefix(stamps, query, 30.0) == int(matchable(stamps, query, 30.0).sum())
    assert matchable_prefix([], 10.0, 0.0) == 0
