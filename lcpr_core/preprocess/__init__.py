"""Sensor data -> model inputs."""
from .camera import IMAGENET_MEAN, IMAGENET_STD, NUSCENES_CAMERAS, camera_tensor, cameras_tensor, decode_image
from .range_image import PRESETS, LidarPreset, lidar_preset, range_image

__all__ = [
    "IMAGENET_MEAN", "IMAGENET_STD", "NUSCENES_CAMERAS", "PRESETS", "LidarPreset",
    "camera_tensor", "cameras_tensor", "decode_image", "lidar_preset", "range_image",
]
