"""SE(3) and rotation math on numpy arrays, the one home for what verification, the pose graph and the
evaluation compute on poses.

Poses are 4 x 4 homogeneous matrices ``a_T_b`` (frame ``b`` expressed in frame ``a``), rotations
3 x 3 matrices, rotation vectors (3,) in radians. Nothing here checks its input: the callers
validate with their own errors (:mod:`lcpr_core.posegraph`, :mod:`lcpr_core.verification`) and
then compute here.
"""
from __future__ import annotations

import math

import numpy as np

from lcpr_common.rotations import interpolate_poses as interpolate_poses  # re-exported: the core's one home
from lcpr_common.rotations import quaternions_xyzw as quaternions_xyzw
from lcpr_common.rotations import rotations_from_xyzw as rotations_from_xyzw


def invert(pose: np.ndarray) -> np.ndarray:
    """The inverse of a rigid (4, 4) transform, or of each in a (..., 4, 4) stack: ``(R^T, -R^T t)``."""
    m = np.asarray(pose, np.float64)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    out = np.zeros_like(m)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ m[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def is_rigid(pose: np.ndarray, *, atol: float = 1e-3) -> bool:
    """Whether ``pose`` is a finite 4 x 4 rigid transform: an orthonormal right-handed rotation, last row 0 0 0 1."""
    T = np.asarray(pose)
    if T.shape != (4, 4) or not np.issubdtype(T.dtype, np.number) or not np.isfinite(T).all():
        return False
    R = T[:3, :3].astype(np.float64)
    return bool(np.abs(R.T @ R - np.eye(3)).max() < atol and np.linalg.det(R) > 0
                and np.allclose(T[3], (0.0, 0.0, 0.0, 1.0)))


def relative(a_T_x: np.ndarray, a_T_y: np.ndarray) -> np.ndarray:
    """``x_T_y = inv(a_T_x) @ a_T_y``: pose ``y`` seen from pose ``x`` (both given in frame ``a``)."""
    return invert(a_T_x) @ np.asarray(a_T_y, np.float64)


def conjugate(a_T_b: np.ndarray, b_pose: np.ndarray) -> np.ndarray:
    """A relative pose between two ``b`` frames as the one between their ``a`` frames: ``a_T_b X inv(a_T_b)``."""
    ext = np.asarray(a_T_b, np.float64)
    return ext @ np.asarray(b_pose, np.float64) @ invert(ext)


def transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N, 3) points moved by ``pose`` (4, 4): ``R p + t`` for each row."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def wrap_angle(angle: float) -> float:
    """An angle in radians brought into [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def skew(w: np.ndarray) -> np.ndarray:
    """The (3, 3) cross-product matrix of ``w`` (3,): ``skew(w) @ v = w x v``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def unit_vector(value: object) -> np.ndarray | None:
    """``value`` as a (3,) unit vector, or None when it is not a finite non-zero 3-vector (the caller says why)."""
    try:
        vec = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return None
    if vec.shape != (3,) or not np.isfinite(vec).all():
        return None
    norm = float(np.linalg.norm(vec))
    return vec / norm if norm >= 1e-9 else None


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (3,) (Rodrigues)."""
    theta = float(np.linalg.norm(w))
    k = skew(w)
    if theta < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(theta) / theta * k + (1.0 - math.cos(theta)) / theta**2 * (k @ k)


def pose_from_xyz_rpy(xyz: tuple[float, ...], rpy: tuple[float, ...]) -> np.ndarray:
    """4 x 4 from a translation and roll, pitch, yaw in radians (R = Rz Ry Rx, as URDF and tf2)."""
    roll, pitch, yaw = rpy
    out = np.eye(4)
    out[:3, :3] = so3_exp(np.array([0.0, 0.0, yaw])) @ so3_exp(np.array([0.0, pitch, 0.0])) \
        @ so3_exp(np.array([roll, 0.0, 0.0]))
    out[:3, 3] = xyz
    return out


def xyz_rpy_from_pose(pose: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Translation and roll, pitch, yaw (rad) of a 4 x 4 pose: the inverse of :func:`pose_from_xyz_rpy`
    (pitch in [-90, 90] deg; at +-90 deg the roll and yaw split of a rotation is not unique)."""
    r = np.asarray(pose, np.float64)[:3, :3]
    pitch = math.asin(max(-1.0, min(1.0, -float(r[2, 0]))))
    if abs(float(r[2, 0])) < 1.0 - 1e-12:
        roll, yaw = math.atan2(float(r[2, 1]), float(r[2, 2])), math.atan2(float(r[1, 0]), float(r[0, 0]))
    else:  # gimbal lock: all of the turn about z is put in yaw
        roll, yaw = 0.0, math.atan2(-float(r[0, 1]), float(r[1, 1]))
    x, y, z = (float(v) for v in np.asarray(pose, np.float64)[:3, 3])
    return (x, y, z), (roll, pitch, yaw)


def nearest_rotation(r: np.ndarray) -> np.ndarray:
    """The rotation matrix nearest ``r`` (3, 3) (SVD projection): removes round-off before a solver sees it."""
    u, _, vt = np.linalg.svd(r)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle_deg(rotation: np.ndarray) -> np.ndarray:
    """Angle (deg, 0..180) of ... x 3 x 3 rotation matrices (a float for one): |log(R)|."""
    r = np.asarray(rotation, np.float64)
    return np.degrees(np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))


def heading_deg(rotation: np.ndarray) -> float:
    """Heading (deg, -180..180] of a (3, 3) rotation or (4, 4) pose: ``atan2(R[1, 0], R[0, 0])``."""
    m = np.asarray(rotation, np.float64)
    return math.degrees(math.atan2(m[1, 0], m[0, 0]))


def umeyama_rigid(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3, 3) and translation (3,) minimising |R source + t - target|^2 over (N, 3) points (no scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    u, _, vt = np.linalg.svd(cov)
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    rot = u @ s @ vt
    return rot, mu_t - rot @ mu_s
