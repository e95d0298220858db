"""Rigid-transform math on numpy arrays: quaternions (x, y, z, w order), 4 x 4 poses, interpolation."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from lcpr_common.rotations import interpolate_poses, quaternions_xyzw, rotations_from_xyzw, slerp_xyzw

from .errors import GeometryError


def quaternion_to_matrix(q_xyzw: ArrayLike) -> np.ndarray:
    """Unit quaternion (x, y, z, w; normalised here) -> 3 x 3 rotation matrix."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1)
    if q.size != 4 or not np.all(np.isfinite(q)):
        raise GeometryError(f"a quaternion needs 4 finite values (x, y, z, w), got {q.tolist()}")
    scale = float(np.abs(q).max())  # divided out first: the norm of values near 1e308 would overflow
    scaled = q / scale if scale else q
    if scale * float(np.linalg.norm(scaled)) < 1e-12:
        raise GeometryError(f"quaternion {q.tolist()} has zero length; accepted: a non-zero (unit) quaternion")
    return rotations_from_xyzw(scaled / np.linalg.norm(scaled))


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """3 x 3 rotation -> unit quaternion (x, y, z, w) with w >= 0 (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise GeometryError(f"a rotation must be a finite 3 x 3 matrix, got {m.tolist()}")
    return quaternions_xyzw(m)


def check_pose(T: np.ndarray, *, what: str = "pose", tol: float = 1e-5) -> np.ndarray:
    """A 4 x 4 rigid transform as float64, or :class:`GeometryError` naming what is wrong."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise GeometryError(f"{what} must be a 4 x 4 matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise GeometryError(f"{what} has non-finite entries: {M.tolist()}")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0]):
        raise GeometryError(f"{what} has bottom row {M[3].tolist()}; accepted: [0, 0, 0, 1]")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=tol) or np.linalg.det(R) <= 0:
        raise GeometryError(f"{what} rotation {R.tolist()} is not orthonormal with determinant +1")
    return M


def pose_from_parts(translation: ArrayLike, q_xyzw: ArrayLike) -> np.ndarray:
    """Translation (3) + quaternion (x, y, z, w) -> 4 x 4 pose."""
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q_xyzw)
    T[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return T


def pose_to_parts(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4 x 4 pose -> (translation (3), quaternion (x, y, z, w))."""
    M = check_pose(T)
    return M[:3, 3].copy(), matrix_to_quaternion(M[:3, :3])


def invert_pose(T: np.ndarray) -> np.ndarray:
    M = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions (x, y, z, w; shortest arc); alpha in [0, 1]."""
    return slerp_xyzw(np.asarray(q0, np.float64), np.asarray(q1, np.float64), alpha)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """Pose between ``T0`` (alpha=0) and ``T1`` (alpha=1): linear translation, slerp rotation."""
    if alpha == 0.0:
        return np.array(T0, dtype=np.float64)
    if alpha == 1.0:
        return np.array(T1, dtype=np.float64)
    return interpolate_poses(check_pose(T0), check_pose(T1), alpha)
