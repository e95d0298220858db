"""RINet-style structure features of labelled points (VSeq2PC), LiDAR slices and camera points."""
from __future__ import annotations

import numpy as np

from ..errors import InputShapeError

#: The 12 semantic channels, in order, with the SemanticKITTI ids each one takes.
CLASSES: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("car", (10, 252)),
    ("road", (40, 60)),  # 60: lane-marking
    ("parking", (44,)),
    ("sidewalk", (48,)),
    ("other-ground", (49,)),
    ("building", (50,)),
    ("fence", (51,)),
    ("vegetation", (70,)),
    ("trunk", (71,)),
    ("terrain", (72,)),
    ("pole", (80,)),
    ("traffic-sign", (81,)),
)
ROAD_CHANNEL = 1  # keeps the largest range; every other class the smallest
SECTORS = 360
MAX_RANGE = 50.0
CAMERA_SECTORS = slice(135, 225)  # the forward 90 degrees (+x is sector 180)

_CHANNEL_OF = np.full(1 << 16, -1, dtype=np.int64)
for _channel, (_, _ids) in enumerate(CLASSES):
    _CHANNEL_OF[list(_ids)] = _channel

#: Cityscapes train ids -> SemanticKITTI ids, for label images from Cityscapes-trained
#: segmenters. Choices where Cityscapes has no SemanticKITTI twin: wall -> other-structure
#: (52, not a feature class), traffic light -> traffic-sign (81), sky -> unlabelled (0).
CITYSCAPES_TO_SEMANTICKITTI = np.array(
    [40, 48, 50, 52, 51, 80, 81, 81, 70, 72, 0, 30, 31, 10, 18, 13, 16, 15, 11], dtype=np.uint32
)


def cityscapes_to_semantickitti(train_ids: np.ndarray) -> np.ndarray:
    """Cityscapes train ids (0..18; 255 = ignore) -> SemanticKITTI ids (0 = unlabelled)."""
    ids = np.asarray(train_ids).astype(np.int64)
    out = np.zeros(ids.shape, dtype=np.uint32)
    valid = (ids >= 0) & (ids < len(CITYSCAPES_TO_SEMANTICKITTI))
    out[valid] = CITYSCAPES_TO_SEMANTICKITTI[ids[valid]]
    return out


def structure_feature(points: np.ndarray, labels: np.ndarray, *, max_range: float = MAX_RANGE) -> np.ndarray:
    """N x (>=3) points (LiDAR frame, x forward) and N SemanticKITTI labels -> 12 x 360 float32 in [0, 1].

    Cell (class, sector): the smallest horizontal range of that class in that
    1-degree sector (road: the largest), divided by ``max_range``; 0 when empty.
    Labels may carry an instance id in their upper 16 bits.
    """
    pts = np.asarray(points)
    lab = np.asarray(labels)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise InputShapeError(f"points have shape {pts.shape}; expected N x 3 or more columns")
    if lab.shape != (len(pts),):
        raise InputShapeError(f"labels have shape {lab.shape}; expected ({len(pts)},), one per point")
    x, y = pts[:, 0].astype(np.float64), pts[:, 1].astype(np.float64)
    channel = _CHANNEL_OF[lab.astype(np.int64) & 0xFFFF]
    r = np.hypot(x, y)
    keep = (channel >= 0) & (r <= max_range) & np.isfinite(r)
    x, y, r, channel = x[keep], y[keep], r[keep], channel[keep]
    sector = np.floor((np.arctan2(y, x) + np.pi) * 180.0 / np.pi).astype(np.int64) % SECTORS

    feature: np.ndarray = np.full(len(CLASSES) * SECTORS, np.inf)
    cell = channel * SECTORS + sector
    road = channel == ROAD_CHANNEL
    np.minimum.at(feature, cell[~road], r[~road])
    feature = feature.reshape(len(CLASSES), SECTORS)
    road_max = np.full(SECTORS, -np.inf)
    np.maximum.at(road_max, sector[road], r[road])
    feature[ROAD_CHANNEL] = road_max
    feature[~np.isfinite(feature)] = 0.0
    return (feature / max_range).astype(np.float32)


def lidar_slices(feature: np.ndarray, *, count: int = 8) -> np.ndarray:
    """12 x 360 -> count x 12 x 360: slice s is the 90-degree window starting at sector
    135 + s * 360/count, rolled to sectors 135..224, zeros elsewhere."""
    f = np.asarray(feature)
    if f.ndim != 2 or f.shape[1] != SECTORS:
        raise InputShapeError(f"feature has shape {f.shape}; expected C x {SECTORS}")
    step = SECTORS // count
    out = np.zeros((count, *f.shape), dtype=f.dtype)
    for s in range(count):
        out[s, :, CAMERA_SECTORS] = np.roll(f, -step * s, axis=1)[:, CAMERA_SECTORS]
    return out


def camera_points(
    depth: np.ndarray, labels: np.ndarray, K: np.ndarray, lidar_T_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Metric depth (H x W, m; 0 or non-finite = none) + labels (H x W) -> LiDAR-frame points and labels.

    Pixels are back-projected with the pinhole intrinsics K (optical frame: z forward,
    x right, y down) and moved into the LiDAR frame with the 4 x 4 ``lidar_T_cam``.
    """
    d = np.asarray(depth, dtype=np.float64)
    lab = np.asarray(labels)
    if d.ndim != 2 or lab.shape != d.shape:
        raise InputShapeError(f"depth {d.shape} and labels {lab.shape} must be the same H x W")
    v, u = np.nonzero(np.isfinite(d) & (d > 0) & (lab != 0))
    z = d[v, u]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cam = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z, np.ones_like(z)], axis=0)  # 4 x N
    pts = (np.asarray(lidar_T_cam, dtype=np.float64) @ cam)[:3].T
    return pts, lab[v, u]


def camera_feature(
    depth: np.ndarray, labels: np.ndarray, K: np.ndarray, lidar_T_cam: np.ndarray
) -> np.ndarray:
    """One camera frame -> its forward 90-degree structure feature, 12 x 90."""
    return structure_feature(*camera_points(depth, labels, K, lidar_T_cam))[:, CAMERA_SECTORS]


def sequence_indices(
    positions: np.ndarray, query: int, *, offsets: tuple[float, ...] = (5.0, 10.0, 15.0)
) -> list[int] | None:
    """The query frame and the first frames at least each offset (m) further along the path.

    positions: N x 2|3 in driving order. Returns None while the drive has not yet gone far enough.
    """
    pos = np.asarray(positions, dtype=np.float64)
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    rel = travelled[query:] - travelled[query]
    picks = [query]
    for offset in offsets:
        after = np.nonzero(rel >= offset)[0]
        if not len(after):
            return None
        picks.append(query + int(after[0]))
    return picks
