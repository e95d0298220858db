"""Pseudo-clouds of a camera sequence: depth back-projected with K, accumulated with odometry.

A VSeq2PC query is a camera sequence (the query frame and the frames up to 15 m further on). Its
frames' metric depth (a depth network's, or exact), back-projected with the pinhole intrinsics and
moved into the vehicle frame with ``lidar_T_cam``, then stacked into the query frame's vehicle frame
with the frames' odometry poses, make a cloud the project's LiDAR verifier can register against a
map scan::

    cloud = frame_cloud(depth, K, lidar_T_cam)                 # per frame: M x 3 in its vehicle frame
    pseudo = accumulate([(cloud, world_T_base), ...], query_pose=world_T_base_q)   # query vehicle frame

The vehicle frame is the one ``lidar_T_cam`` maps into (what :func:`~lcpr_core.vseq2pc.preprocess.camera_points`
uses); poses are world_T_base of that frame. Bad input raises :class:`~lcpr_core.errors.VerificationError`
whose message starts with one of :data:`INPUT_REASONS` (:func:`reason_of`; counted by the detector, never
raised out of it).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidValueError, VerificationError
from ..geometry import is_rigid, transform_points
from ..verification.clouds import voxel_cap

__all__ = ["BAD_DEPTH", "BAD_INTRINSICS", "DEPTH_SIZE", "INPUT_REASONS", "NO_ODOMETRY", "PseudoCloudConfig",
           "accumulate", "check_pose", "frame_cloud", "reason_of"]

BAD_DEPTH = "bad depth"  # no finite positive depth in range (all NaN, zeros, negative)
DEPTH_SIZE = "depth size"  # depth not H x W, or not the labels' size
BAD_INTRINSICS = "bad intrinsics"  # K not 3 x 3 pinhole, or its principal point not near the image centre
NO_ODOMETRY = "no odometry"  # a frame's pose is missing, not finite, a position only, or not rigid
INPUT_REASONS: tuple[str, ...] = (BAD_DEPTH, DEPTH_SIZE, BAD_INTRINSICS, NO_ODOMETRY)


def _refused(reason: str, detail: str) -> VerificationError:
    """The error for a frame the pseudo-cloud cannot use: its message starts with the reason (:func:`reason_of`)."""
    return VerificationError(f"{reason}: {detail}")


def reason_of(err: VerificationError) -> str:
    """Which of INPUT_REASONS a refusal of this module names ("failed" for any other error)."""
    head = str(err).split(":", 1)[0]
    return head if head in INPUT_REASONS else "failed"


@dataclass(frozen=True)
class PseudoCloudConfig:
    """How camera frames become a cloud.

    min_depth / max_depth: pixels nearer / farther along the optical axis are left out (a depth
    network's error grows with range; 25 m is where citysim's network-like depth stops).
    voxel: each frame is voxel-downsampled to this (centroids) before it is kept.
    max_points: cap per frame after voxelisation (evenly spaced subset): a kept frame costs
    12 * max_points bytes at most (float32 x, y, z).
    max_frames: frames of one sequence stacked at most (evenly spaced, the query frame always).
    stride: every stride-th pixel row and column is back-projected (speed; the voxel grid is coarser).
    """

    min_depth: float = 1.0
    max_depth: float = 25.0
    voxel: float = 0.2
    max_points: int = 6000
    max_frames: int = 12
    stride: int = 2

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_depth < self.max_depth:
            raise InvalidValueError(f"verify.min_depth={self.min_depth!r}, verify.max_depth={self.max_depth!r}; "
                                    "accepted: 0 <= min_depth < max_depth")
        if not self.voxel > 0:
            raise InvalidValueError(f"verify.voxel={self.voxel!r}; it must be > 0 (m)")
        for name in ("max_points", "max_frames", "stride"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InvalidValueError(f"verify.{name}={value!r}; it must be a positive integer")


def check_pose(pose: object, what: str = "pose") -> np.ndarray:
    """A finite rigid 4 x 4 world_T_base, or VerificationError naming NO_ODOMETRY."""
    if pose is None:
        raise _refused(NO_ODOMETRY, f"{what} is None; a 4 x 4 odometry pose is needed")
    T = np.asarray(pose, np.float64)
    if T.shape != (4, 4):
        raise _refused(NO_ODOMETRY, f"{what} has shape {T.shape}; a 4 x 4 world_T_base is needed "
                                                 "(a position alone has no orientation)")
    if not is_rigid(T):
        raise _refused(NO_ODOMETRY, f"{what} is not a finite rigid transform")
    return T


def _check_intrinsics(K: object, width: int, height: int) -> np.ndarray:
    try:
        k = np.asarray(K, np.float64)
    except (TypeError, ValueError):
        raise _refused(BAD_INTRINSICS, f"K={K!r} is not a 3 x 3 array of numbers") from None
    if k.shape != (3, 3) or not np.isfinite(k).all():
        raise _refused(BAD_INTRINSICS, f"K of shape {k.shape}; expected a finite 3 x 3 pinhole matrix")
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    if not (fx > 0 and fy > 0):
        raise _refused(BAD_INTRINSICS, f"K has fx={fx:g}, fy={fy:g}; both must be > 0")
    if not (0.25 * width <= cx <= 0.75 * width and 0.25 * height <= cy <= 0.75 * height):
        raise _refused(BAD_INTRINSICS, f"K's principal point ({cx:g}, {cy:g}) is not in the middle half "
                                                    f"of the {width} x {height} image (accepted: cx in "
                                                    f"[{0.25 * width:g}, {0.75 * width:g}], cy in [{0.25 * height:g}, "
                                                    f"{0.75 * height:g}]): K does not belong to this image")
    return k


def frame_cloud(depth: object, K: object, lidar_T_cam: np.ndarray, *, labels: np.ndarray | None = None,
                config: PseudoCloudConfig | None = None) -> np.ndarray:
    """One frame's depth (H x W metres; 0 or non-finite = none) -> M x 3 float32 points in its vehicle frame.

    Pixels with label 0 (unlabelled, sky) are left out when ``labels`` is given. Raises
    VerificationError (bad depth, depth size, bad intrinsics: :func:`reason_of`) when the frame gives no cloud.
    """
    cfg = config if config is not None else PseudoCloudConfig()
    try:
        d = np.asarray(depth, np.float32)
    except (TypeError, ValueError):
        raise _refused(DEPTH_SIZE, f"depth {type(depth).__name__} is not an array of numbers") from None
    if d.ndim != 2 or min(d.shape) < 2:
        raise _refused(DEPTH_SIZE, f"depth of shape {d.shape}; expected an H x W image")
    if labels is not None and np.shape(labels) != d.shape:
        raise _refused(DEPTH_SIZE, f"depth {d.shape} and labels {np.shape(labels)} differ in size")
    k = _check_intrinsics(K, d.shape[1], d.shape[0])
    s = cfg.stride
    sub = d[::s, ::s]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(sub) & (sub >= cfg.min_depth) & (sub <= cfg.max_depth)
    if labels is not None:
        ok &= np.asarray(labels)[::s, ::s] != 0
    v, u = np.nonzero(ok)
    if len(v) == 0:
        raise _refused(BAD_DEPTH, f"no pixel of the {d.shape[1]} x {d.shape[0]} depth image holds a "
                                               f"finite depth in [{cfg.min_depth:g}, {cfg.max_depth:g}] m")
    z = sub[v, u].astype(np.float64)
    u, v = u * s, v * s
    cam = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=1)  # N x 3 optical frame
    pts = transform_points(cam, np.asarray(lidar_T_cam, np.float64))
    return np.asarray(voxel_cap(pts, cfg.voxel, cfg.max_points), np.float32)


def accumulate(frames: Sequence[tuple[np.ndarray, np.ndarray]], *, query_pose: np.ndarray,
               config: PseudoCloudConfig | None = None) -> np.ndarray:
    """Frames' clouds (M_i x 3, each in its vehicle frame) with their world_T_base poses -> one N x 3 cloud
    in the query's vehicle frame (float64), at most ``max_frames`` frames (evenly spaced, the first kept)."""
    cfg = config if config is not None else PseudoCloudConfig()
    q_inv = np.linalg.inv(check_pose(query_pose, "the query frame's pose"))
    picks = np.unique(np.linspace(0, len(frames) - 1, min(cfg.max_frames, len(frames))).round().astype(np.int64))
    parts = []
    for i in picks.tolist() if len(frames) else []:
        cloud, pose = frames[i]
        T = q_inv @ check_pose(pose, f"frame {i}'s pose")
        parts.append(transform_points(np.asarray(cloud, np.float64), T))
    return np.concatenate(parts) if parts else np.zeros((0, 3))

