"""Sensor rigs: a nuScenes-like (six cameras + 32-beam LiDAR) and a KITTI-like (front camera + 64 beams).

``base_link`` is REP-103 (x forward, y left, z up). The nuScenes-like base sits on the ground
under the rear axle, LIDAR_TOP (x right, y forward, z up) 1.84 m up, as in nuScenes.
The KITTI-like base is the Velodyne frame itself (x forward, y left, z up, 1.73 m up), as
the KITTI converter writes it. Cameras are level (the 2.5-D renderer needs that).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msg_tools.frames import KITTI_TOPICS, NUSCENES_CAMERAS, NUSCENES_TOPICS, CameraModel, Topics

RIGS = ("nuscenes", "kitti")


@dataclass(frozen=True)
class LidarModel:
    """A spinning LiDAR: beam elevations (top first), azimuth steps, range limits and noise."""

    frame_id: str
    elevations_deg: tuple[float, ...]  # row 0 = top beam; ring = rows - 1 - row (ring 0 = lowest)
    azimuth_steps: int
    base_T_lidar: np.ndarray  # 4 x 4, must be level (z up)
    max_range: float = 100.0
    min_range: float = 1.0
    range_noise: float = 0.02  # metres (1 sigma) at short range
    intensity_max: float = 255.0  # nuScenes 0..255, KITTI reflectance 0..1


@dataclass(frozen=True)
class Rig:
    """Cameras, LiDAR and bag topics of one synthetic vehicle."""

    name: str
    cameras: tuple[CameraModel, ...]
    lidar: LidarModel
    topics: Topics
    jpeg: bool  # cameras stored as JPEG bytes (else raw rgb)
    depth_and_labels: bool  # cameras carry metric depth and label images
    default_spacing: float  # metres between keyframes


def pose_matrix(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """4 x 4 transform: rotation yaw about z, then translation (x, y, z)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, z)
    return T


def level_camera(name: str, frame_id: str, *, width: int, height: int, hfov_deg: float, xyz: tuple[float, float, float],
                 yaw_deg: float) -> CameraModel:
    """A level pinhole camera with square pixels, looking along yaw (degrees, CCW from base x)."""
    fx = (width / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
    K = np.array([[fx, 0.0, (width - 1) / 2], [0.0, fx, (height - 1) / 2], [0.0, 0.0, 1.0]])
    yaw = np.deg2rad(yaw_deg)
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([right, [0.0, 0.0, -1.0], fwd], axis=1)  # columns: optical x, y, z in base
    T[:3, 3] = xyz
    return CameraModel(name=name, frame_id=frame_id, width=width, height=height, K=K, base_T_cam=T)


# nuScenes-like mounting: (yaw deg, hfov deg, position in base_link)
_NUSCENES_MOUNTS = {
    "CAM_FRONT": (0.0, 70.0, (1.70, 0.00, 1.51)),
    "CAM_FRONT_RIGHT": (-55.0, 70.0, (1.55, -0.49, 1.50)),
    "CAM_BACK_RIGHT": (-110.0, 70.0, (1.03, -0.48, 1.59)),
    "CAM_BACK": (180.0, 110.0, (0.03, 0.00, 1.57)),
    "CAM_BACK_LEFT": (110.0, 70.0, (1.05, 0.48, 1.57)),
    "CAM_FRONT_LEFT": (55.0, 70.0, (1.52, 0.49, 1.51)),
}


def nuscenes_rig(*, image_size: tuple[int, int] = (800, 450), azimuth_steps: int = 1088) -> Rig:
    """Six level cameras (nuScenes yaws, 70 deg, back 110 deg) and a 32-beam LIDAR_TOP (+10..-30 deg)."""
    width, height = image_size
    cams = tuple(level_camera(n, n, width=width, height=height, hfov_deg=_NUSCENES_MOUNTS[n][1],
                              xyz=_NUSCENES_MOUNTS[n][2], yaw_deg=_NUSCENES_MOUNTS[n][0]) for n in NUSCENES_CAMERAS)
    base_T_lidar = np.eye(4)
    base_T_lidar[:3, :3] = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # lidar x = base -y, y = base x
    base_T_lidar[:3, 3] = (0.94, 0.0, 1.84)
    # beams at the centres of the 32 rows of LCPR's range image (+10..-30 deg)
    elevations = tuple(float(e) for e in 10.0 - (np.arange(32) + 0.5) * 40.0 / 32)
    lidar = LidarModel("LIDAR_TOP", elevations, azimuth_steps, base_T_lidar, max_range=100.0, intensity_max=255.0)
    return Rig("nuscenes", cams, lidar, NUSCENES_TOPICS, jpeg=True, depth_and_labels=False, default_spacing=5.0)


def kitti_rig(*, image_size: tuple[int, int] = (1241, 376), azimuth_steps: int = 2000) -> Rig:
    """A front colour camera (KITTI image_2 geometry, depth + labels) and a 64-beam Velodyne (+2..-24.8 deg)."""
    width, height = image_size
    fx = 718.856 * width / 1241.0
    cam = CameraModel(
        name="camera_left", frame_id="camera_left", width=width, height=height,
        K=np.array([[fx, 0.0, (width - 1) / 2], [0.0, fx, 185.2 * height / 376.0], [0.0, 0.0, 1.0]]),
        base_T_cam=level_camera("", "", width=1, height=1, hfov_deg=90.0, xyz=(0.27, 0.06, -0.08),
                                yaw_deg=0.0).base_T_cam,
    )
    elevations = tuple(float(e) for e in np.linspace(2.0, -24.8, 64))
    lidar = LidarModel("velodyne", elevations, azimuth_steps, np.eye(4), max_range=100.0, intensity_max=1.0)
    return Rig("kitti", (cam,), lidar, KITTI_TOPICS, jpeg=False, depth_and_labels=True, default_spacing=1.0)


#: height of base_link above the ground
BASE_HEIGHT = {"nuscenes": 0.0, "kitti": 1.73}


def make_rig(name: str, *, image_size: tuple[int, int] | None = None) -> Rig:
    """The rig called ``name`` ('nuscenes' or 'kitti'); image_size = (width, height) overrides the default."""
    if name not in RIGS:
        raise ValueError(f"unknown rig {name!r}; accepted: {', '.join(RIGS)}")
    if image_size is not None:
        w, h = image_size
        if w < 16 or h < 16:
            raise ValueError(f"image size {w}x{h}; both sides must be at least 16 pixels")
    if name == "nuscenes":
        return nuscenes_rig() if image_size is None else nuscenes_rig(image_size=image_size)
    return kitti_rig() if image_size is None else kitti_rig(image_size=image_size)


def check_level(T: np.ndarray, what: str, *, optical: bool) -> float:
    """Yaw (radians) of a level sensor's forward axis in base_link; ValueError if it is tilted."""
    R = np.asarray(T)[:3, :3]
    up = -R[:, 1] if optical else R[:, 2]
    if not np.allclose(up, (0.0, 0.0, 1.0), atol=1e-6):
        raise ValueError(f"{what} is not level (its up axis is {np.round(up, 4).tolist()}); the 2.5-D renderer "
                         "needs level sensors")
    fwd = R[:, 2] if optical else R[:, 0]
    return float(np.arctan2(fwd[1], fwd[0]))
