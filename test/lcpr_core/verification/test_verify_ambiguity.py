"""A pose that could slide along a street onto a look-alike is refused as "ambiguous", not published."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lcpr_core.errors import VerificationError
from lcpr_core.verification import REJECT_REASONS, GeometricVerifier, VerifierConfig
from lcpr_offline.synthetic_scenes import sensor_view, straight_street

CONFIG = VerifierConfig(num_threads=1)


def _seen(world: np.ndarray, x: float, y: float, yaw_deg: float, seed: int) -> np.ndarray:
    return sensor_view(world, x, y, yaw_deg, seed=seed, reach=40.0)


@pytest.fixture(scope="module")
def street_pair() -> tuple[np.ndarray, np.ndarray, float]:
    """(query, match, metres apart): the query 10 m further along the street, turned 5 deg."""
    world = straight_street(9)
    return _seen(world, 10.0, 0.5, 5.0, seed=2), _seen(world, 0.0, 0.0, 0.0, seed=1), 10.0


def test_a_pair_that_slides_along_a_street_onto_a_wrong_pose_is_refused_as_ambiguous(street_pair):
    query, match, apart = street_pair
    without = GeometricVerifier(replace(CONFIG, ambiguity_constraint=0.0)).verify(query, match)
    # what the test guards against: without the check the slid pose is accepted, metres off along the street
    assert without.accepted
    assert abs(float(without.match_T_query[0, 3]) - apart) > 2.0
    v = GeometricVerifier(CONFIG).verify(query, match)
    assert not v.accepted and v.reason == "ambiguous" and "ambiguous" in REJECT_REASONS
    assert v.translation_constraint < CONFIG.ambiguity_constraint
    assert v.alternative_fitness >= CONFIG.ambiguity_ratio * v.fitness  # another pose fits about as well


def test_a_place_that_pins_down_every_direction_is_accepted_without_the_extra_registrations():
    rng = np.random.default_rng(3)
    world = [np.c_[rng.uniform(-40, 40, (6000, 2)), np.zeros(6000)]]
    for _ in range(10):  # walls in every direction
        (cx, cy), heading = rng.uniform(-30, 30, 2), rng.uniform(0, math.pi)
        s, z = rng.uniform(-10, 10, 900), rng.uniform(0, 6, 900)
        world.append(np.c_[cx + s * math.cos(heading), cy + s * math.sin(heading), z])
    points = np.concatenate(world)
    v = GeometricVerifier(CONFIG).verify(_seen(points, 1.5, -1.0, 20.0, seed=5), _seen(points, 0.0, 0.0, 0.0, seed=6))
    assert v.accepted, v.reason
    assert v.translation_constraint >= CONFIG.ambiguity_constraint
    assert math.isnan(v.alternative_fitness)  # the check only runs on weakly constrained pairs


def test_a_refused_pair_costs_no_ambiguity_check(street_pair):
    query, _, _ = street_pair
    other = _seen(straight_street(99), 0.0, 0.0, 0.0, seed=7)  # another street: refused before the check
    v = GeometricVerifier(replace(CONFIG, min_fitness=0.99)).verify(query, other)
    assert not v.accepted and v.reason != "ambiguous"
    assert math.isnan(v.alternative_fitness)


@pytest.mark.parametrize("field, value", [("ambiguity_constraint", -0.1), ("ambiguity_ratio", 0.0),
                                          ("ambiguity_distance", 0.0)])
def test_an_ambiguity_setting_out_of_range_is_refused_naming_the_field(field, value):
    with pytest.raises(VerificationError, match=field):
        VerifierConfig(**{field: value})
