"""The shared quaternion and interpolation helpers the core and the bag tools both use."""
from __future__ import annotations

import numpy as np

from lcpr_common.rotations import interpolate_poses, quaternions_xyzw, rotations_from_xyzw, slerp_xyzw


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return rotations_from_xyzw(q / np.linalg.norm(q, axis=1, keepdims=True))


def test_quaternions_round_trip_every_rotation_with_a_non_negative_w() -> None:
    rng = np.random.default_rng(0)
    r = np.concatenate([random_rotations(rng, 200), np.diag([1.0, -1.0, -1.0])[None], np.eye(3)[None]])
    q = quaternions_xyzw(r)
    assert np.all(q[:, 3] >= 0) and np.allclose(np.linalg.norm(q, axis=1), 1.0)
    assert np.allclose(rotations_from_xyzw(q), r, atol=1e-12)


def test_slerp_halfway_between_two_yaws_is_the_middle_yaw_along_the_short_arc() -> None:
    def yaw(deg: float) -> np.ndarray:
        h = np.radians(deg) / 2
        return np.array([0.0, 0.0, np.sin(h), np.cos(h)])

    mid = slerp_xyzw(yaw(170.0), -yaw(-170.0), 0.5)  # either sign of a quaternion is the same rotation
    assert np.allclose(rotations_from_xyzw(mid), rotations_from_xyzw(yaw(180.0)), atol=1e-12)
    assert np.allclose(slerp_xyzw(yaw(10.0), yaw(10.0), 0.3), yaw(10.0))  # identical ends: no division by zero


def test_interpolated_poses_move_linearly_and_keep_a_rotation_per_row() -> None:
    rng = np.random.default_rng(1)
    a, b = np.tile(np.eye(4), (5, 1, 1)), np.tile(np.eye(4), (5, 1, 1))
    a[:, :3, :3], b[:, :3, :3] = random_rotations(rng, 5), random_rotations(rng, 5)
    a[:, :3, 3], b[:, :3, 3] = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    w = np.linspace(0.0, 1.0, 5)
    out = interpolate_poses(a, b, w)
    assert np.allclose(out[0], a[0]) and np.allclose(out[-1], b[-1])
    assert np.allclose(out[:, :3, 3], (1 - w)[:, None] * a[:, :3, 3] + w[:, None] * b[:, :3, 3])
    r = out[:, :3, :3]
    assert np.allclose(r @ r.transpose(0, 2, 1), np.eye(3), atol=1e-12)
