"""The paper's data organisation from poses: database, queries, positives <= 9 m, negatives >= 18 m."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core.lcpr.training import SplitConfig, split_samples
from training_fixtures import out_and_back


def test_first_visits_form_the_database_and_revisits_become_queries():
    pos, stamps = out_and_back(n=24, step=5.0, dt=10.0)
    split = split_samples(pos, stamps, np.zeros(24, int), SplitConfig(fractions=(0.5, 0.25, 0.25)))
    queries = np.sort(np.concatenate([split.train, split.val, split.test]))
    assert np.array_equal(np.sort(np.concatenate([split.database, queries])), np.arange(24))
    assert split.database[:12].tolist() == list(range(12))  # the outward leg is all database
    for q in queries:  # every query revisits a database place recorded more than 30 s earlier
        pos_ids = split.positives(int(q))
        assert len(pos_ids) > 0
        assert (np.hypot(*(pos[pos_ids] - pos[q]).T) <= 9.0).all()
        assert (stamps[q] - stamps[pos_ids] > 30.0).all()
    assert split.database.tolist() == list(range(13))  # the turn (12) has no place seen 30 s before
    assert (len(split.train), len(split.val), len(split.test)) == (6, 3, 2)  # 11 queries by 0.5 / 0.25 / 0.25


def test_negatives_are_at_least_18_m_away_and_nothing_between_counts():
    pos, stamps = out_and_back()
    split = split_samples(pos, stamps, np.zeros(len(stamps), int))
    q = int(split.train[0])
    neg = split.negatives(q)
    d = np.hypot(*(pos[split.database] - pos[q]).T)
    assert set(neg.tolist()) == set(split.database[d >= 18.0].tolist())
    assert not set(neg.tolist()) & set(split.positives(q).tolist())


def test_samples_of_another_bag_are_negatives_never_positives():
    pos, stamps = out_and_back()
    both = split_samples(np.r_[pos, pos], np.r_[stamps, stamps], np.r_[np.zeros(24), np.ones(24)].astype(int))
    q = int(both.train[0])
    other_bag = both.database[both.groups[both.database] != both.groups[q]]
    assert set(other_bag.tolist()) <= set(both.negatives(q).tolist())
    assert (both.groups[both.positives(q)] == both.groups[q]).all()


def test_a_split_config_names_bad_values():
    with pytest.raises(ValueError, match="negative_radius=5"):
        SplitConfig(positive_radius=9.0, negative_radius=5.0)
    with pytest.raises(ValueError, match="fractions="):
        SplitConfig(fractions=(0.5, 0.5, 0.5))
