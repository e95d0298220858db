"""Message checks both nodes share: LiDAR clouds and odometry, refused with a short, stable reason.

Works on rclpy and rosbags messages alike (msg_tools reads attribute names only). Every refusal is an
:class:`~ros_common.errors.InputRejected` whose ``reason`` is one of the constants below.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from msg_tools.errors import GeometryError, MissingFieldError, PointCloudDataError, PointCloudError
from msg_tools.pointcloud import finite_mask, pointcloud2_to_array
from msg_tools.transforms import odometry_to_pose

from .errors import InputRejected
from .poses import OdometryBuffer
from .stamps import NS_PER_S, stamp_ns

CLOUD_NO_XYZ = "cloud: no x/y/z fields"
CLOUD_TRUNCATED = "cloud: truncated data"
CLOUD_BAD_LAYOUT = "cloud: bad layout"
CLOUD_NAN = "cloud: NaN points removed"  # not a drop: the points are removed, the cloud is used
ODOM_BAD = "odometry: bad pose"


def cloud_array(msg: Any) -> np.ndarray:
    """PointCloud2 -> its points as a structured (N,) array, refusing missing x/y/z, truncated data and
    layouts msg_tools cannot read."""
    try:
        return pointcloud2_to_array(msg, require_xyz=True).reshape(-1)
    except MissingFieldError as err:
        raise InputRejected(CLOUD_NO_XYZ, str(err)) from err
    except PointCloudDataError as err:
        raise InputRejected(CLOUD_TRUNCATED, str(err)) from err
    except PointCloudError as err:
        raise InputRejected(CLOUD_BAD_LAYOUT, str(err)) from err


def finite_points(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(N x 3 float32 points with finite x, y, z other than the origin; the (len(cloud),) mask of them;
    how many points had NaN/inf x, y or z).

    x = y = z = 0 is how Ouster's and several other drivers mark a beam without a return in an
    organised cloud: it is no measurement and never becomes a range-image pixel or a map point.
    """
    finite = finite_mask(cloud)
    keep = finite & ~((cloud["x"] == 0) & (cloud["y"] == 0) & (cloud["z"] == 0))
    points = np.stack([cloud["x"][keep], cloud["y"][keep], cloud["z"][keep]], axis=1).astype(np.float32)
    return points, keep, int(finite.size - np.count_nonzero(finite))


def odometry_pose(msg: Any) -> np.ndarray:
    try:
        pose = odometry_to_pose(msg)
    except GeometryError as err:
        raise InputRejected(ODOM_BAD, str(err)) from err
    if not np.isfinite(pose).all():
        raise InputRejected(ODOM_BAD, f"the pose has non-finite values: {pose[:3, 3].tolist()}")
    return pose


def offer_odometry(buffer: OdometryBuffer, msg: Any) -> None:
    """Check an Odometry message and add its pose to ``buffer``; InputRejected when either refuses it."""
    pose = odometry_pose(msg)
    ns = stamp_ns(msg.header)
    refused = buffer.offer(ns, pose, msg.header.frame_id)
    if refused is not None:
        raise InputRejected(f"odometry: {refused}", f"stamp {ns / NS_PER_S:.9f}")
