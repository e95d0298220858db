"""The positive-pair rule of LCPR's ground truth, metrics and training (lcpr_core.positives)."""
from __future__ import annotations

import numpy as np

from lcpr_core.positives import within_radius


def test_a_place_exactly_at_the_radius_is_the_same_place_and_height_counts() -> None:
    offsets = np.array([[9.0, 0.0, 0.0], [6.0, 6.0, 0.0], [6.0, 6.0, 3.1], [0.0, 0.0, 9.01]])
    np.testing.assert_array_equal(within_radius(offsets, 9.0), [True, True, False, False])


def test_unknown_positions_are_never_a_positive() -> None:
    assert not within_radius(np.array([np.nan, 0.0, 0.0]), 9.0)


def test_planar_positions_use_their_two_dimensions() -> None:
    np.testing.assert_array_equal(within_radius(np.array([[3.0, 4.0], [3.0, 4.1]]), 5.0), [True, False])
