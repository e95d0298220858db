"""Sensor data -> model inputs."""
from .camera import IMAGENET_MEAN, IMAGENET_STD, NUSCENES_CAMERAS, camera_tensor, cameras_tensor, decode_image
from .range_image import CUSTOM, PRESETS, LidarGeometry, LidarPreset, lidar_preset, range_image

__all__ = [
    "CUSTOM", "IMAGENET_MEAN", "IMAGENET_STD", "NUSCENES_CAMERAS", "PRESETS", "LidarGeometry", "LidarPreset",
    "camera_tensor", "cameras_tensor", "decode_image", "lidar_preset", "range_image",
]
