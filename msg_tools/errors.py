"""Exceptions raised by msg_tools; every message names the bad value and what is accepted.

Errors about malformed input also derive from :class:`ValueError`, so callers that
only know the standard library can still catch them.
"""
from __future__ import annotations

from lcpr_common.errors import ProjectError


class MsgToolsError(ProjectError):
    """Base class of every error raised by msg_tools."""


class MessageError(MsgToolsError, ValueError):
    """A message (or message class) cannot be built or read."""


class StampError(MessageError):
    """A time stamp is out of the range a ROS ``builtin_interfaces/Time`` holds."""


class PointCloudError(MsgToolsError, ValueError):
    """A PointCloud2 message or a point array cannot be converted."""


class PointFieldDatatypeError(PointCloudError):
    """A PointField's datatype is not one of the eight ROS datatypes (or a dtype has no ROS datatype)."""


class PointFieldLayoutError(PointCloudError):
    """PointFields overlap, reach beyond point_step, repeat a name, or rows overlap."""


class PointCloudDataError(PointCloudError):
    """The data buffer is shorter than ``row_step * height``."""


class MissingFieldError(PointCloudError):
    """A field the caller requires (x, y, z) is absent."""


class ImageError(MsgToolsError, ValueError):
    """An Image or CompressedImage message or an image array cannot be converted."""


class ImageEncodingError(ImageError):
    """An image encoding (or compressed format) is not supported, or does not fit the array."""


class ImageLayoutError(ImageError):
    """An image's step, size or data length are inconsistent."""


class CameraInfoError(MsgToolsError, ValueError):
    """A CameraInfo message or a camera model cannot be converted."""


class GeometryError(MsgToolsError, ValueError):
    """A pose or transform is not a valid rigid transform."""


class BagError(MsgToolsError):
    """A rosbag2 cannot be written or read."""


class BagTopicError(BagError, ValueError):
    """A topic is missing from a bag, or holds a message type other than the one needed."""


class DatasetError(MsgToolsError):
    """A dataset folder (nuScenes, KITTI) is missing files or holds inconsistent tables."""


class TrajectoryError(MsgToolsError, ValueError):
    """Frames handed to :func:`msg_tools.ground_truth.poses_from_frames` lack a pose or have a malformed one."""
