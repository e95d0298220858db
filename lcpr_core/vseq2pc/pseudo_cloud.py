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

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import small_gicp

from ..errors import InvalidValueError, VerificationError
from ..geometry import is_rigid, transform_points
from ..verification.clouds import voxel_cap

__all__ = ["BAD_DEPTH", "BAD_INTRINSICS", "DEPTH_SIZE", "INPUT_REASONS", "NO_ODOMETRY", "PseudoCloudConfig",
           "accumulate", "check_pose", "frame_cloud", "fuse_scales", "reason_of"]

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
    fuse: correct each stacked frame's smooth depth-scale error against the other frames' surfaces before
    stacking (:func:`fuse_scales`; needs ``lidar_T_cam`` in :func:`accumulate`): a depth network's error is
    independent between frames, the frames see the same surfaces.
    fuse_iterations / fuse_radius / fuse_cell: rounds of that correction; how far (m) the other frames' surface
    may lie from a point; the angle (rad, in the image plane) over which a frame's scale is smoothed (0.09: about
    the 32 px correlation of citysim's depth error at the KITTI rig's focal length). Off by default: on the
    validation drive (citysim seed 43) it lifts few loops at 5-10 % depth error for about 1 s more per query
    (docs/vseq2pc_verification.md, What was tried); 2 rounds, 1.5 m and 0.09 rad against 4 rounds, 3 m, 0.05 or
    0.2 rad on 15 of that drive's queries' cloud error.
    """

    min_depth: float = 1.0
    max_depth: float = 25.0
    voxel: float = 0.2
    max_points: int = 6000
    max_frames: int = 12
    stride: int = 2
    fuse: bool = False
    fuse_iterations: int = 2
    fuse_radius: float = 1.5
    fuse_cell: float = 0.09

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_depth < self.max_depth:
            raise InvalidValueError(f"verify.min_depth={self.min_depth!r}, verify.max_depth={self.max_depth!r}; "
                                    "accepted: 0 <= min_depth < max_depth")
        if not self.voxel > 0:
            raise InvalidValueError(f"verify.voxel={self.voxel!r}; it must be > 0 (m)")
        if not (self.fuse_radius > 0 and self.fuse_cell > 0):
            raise InvalidValueError(f"verify.fuse_radius={self.fuse_radius!r}, verify.fuse_cell={self.fuse_cell!r}; "
                                    "both must be > 0")
        for name in ("max_points", "max_frames", "stride", "fuse_iterations"):
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
               config: PseudoCloudConfig | None = None, lidar_T_cam: np.ndarray | None = None) -> np.ndarray:
    """Frames' clouds (M_i x 3, each in its vehicle frame) with their world_T_base poses -> one N x 3 cloud
    in the query's vehicle frame (float64), at most ``max_frames`` frames (evenly spaced, the first kept).
    With ``config.fuse`` and ``lidar_T_cam`` each frame's depth-scale error is corrected first (:func:`fuse_scales`)."""
    cfg = config if config is not None else PseudoCloudConfig()
    q_inv = np.linalg.inv(check_pose(query_pose, "the query frame's pose"))
    picks = np.unique(np.linspace(0, len(frames) - 1, min(cfg.max_frames, len(frames))).round().astype(np.int64))
    parts, cams = [], []
    for i in picks.tolist() if len(frames) else []:
        cloud, pose = frames[i]
        T = q_inv @ check_pose(pose, f"frame {i}'s pose")
        parts.append(transform_points(np.asarray(cloud, np.float64), T))
        if lidar_T_cam is not None:
            cams.append(T @ np.asarray(lidar_T_cam, np.float64).reshape(4, 4))
    if cfg.fuse and len(cams) >= 2:
        parts = fuse_scales(parts, cams, config=cfg)
    return np.concatenate(parts) if parts else np.zeros((0, 3))


FUSE_SAMPLE = 1500  # points per frame the depth-scale correction is estimated on


def _planes(points: np.ndarray, tree: small_gicp.KdTree) -> tuple[np.ndarray, np.ndarray]:
    """Per point of one frame: its local plane's unit normal (M x 3, from its 6 nearest points of the same frame,
    whose error is alike) and whether the neighbourhood is planar (M)."""
    k = 6
    idx, _ = tree.batch_knn_search(points, k, num_threads=1)
    q = points[np.maximum(np.asarray(idx, np.int64), 0)]  # M x k x 3
    d = q - q.mean(axis=1)[:, None, :]
    w, v = np.linalg.eigh(np.einsum("mki,mkj->mij", d, d) / k)
    return v[:, :, 0], w[:, 0] <= 0.2 * w[:, 1]


def _scale_against(points: np.ndarray, centre: np.ndarray, other: np.ndarray, tree: small_gicp.KdTree,
                   planes: tuple[np.ndarray, np.ndarray], radius: float) -> np.ndarray:
    """Per point of one frame: the log of the factor along its camera ray (from ``centre``) that puts it on another
    frame's local plane at its nearest point there; NaN where that frame has no planar point within ``radius``, or
    the ray grazes the plane."""
    idx, sq = tree.batch_knn_search(points, 1, num_threads=1)
    j = np.asarray(idx, np.int64)[:, 0]
    ok = (j >= 0) & (np.asarray(sq)[:, 0] <= radius * radius)
    j = np.maximum(j, 0)
    normal, planar = planes[0][j], planes[1][j] & ok  # M x 3, M
    ray = points - centre  # M x 3
    along = np.einsum("mi,mi->m", normal, ray)
    facing = np.abs(along) >= 0.2 * np.linalg.norm(ray, axis=1)  # the ray meets the plane at more than ~12 deg
    with np.errstate(divide="ignore", invalid="ignore"):
        log_s = np.log(np.einsum("mi,mi->m", normal, other[j] - centre) / along)
    good = planar & facing & np.isfinite(log_s) & (np.abs(log_s) <= 0.4)
    return np.where(good, log_s, np.nan)


def _smooth_in_image(image: np.ndarray, values: np.ndarray, cell: float, *, at: np.ndarray) -> np.ndarray:
    """Per point ``at`` (image-plane coordinates K x 2): the median of the finite ``values`` of the points ``image``
    (M x 2) within ``cell`` of it (of its 16 nearest); the frame's median where none lies that near, 0 where the
    frame has none."""
    good = np.isfinite(values)
    if not good.any():
        return np.zeros(len(at))
    src = np.zeros((int(good.sum()), 3))
    src[:, :2] = image[good]
    flat = np.zeros((len(at), 3))
    flat[:, :2] = at
    tree = small_gicp.KdTree(src, num_threads=1)
    k = int(min(16, good.sum()))
    idx, sq = tree.batch_knn_search(flat, k, num_threads=1)
    idx = np.asarray(idx, np.int64)
    near = (idx >= 0) & (np.asarray(sq) <= cell * cell)
    vals = np.where(near, values[good][np.maximum(idx, 0)], np.nan)
    fallback = float(np.median(values[good]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a row without a near value: all-NaN, the fallback below
        med = np.nanmedian(vals, axis=1)
    return np.where(np.isfinite(med), med, fallback)


def fuse_scales(parts: list[np.ndarray], cameras: list[np.ndarray], *, config: PseudoCloudConfig | None = None
                ) -> list[np.ndarray]:
    """Each frame's cloud (M_i x 3, query frame) with its smooth depth-scale error taken out against the others.

    A depth network's error is a smooth relative error over each image, independent between frames, while the
    stacked frames see the same surfaces. Per round, every point of a frame is moved along its camera ray (camera
    pose ``cameras[i]``, 4 x 4 query_T_cam) by the factor that puts it on the other frames' local plane, weighted
    m / (m + 1) for m other frames there (the mean with its own), with the factor smoothed over ``fuse_cell`` of
    the image; all frames move at once, ``fuse_iterations`` rounds."""
    cfg = config if config is not None else PseudoCloudConfig()
    cur = [np.asarray(p, np.float64) for p in parts]
    centres = [np.asarray(T, np.float64)[:3, 3] for T in cameras]
    images = []
    for p, T in zip(cur, cameras, strict=True):
        cam = (p - T[:3, 3]) @ np.asarray(T, np.float64)[:3, :3]  # M x 3 in the camera's optical frame
        z = np.maximum(cam[:, 2], 1e-6)
        images.append(cam[:, :2] / z[:, None])  # M x 2 normalised image coordinates
    # the scales are estimated on an evenly spaced subset of each frame (at most FUSE_SAMPLE points; cost) and
    # carried to every point through the image-plane smoothing
    picks = [np.linspace(0, len(p) - 1, min(len(p), FUSE_SAMPLE)).round().astype(np.int64) for p in cur]
    for _ in range(cfg.fuse_iterations):
        samples = [np.ascontiguousarray(p[k]) for p, k in zip(cur, picks, strict=True)]
        trees = [small_gicp.KdTree(x, num_threads=1) if len(x) >= 6 else None for x in samples]
        planes = [_planes(x, t) if t is not None else None for x, t in zip(samples, trees, strict=True)]
        nxt = []
        for i, p in enumerate(cur):
            per_frame = [_scale_against(samples[i], centres[i], samples[j], tree, plane, cfg.fuse_radius)
                         for j, (tree, plane) in enumerate(zip(trees, planes, strict=True))
                         if j != i and tree is not None and plane is not None]
            if len(p) == 0 or not per_frame:
                nxt.append(p)
                continue
            seen = np.stack(per_frame)  # F x M: each other frame's factor
            count = np.isfinite(seen).sum(axis=0)
            # the mean over this frame (factor 1) and the others that see the surface; NaN where none does
            mean = np.where(count > 0, np.nansum(seen, axis=0) / (count + 1.0), np.nan)
            smooth = _smooth_in_image(images[i][picks[i]], mean, cfg.fuse_cell, at=images[i])
            nxt.append(centres[i] + np.exp(smooth)[:, None] * (p - centres[i]))
        cur = nxt
    return cur
