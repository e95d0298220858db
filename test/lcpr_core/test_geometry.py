"""SE(3) helpers of lcpr_core.geometry: poses from and to a translation with roll, pitch and yaw."""
from __future__ import annotations

import math

import numpy as np

from lcpr_core.geometry import pose_from_xyz_rpy, xyz_rpy_from_pose


def test_roll_pitch_yaw_come_back_from_the_pose_they_make() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        xyz = tuple(rng.normal(size=3))
        rpy = (rng.uniform(-math.pi, math.pi), rng.uniform(-1.5, 1.5), rng.uniform(-math.pi, math.pi))
        got_xyz, got_rpy = xyz_rpy_from_pose(pose_from_xyz_rpy(xyz, rpy))
        assert np.allclose(got_xyz, xyz) and np.allclose(got_rpy, rpy)


def test_a_pitch_of_ninety_degrees_still_gives_a_pose_that_rebuilds_the_rotation() -> None:
    T = pose_from_xyz_rpy((1.0, 2.0, 3.0), (0.3, math.pi / 2, -0.4))
    xyz, rpy = xyz_rpy_from_pose(T)
    assert np.allclose(pose_from_xyz_rpy(xyz, rpy), T, atol=1e-9)
