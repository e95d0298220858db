"""msg_tools: ROS 2 messages and rosbag2 files <-> numpy, without a ROS installation.

Conversions accept rosbags message objects and rclpy message objects alike (they
only read attribute names) and build rosbags messages by default, or instances of
a ``msg_type`` class the caller passes (e.g. rclpy's ``sensor_msgs.msg.Image``).
"""
from .bags import BagSummary, BagWriter, FrameStream, ReadStats, bag_summary, read_camera_models, read_frames
from .camera_info import camera_info_to_model, model_to_camera_info
from .compressed import (
    array_to_compressed,
    compressed_bytes,
    compressed_from_bytes,
    compressed_jpeg_bytes,
    compressed_to_array,
)
from .errors import (
    BagError,
    BagTopicError,
    CameraInfoError,
    DatasetError,
    ImageEncodingError,
    ImageError,
    ImageLayoutError,
    MissingFieldError,
    MsgToolsError,
    PointCloudDataError,
    PointCloudError,
    PointFieldDatatypeError,
    PointFieldLayoutError,
    TrajectoryError,
)
from .frames import (
    KITTI_TOPICS,
    NUSCENES_CAMERAS,
    NUSCENES_TOPICS,
    CameraImage,
    CameraModel,
    SensorFrame,
    Topics,
)
from .ground_truth import poses_from_frames
from .image import array_to_image, depth_to_metres, image_to_array, image_to_rgb
from .pointcloud import array_to_pointcloud2, pointcloud2_to_array, xyz_cloud
from .transforms import odometry_to_pose, pose_to_odometry
from .types import Stamp, sec_to_stamp, stamp_to_ns, stamp_to_sec, typestore

__all__ = [
    "KITTI_TOPICS", "NUSCENES_CAMERAS", "NUSCENES_TOPICS",
    "BagError", "BagSummary", "BagTopicError", "BagWriter", "CameraImage", "CameraInfoError", "CameraModel",
    "DatasetError", "FrameStream", "ImageEncodingError", "ImageError", "ImageLayoutError", "MissingFieldError",
    "MsgToolsError", "PointCloudDataError", "PointCloudError", "PointFieldDatatypeError", "PointFieldLayoutError",
    "ReadStats", "SensorFrame", "Stamp", "Topics", "TrajectoryError",
    "array_to_compressed", "array_to_image", "array_to_pointcloud2", "bag_summary", "camera_info_to_model",
    "compressed_bytes", "compressed_from_bytes", "compressed_jpeg_bytes", "compressed_to_array", "depth_to_metres",
    "image_to_array", "image_to_rgb", "model_to_camera_info", "odometry_to_pose", "pointcloud2_to_array",
    "pose_to_odometry", "poses_from_frames", "read_camera_models", "read_frames", "sec_to_stamp",
    "stamp_to_ns", "stamp_to_sec", "typestore", "xyz_cloud",
]
