"""A pose that could slide along a street onto a look-alike is refused as "ambiguous", not published."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lcpr_core.errors import VerificationError
from lcpr_core.verification import REJECT_REASONS, GeometricVerifier, VerifierConfig

CONFIG = VerifierConfig(num_threads=1)
LENGTH = 240.0  # m of street, much longer than a view


def _street(seed: int) -> np.ndarray:
    """N x 3 world points of a straight street along x: ground, two continuous 6 m walls 16 m apart, and 56 poles
    and 28 boxes at random places along it (the only things that pin down a position along the street)."""
    rng = np.random.default_rng(seed)
    ground = int(LENGTH * 128)
    parts = [np.c_[rng.uniform(-LENGTH / 2, LENGTH / 2, ground), rng.uniform(-8, 8, ground), np.zeros(ground)]]
    wall = int(LENGTH * 60)
    for y in (-8.0, 8.0):
        parts.append(np.c_[rng.uniform(-LENGTH / 2, LENGTH / 2, wall), np.full(wall, y), rng.uniform(0, 6, wall)])
    for x in rng.uniform(-LENGTH / 2, LENGTH / 2, 56):  # poles, radius 0.25 m, 5 m high
        y, angle = rng.choice((-6.0, 6.0)), rng.uniform(0, 2 * math.pi, 150)
        parts.append(np.c_[x + 0.25 * np.cos(angle), y + 0.25 * np.sin(angle), rng.uniform(0, 5, 150)])
    for x in rng.uniform(-LENGTH / 2, LENGTH / 2, 28):  # boxes by the walls: four sides and a top
        u, face = rng.uniform(-1, 1, (300, 3)), rng.integers(0, 5, 300)
        for f, (axis, side) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1), (2, 1))):
            u[face == f, axis] = side
        parts.append(np.c_[x + u[:, 0], rng.choice((-7.0, 7.0)) + 0.8 * u[:, 1], u[:, 2] + 1.0])
    return np.concatenate(parts)


def _view(world: np.ndarray, x: float, y: float, yaw_deg: float, seed: int) -> np.ndarray:
    """M x 3: what a sensor 1.8 m above (x, y), turned by yaw, sees within 40 m (its own 85 %, 1 cm noise)."""
    rng = np.random.default_rng(seed)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    local = (world - (x, y, 1.8)) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = local[(np.linalg.norm(local, axis=1) < 40.0) & (rng.random(len(local)) < 0.85)]
    return local + rng.normal(0.0, 0.01, local.shape)


@pytest.fixture(scope="module")
def street_pair() -> tuple[np.ndarray, np.ndarray, float]:
    """(query, match, metres apart): the query 10 m further along the street, turned 5 deg."""
    world = _street(9)
    return _view(world, 10.0, 0.5, 5.0, seed=2), _view(world, 0.0, 0.0, 0.0, seed=1), 10.0


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
    v = GeometricVerifier(CONFIG).verify(_view(points, 1.5, -1.0, 20.0, seed=5), _view(points, 0.0, 0.0, 0.0, seed=6))
    assert v.accepted, v.reason
    assert v.translation_constraint >= CONFIG.ambiguity_constraint
    assert math.isnan(v.alternative_fitness)  # the check only runs on weakly constrained pairs


def test_a_refused_pair_costs_no_ambiguity_check(street_pair):
    query, _, _ = street_pair
    other = _view(_street(99), 0.0, 0.0, 0.0, seed=7)  # another street: refused before the check
    v = GeometricVerifier(replace(CONFIG, min_fitness=0.99)).verify(query, other)
    assert not v.accepted and v.reason != "ambiguous"
    assert math.isnan(v.alternative_fitness)


@pytest.mark.parametrize("field, value", [("ambiguity_constraint", -0.1), ("ambiguity_ratio", 0.0),
                                          ("ambiguity_distance", 0.0)])
def test_an_ambiguity_setting_out_of_range_is_refused_naming_the_field(field, value):
    with pytest.raises(VerificationError, match=field):
        VerifierConfig(**{field: value})
