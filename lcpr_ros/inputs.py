"""Sensor messages -> what the detector reads, refusing bad ones with a short, stable reason.

Works on rclpy and rosbags messages alike (msg_tools reads attribute names only).
Every refusal is an :class:`~lcpr_ros.errors.InputRejected` whose ``reason`` is one
of the constants below; the node counts them and warns once per reason.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from lcpr_core.errors import InputShapeError
from lcpr_core.preprocess.camera import CameraInput, decode_image
from msg_tools.compressed import compressed_bytes, sniff_format
from msg_tools.errors import (
    GeometryError,
    ImageEncodingError,
    ImageError,
    ImageLayoutError,
    MissingFieldError,
    PointCloudDataError,
    PointCloudError,
)
from msg_tools.image import COLOUR_ENCODINGS, check_layout, image_to_rgb
from msg_tools.pointcloud import finite_mask, pointcloud2_to_array
from msg_tools.transforms import odometry_to_pose

from .errors import InputRejected

CLOUD_NO_XYZ = "cloud: no x/y/z fields"
CLOUD_TRUNCATED = "cloud: truncated data"
CLOUD_BAD_LAYOUT = "cloud: bad layout"
CLOUD_NAN = "cloud: NaN points removed"  # not a drop: the points are removed, the cloud is used
IMAGE_ENCODING = "image: unknown encoding"
IMAGE_SIZE = "image: wrong size"
IMAGE_DECODE = "image: cannot decode"
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


def cloud_points(msg: Any) -> tuple[np.ndarray, int]:
    """PointCloud2 -> (N x 3 float32 points, number of points with NaN/inf x, y or z removed).

    Zero (no-return) points are removed too, without being counted: a driver's convention, not a fault.
    """
    cloud = cloud_array(msg)
    if any(cloud.dtype[name].shape for name in ("x", "y", "z")):
        raise InputRejected(CLOUD_BAD_LAYOUT, "x, y and z must be single values per point (PointField count 1)")
    points, _, nonfinite = finite_points(cloud)
    return points, nonfinite


def compressed_payload(msg: Any) -> bytes:
    """CompressedImage -> its JPEG/PNG bytes (decoded later, by the worker)."""
    data = compressed_bytes(msg)
    if not data:
        raise InputRejected(IMAGE_SIZE, "the compressed image holds no bytes")
    try:
        sniff_format(data)
    except ImageEncodingError as err:
        raise InputRejected(IMAGE_ENCODING, f"format {getattr(msg, 'format', '')!r}: {err}") from err
    return data


def raw_payload(msg: Any) -> Any:
    """Image -> the message itself once its encoding and size are checked (converted later)."""
    encoding = str(msg.encoding)
    if encoding not in COLOUR_ENCODINGS:
        raise InputRejected(IMAGE_ENCODING,
                            f"encoding {encoding!r} is not a colour encoding; accepted: {', '.join(COLOUR_ENCODINGS)}")
    if int(msg.height) <= 0 or int(msg.width) <= 0:
        raise InputRejected(IMAGE_SIZE, f"image is {msg.width} x {msg.height}; it must not be empty")
    try:
        check_layout(msg)
    except ImageLayoutError as err:
        raise InputRejected(IMAGE_SIZE, str(err)) from err
    return msg


def camera_input(payload: Any, *, draft_size: tuple[int, int] | None = None) -> CameraInput:
    """A payload from :func:`compressed_payload` / :func:`raw_payload` -> decoded RGB image."""
    try:
        if isinstance(payload, bytes):
            return decode_image(payload, draft_size=draft_size)
        return image_to_rgb(payload)
    except (InputShapeError, ImageError) as err:
        raise InputRejected(IMAGE_DECODE, str(err)) from err


def odometry_pose(msg: Any) -> np.ndarray:
    try:
        pose = odometry_to_pose(msg)
    except GeometryError as err:
        raise InputRejected(ODOM_BAD, str(err)) from err
    if not np.isfinite(pose).all():
        raise InputRejected(ODOM_BAD, f"the pose has non-finite values: {pose[:3, 3].tolist()}")
    return pose
