"""Ground-truth revisits (lcpr_core.revisits) on hand-made trajectories, checked against brute force."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lcpr_core.errors import InputShapeError, InvalidValueError
from lcpr_core.revisits import revisit_pairs


def _brute_force(positions: np.ndarray, stamps: np.ndarray, radius: float, gap: float,
                 queries: np.ndarray | None = None) -> np.ndarray:
    """(query, match) pairs by the rule itself, sorted; ``queries``: only these query indices (default all)."""
    q = np.arange(len(positions)) if queries is None else queries
    d = np.linalg.norm(positions[q, None] - positions[None], axis=-1)
    rows, cols = np.nonzero((d <= radius) & (stamps[q, None] - stamps[None] > gap))
    return np.stack([q[rows], cols], axis=1)


def _square_loop(laps: int, side: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """Drive a square at 1 m/s, sampled every second, ``laps`` times."""
    s = np.arange(int(4 * side * laps), dtype=np.float64)
    edge, along = np.divmod(s % (4 * side), side)
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], dtype=np.float64)
    start, end = corners[edge.astype(int)], corners[edge.astype(int) + 1]
    positions = start + (end - start) * (along / side)[:, None]
    return positions, s


def test_the_second_lap_of_a_loop_revisits_the_first() -> None:
    positions, stamps = _square_loop(2)
    pairs = revisit_pairs(positions, stamps, radius=9.0, min_time_gap=30.0)
    assert np.array_equal(pairs, _brute_force(positions, stamps, 9.0, 30.0))
    queries = np.unique(pairs[:, 0])
    assert queries.min() >= 160 - 9  # nothing before the loop closes (corner shortcuts start a little early)
    assert set(range(160, 320)) <= set(queries.tolist())  # every pose of lap 2 has a match
    q = 160 + 20  # middle of the first edge on lap 2
    assert set(pairs[pairs[:, 0] == q, 1].tolist()) == set(range(11, 30))
    assert np.all(stamps[pairs[:, 0]] - stamps[pairs[:, 1]] > 30.0)


def test_three_dimensional_positions_use_their_height() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 20.0], [1.0, 0.0, 0.0]])  # a bridge over the start
    stamps = np.array([0.0, 100.0, 200.0])
    assert revisit_pairs(positions, stamps).tolist() == [[2, 0]]
    assert revisit_pairs(positions[:, :2], stamps).tolist() == [[1, 0], [2, 0], [2, 1]]


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 120),
    dims=st.sampled_from([2, 3]),
    radius=st.floats(0.5, 30.0),
    gap=st.floats(0.0, 50.0),
    seed=st.integers(0, 2**31),
)
def test_grid_search_finds_exactly_the_brute_force_pairs(
    n: int, dims: int, radius: float, gap: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-60, 60, size=(n, dims))
    stamps = rng.uniform(0, 300, size=n)
    got = revisit_pairs(positions, stamps, radius=radius, min_time_gap=gap)
    assert got.dtype == np.int64 and got.shape[1] == 2
    assert np.array_equal(got, _brute_force(positions, stamps, radius, gap).reshape(-1, 2))


def test_ten_thousand_poses_give_the_pairs_of_the_brute_force_rule() -> None:
    # Speed is benchmarked, not timed here; at this size the cell grid must still find every pair.
    positions, stamps = _square_loop(5, side=500.0)  # 10 000 poses, 5 laps
    pairs = revisit_pairs(positions, stamps)
    queries = np.arange(0, len(stamps), 97)  # every 97th pose, brute force against all
    expected = _brute_force(positions, stamps, 9.0, 30.0, queries=queries)
    assert len(expected) > 0 and np.array_equal(pairs[np.isin(pairs[:, 0], queries)], expected)
    assert np.all(pairs[:, 0] > pairs[:, 1])


def test_bad_trajectories_are_refused_by_name() -> None:
    with pytest.raises(InputShapeError, match="N x 2 or N x 3, got shape \\(4,\\)"):
        revisit_pairs(np.zeros(4), np.zeros(4))
    with pytest.raises(InputShapeError, match="stamps must have shape \\(3,\\)"):
        revisit_pairs(np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(InvalidValueError, match="radius must be > 0"):
        revisit_pairs(np.zeros((3, 2)), np.zeros(3), radius=0.0)
