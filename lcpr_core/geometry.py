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


def invert(pose: np.ndarray) -> np.ndarray:
    """The inverse of a rigid (4, 4) transform, or of each in a (..., 4, 4) stack: ``(R^T, -R^T t)``."""
    m = np.asarray(pose, np.float64)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    out = np.zeros_like(m)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ m[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


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


def skew(w: np.ndarray) -> np.ndarray:
    """The (3, 3) cross-product matrix of ``w`` (3,): ``skew(w) @ v = w x v``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


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


def quaternions_xyzw(rotations: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w; w >= 0, as geometry_msgs orders them) of (..., 3, 3) rotations.

    Shepperd's method, each matrix through its largest component, so no branch divides by a small number.
    A NaN matrix gives a NaN quaternion.
    """
    r = np.asarray(rotations, np.float64)
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    squares = np.stack([1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22, 1 + r00 + r11 + r22],
                       axis=-1) / 4.0  # x^2, y^2, z^2, w^2
    a, b, c = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]  # 4w(x, y, z)
    d, e, f = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]  # 4xy, 4xz, 4yz
    k = np.argmax(np.nan_to_num(squares, nan=-1.0), axis=-1)
    big = 4.0 * np.take_along_axis(squares, k[..., None], -1)[..., 0]  # each branch is 4 q_k (x, y, z, w)
    with np.errstate(invalid="ignore"):
        branches = np.stack([np.stack([big, d, e, a], -1), np.stack([d, big, f, b], -1),
                             np.stack([e, f, big, c], -1), np.stack([a, b, c, big], -1)], axis=-2)
        q = np.take_along_axis(branches, k[..., None, None], -2)[..., 0, :]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0, -q, q)


def rotations_from_xyzw(quaternions: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations of (..., 4) unit quaternions (x, y, z, w); NaN in, NaN out."""
    q = np.asarray(quaternions, np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
