"""rosbag2 writing and synchronised reading of SensorFrames (sqlite3 and mcap storage)."""
from .calibration import StaticTransforms, read_camera_models, read_static_transforms
from .reader import FrameStream, ReadStats, read_frames
from .summary import BagSummary, TopicSummary, bag_summary
from .writer import STORAGES, BagWriter, label_image

__all__ = [
    "STORAGES", "BagSummary", "BagWriter", "FrameStream", "ReadStats", "StaticTransforms", "TopicSummary",
    "bag_summary", "label_image", "read_camera_models", "read_frames", "read_static_transforms",
]
