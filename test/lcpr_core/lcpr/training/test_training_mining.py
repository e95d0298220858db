"""Hard mining on hand-made descriptors, and the triplet loss of the paper's Eq. 8."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lcpr_core.lcpr.training import (
    MiningConfig,
    batch_triplet_loss,
    closest_positive,
    mine,
    negatives_inside_margin,
    split_samples,
    triplet_loss,
)
from training_fixtures import out_and_back


def unit(*v: float) -> np.ndarray:
    a = np.asarray(v, np.float64)
    return a / np.linalg.norm(a)


def test_mining_picks_the_positive_closest_in_descriptor_space():
    q = unit(1, 0, 0)
    ids = np.array([10, 11, 12])
    desc = np.stack([unit(0, 1, 0), unit(1, 0.1, 0), unit(1, 1, 0)])
    best, d = closest_positive(q, ids, desc)
    assert best == 11 and d == pytest.approx(np.linalg.norm(desc[1] - q))


def test_only_negatives_inside_the_margin_are_kept_hardest_first():
    q = np.array([1.0, 0.0])
    ids = np.array([20, 21, 22, 23, 24])
    dists = np.array([0.9, 0.3, 1.5, 0.6, 0.7])  # distances from q along y
    desc = q + np.stack([np.zeros(5), dists], axis=1)
    cfg = MiningConfig(negatives=2, margin=0.5, pool=8)
    # violating: d(q, n) < d(q, p) + m = 0.2 + 0.5 -> 21 (0.3), 23 (0.6); 24 (0.7) is not strictly inside
    assert negatives_inside_margin(q, 0.2, ids, desc, cfg).tolist() == [21, 23]
    assert negatives_inside_margin(q, 0.6, ids, desc, MiningConfig(negatives=6, pool=8)).tolist() == [21, 23, 24, 20]
    # absolute (Eq. 7): d(q, n) < m, whatever the positive
    assert negatives_inside_margin(q, 5.0, ids, desc, MiningConfig(negatives=6, pool=8, rule="absolute")).tolist() \
        == [21]


def test_mine_builds_triplets_and_skips_queries_without_hard_negatives():
    pos, stamps = out_and_back()
    split = split_samples(pos, stamps, np.zeros(len(stamps), int))
    desc = np.zeros((len(stamps), 2))
    desc[:, 0] = pos[:, 0] / 100.0  # descriptors that already order places well
    hard = mine(split.train, split, desc, MiningConfig(margin=0.5, negatives=6, pool=64), np.random.default_rng(0))
    assert hard.stats.tuples == len(split.train)
    for t in hard.triplets:
        assert t.positive in split.positives(t.query).tolist()
        assert set(t.negatives) <= set(split.negatives(t.query).tolist()) and 1 <= len(t.negatives) <= 6
    easy = mine(split.train, split, desc, MiningConfig(margin=0.01, pool=64), np.random.default_rng(0))
    assert easy.stats.tuples < len(split.train) and easy.stats.no_negative > 0


def test_the_triplet_loss_is_the_mean_hinge_over_negatives():
    q, p = torch.tensor([1.0, 0.0]), torch.tensor([0.8, 0.0])  # d(q, p) = 0.2
    n = torch.tensor([[1.0, 0.3], [1.0, 2.0]])  # d = 0.3 (hinge 0.4) and 2.0 (hinge 0)
    assert triplet_loss(q, p, n, margin=0.5).item() == pytest.approx(0.2)
    stacked = torch.cat([q[None], p[None], n, q[None], p[None], n[:1]])
    assert batch_triplet_loss(stacked, [2, 1], margin=0.5).item() == pytest.approx((0.2 + 0.4) / 2)
    with pytest.raises(ValueError, match="account for"):
        batch_triplet_loss(stacked, [2, 2])
