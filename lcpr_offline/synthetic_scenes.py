"""Small synthetic LiDAR scenes with known answers, for the verifier's tests and studies.

    world = scattered_world(1)                    # ground, walls and poles over 80 x 80 m
    street = straight_street(9)                   # a 240 m street that a registration can slide along
    cloud = sensor_view(world, 1.5, -1.0, 10.0, seed=20)   # what a sensor there sees, in its own frame
"""
from __future__ import annotations

import math

import numpy as np

STREET_LENGTH = 240.0  # m, much longer than a view


def scattered_world(seed: int) -> np.ndarray:
    """N x 3 world points: ground, 10 walls and 20 poles scattered over 80 x 80 m (every view is distinct)."""
    rng = np.random.default_rng(seed)
    parts = [np.c_[rng.uniform(-40, 40, (4000, 2)), np.zeros(4000)]]
    for _ in range(10):
        (cx, cy), heading = rng.uniform(-30, 30, 2), rng.uniform(0, math.pi)
        s, z = rng.uniform(-10, 10, 800), rng.uniform(0, rng.uniform(3, 8), 800)
        parts.append(np.c_[cx + s * math.cos(heading), cy + s * math.sin(heading), z])
    for _ in range(20):
        (cx, cy), angle = rng.uniform(-35, 35, 2), rng.uniform(0, 2 * math.pi, 150)
        parts.append(np.c_[cx + 0.2 * np.cos(angle), cy + 0.2 * np.sin(angle), rng.uniform(0, 5, 150)])
    return np.concatenate(parts)


def straight_street(seed: int, *, length: float = STREET_LENGTH) -> np.ndarray:
    """N x 3 world points of a straight street along x: ground, two continuous 6 m walls 16 m apart, and 56 poles
    and 28 boxes at random places along it (the only things that pin down a position along the street)."""
    rng = np.random.default_rng(seed)
    ground = int(length * 128)
    parts = [np.c_[rng.uniform(-length / 2, length / 2, ground), rng.uniform(-8, 8, ground), np.zeros(ground)]]
    wall = int(length * 60)
    for y in (-8.0, 8.0):
        parts.append(np.c_[rng.uniform(-length / 2, length / 2, wall), np.full(wall, y), rng.uniform(0, 6, wall)])
    for x in rng.uniform(-length / 2, length / 2, 56):  # poles, radius 0.25 m, 5 m high
        y, angle = rng.choice((-6.0, 6.0)), rng.uniform(0, 2 * math.pi, 150)
        parts.append(np.c_[x + 0.25 * np.cos(angle), y + 0.25 * np.sin(angle), rng.uniform(0, 5, 150)])
    for x in rng.uniform(-length / 2, length / 2, 28):  # boxes by the walls: four sides and a top
        u, face = rng.uniform(-1, 1, (300, 3)), rng.integers(0, 5, 300)
        for f, (axis, side) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1), (2, 1))):
            u[face == f, axis] = side
        parts.append(np.c_[x + u[:, 0], rng.choice((-7.0, 7.0)) + 0.8 * u[:, 1], u[:, 2] + 1.0])
    return np.concatenate(parts)


def sensor_view(world: np.ndarray, x: float, y: float, yaw_deg: float, *, seed: int, reach: float = 50.0
                ) -> np.ndarray:
    """M x 3: what a sensor 1.8 m above (x, y), turned by ``yaw_deg``, sees within ``reach`` m, in its own frame
    (a random 85 % of those points, 1 cm noise)."""
    rng = np.random.default_rng(seed)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    local = (world - (x, y, 1.8)) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = local[(np.linalg.norm(local, axis=1) < reach) & (rng.random(len(local)) < 0.85)]
    return local + rng.normal(0.0, 0.01, local.shape)
