"""The bird's-eye views behind the initial guess: each cell's height span, the same turned as rotated."""
from __future__ import annotations

import math

import numpy as np
import pytest

from lcpr_core.points import rotate_z
from lcpr_core.verification.initial import BevMatcher, bev_image


def _span_by_loop(xyz: np.ndarray, cell: float, extent: float) -> np.ndarray:
    size = int(round(2 * extent / cell))
    top, low = np.full((size, size), -np.inf), np.full((size, size), np.inf)
    for x, y, z in xyz:
        i, j = math.floor((x + extent) / cell), math.floor((y + extent) / cell)
        if 0 <= i < size and 0 <= j < size:
            top[i, j], low[i, j] = max(top[i, j], z), min(low[i, j], z)
    return np.where(np.isfinite(top), np.minimum(top - low, 3.0), 0.0).astype(np.float32)


@pytest.mark.parametrize("cell, extent", [(1.0, 8.0), (0.5, 4.0), (2.0, 10.0)])
def test_each_cell_holds_the_height_span_of_its_points_capped_at_3_m_and_outside_points_are_left_out(cell, extent):
    rng = np.random.default_rng(3)
    xyz = np.c_[rng.uniform(-1.5 * extent, 1.5 * extent, (600, 2)), rng.uniform(-1.0, 5.0, 600)]
    xyz[:5, :2] = (-extent, -extent), (extent, extent), (extent - 1e-9, 0.0), (0.0, -extent - 1e-9), (0.0, 0.0)
    assert np.array_equal(bev_image(xyz, cell=cell, extent=extent), _span_by_loop(xyz, cell, extent))


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, -37.5, 180.0])
def test_a_turned_query_is_located_as_the_same_points_rotated_beforehand(yaw_deg):
    rng = np.random.default_rng(4)
    world = np.c_[rng.uniform(-30, 30, (3000, 2)), rng.uniform(0, 4, 3000)]
    matcher = BevMatcher(world, cell=1.0, extent=24.0, max_offset=12.0)
    query = world[::2] - (3.0, -2.0, 0.0)
    yaw = math.radians(yaw_deg)
    turned = matcher.locate(query, yaw)
    rotated = matcher.locate(rotate_z(query, yaw_deg), 0.0)
    assert (turned.x, turned.y, turned.score) == (rotated.x, rotated.y, rotated.score)
    if yaw_deg == 0.0:
        assert (turned.x, turned.y) == (3.0, -2.0)  # the shift that brings the query back onto the world


def test_the_best_offset_is_found_only_within_reach():
    rng = np.random.default_rng(5)
    world = np.c_[rng.uniform(-30, 30, (3000, 2)), rng.uniform(0, 4, 3000)]
    near = BevMatcher(world, cell=1.0, extent=24.0, max_offset=4.0).locate(world - (8.0, 0.0, 0.0), 0.0)
    assert abs(near.x) <= 4.0 and abs(near.y) <= 4.0
