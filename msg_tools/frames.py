"""Sensor data in numpy form, as the bag tools, converters and the synthetic city exchange it.

A :class:`SensorFrame` is one synchronised multi-sensor sample: camera images, one
LiDAR cloud and, when known, the vehicle pose. Everything that makes bags (dataset
converters, the synthetic city) produces these; everything that reads bags returns
them; ``lcpr_core`` consumes their arrays without knowing about ROS.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import ImageError

#: nuScenes camera order, which is also LCPR's panorama order.
NUSCENES_CAMERAS = (
    "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT",
)


@dataclass(frozen=True)
class Topics:
    """Topic names of one rig in a bag. Camera topics follow ``cameras`` order."""

    cameras: tuple[str, ...]
    lidar: str
    odom: str = "/odom"
    camera_info: tuple[str, ...] = ()
    depth: tuple[str, ...] = ()  # metric depth images (KITTI-like rig), same order as cameras
    labels: tuple[str, ...] = ()  # SemanticKITTI label images, same order as cameras
    tf_static: str = "/tf_static"


NUSCENES_TOPICS = Topics(
    cameras=tuple(f"/{c}/image/compressed" for c in NUSCENES_CAMERAS),
    camera_info=tuple(f"/{c}/camera_info" for c in NUSCENES_CAMERAS),
    lidar="/LIDAR_TOP/points",
)

KITTI_TOPICS = Topics(
    cameras=("/kitti/camera_left/image",),
    camera_info=("/kitti/camera_left/camera_info",),
    depth=("/kitti/camera_left/depth",),
    labels=("/kitti/camera_left/labels",),
    lidar="/kitti/velodyne/points",
)


@dataclass
class CameraImage:
    """One camera image: exactly one of ``rgb`` (H x W x 3 uint8) or ``jpeg`` (encoded bytes)."""

    stamp: float  # header stamp, seconds
    frame_id: str
    rgb: np.ndarray | None = None
    jpeg: bytes | None = None
    depth: np.ndarray | None = None  # H x W float32 metres, 0 = unknown (KITTI-like rig)
    labels: np.ndarray | None = None  # H x W uint16/uint32 SemanticKITTI ids (KITTI-like rig)

    def __post_init__(self) -> None:
        if (self.rgb is None) == (self.jpeg is None):
            raise ImageError(f"a CameraImage holds exactly one of rgb or jpeg; got rgb {self.rgb is not None}, "
                             f"jpeg {self.jpeg is not None}")


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics and the camera's pose in the vehicle (base_link) frame."""

    name: str
    frame_id: str
    width: int
    height: int
    K: np.ndarray  # 3 x 3
    base_T_cam: np.ndarray  # 4 x 4, optical frame (z forward, x right, y down)


@dataclass
class SensorFrame:
    """One synchronised sample of a rig."""

    stamp: float  # the LiDAR's header stamp, seconds
    cameras: list[CameraImage | None]  # rig order; None = no image within the slop
    cloud: np.ndarray  # structured: x, y, z, intensity float32 (+ ring uint16, label uint32)
    lidar_frame_id: str = "lidar"
    pose: np.ndarray | None = None  # 4 x 4 world_T_base at ``stamp``, or None
    extras: dict[str, object] = field(default_factory=dict)

    @property
    def xyz(self) -> np.ndarray:
        """N x 3 float64 point coordinates."""
        out = np.empty((len(self.cloud), 3))  # filled column by column: 5x faster than stacking the fields
        for k, name in enumerate("xyz"):
            out[:, k] = self.cloud[name]
        return out
