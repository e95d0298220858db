"""A pair whose points lie where the other sensor saw through is refused as "contradicted"."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lcpr_core.errors import VerificationError
from lcpr_core.verification import REJECT_REASONS, GeometricVerifier, VerifierConfig
from lcpr_core.verification.free_space import MARGIN_M, FreeSpace
from lcpr_offline.synthetic_scenes import scattered_world, sensor_view

CONFIG = VerifierConfig(num_threads=1)


def _ring(radius: float, *, count: int = 3600, z: float = 0.0) -> np.ndarray:
    """``count`` points on a horizontal circle of ``radius`` m around the origin at height ``z``."""
    angle = np.linspace(-math.pi, math.pi, count, endpoint=False)
    return np.c_[radius * np.cos(angle), radius * np.sin(angle), np.full(count, z)]


def test_a_point_in_front_of_what_the_sensor_saw_contradicts_it_and_one_behind_does_not():
    space = FreeSpace(_ring(20.0))
    bad, seen = space.contradicting(np.array([[10.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 20.0 - MARGIN_M / 2, 0.0]]))
    assert (bad, seen) == (1, 3)  # in front: seen through; behind: hidden; within the margin: the same surface


def test_directions_the_sensor_did_not_see_say_nothing():
    space = FreeSpace(_ring(20.0))  # a ring at the sensor's height: nothing seen 30 deg up
    up = np.array([[10.0 * math.cos(math.radians(30)), 0.0, 10.0 * math.sin(math.radians(30))]])
    assert space.contradicting(up) == (0, 0)


def test_a_return_in_the_next_bin_still_shades_a_point():
    post = np.array([[5.0, 0.0, 0.0]])  # a post at 5 m, one return
    space = FreeSpace(np.concatenate([_ring(20.0), post]))
    beside = np.array([[6.0 * math.cos(math.radians(2.5)), 6.0 * math.sin(math.radians(2.5)), 0.0]])  # next bin
    assert space.contradicting(beside) == (0, 1)  # nearer than the wall, but not than the post next to it


def test_excused_points_never_count():
    space = FreeSpace(_ring(20.0))
    points = np.array([[10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    assert space.contradicting(points, excused=np.array([True, False])) == (1, 2)


@pytest.fixture(scope="module")
def views() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(match, query, walls): two views 2 m apart of one place, and three 6 m walls around the query (4 m ahead,
    6 m to each side) that stand where the match's sensor saw straight through to the ground behind them."""
    world = scattered_world(4)
    match = sensor_view(world, 0.0, 0.0, 0.0, seed=1, reach=25.0)
    query = sensor_view(world, 2.0, 0.0, 0.0, seed=2, reach=25.0)
    rng = np.random.default_rng(5)
    n = 3000
    ahead = np.c_[np.full(n, 6.0), rng.uniform(-6.0, 6.0, n), rng.uniform(-1.8, 4.2, n)]
    left = np.c_[rng.uniform(-2.0, 6.0, n), np.full(n, 6.0), rng.uniform(-1.8, 4.2, n)]
    return match, query, np.concatenate([ahead, left, left * (1.0, -1.0, 1.0)])


TRUTH = np.array([[1.0, 0, 0, 2.0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])  # match_T_query


def test_the_same_place_rightly_aligned_is_hardly_contradicted(views):
    match, query, _ = views
    v = GeometricVerifier(CONFIG).verify(query, match, initial_guess=TRUTH)
    assert v.accepted, v.reason
    assert v.contradiction < CONFIG.max_contradiction / 2


def test_walls_the_other_sensor_saw_through_refuse_the_pair_as_contradicted(views):
    match, query, walls = views
    changed = np.concatenate([query, walls])
    without = GeometricVerifier(replace(CONFIG, max_contradiction=1.0)).verify(changed, match, initial_guess=TRUTH)
    # what the test guards against: the rest of the place still overlaps enough to be accepted
    assert without.accepted, without.reason
    assert math.isnan(without.contradiction)  # 1 = the test does not run
    v = GeometricVerifier(CONFIG).verify(changed, match, initial_guess=TRUTH)
    assert not v.accepted and v.reason == "contradicted" and "contradicted" in REJECT_REASONS
    assert v.contradiction > CONFIG.max_contradiction


@pytest.mark.parametrize("value", [-0.1, 1.5, True, math.nan])
def test_a_max_contradiction_outside_0_to_1_is_refused_with_its_value(value):
    with pytest.raises(VerificationError, match=r"max_contradiction=.*accepted: 0 <= max_contradiction <= 1"):
        VerifierConfig(max_contradiction=value)
