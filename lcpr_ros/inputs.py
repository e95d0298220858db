"""Sensor messages -> what the detector reads, refusing bad ones with a short, stable reason.

Works on rclpy and rosbags messages alike (msg_tools reads attribute names only).
Every refusal is an :class:`~ros_common.errors.InputRejected` whose ``reason`` is one
of the constants below; the node counts them and warns once per reason.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from lcpr_core.errors import InputShapeError
from lcpr_core.lcpr.preprocess.camera import CameraInput
from msg_tools.compressed import compressed_bytes, sniff_format
from msg_tools.errors import ImageEncodingError, ImageError, ImageLayoutError
from msg_tools.image import COLOUR_ENCODINGS, check_layout, image_to_rgb
from ros_common.errors import InputRejected
from ros_common.inputs import (  # noqa: F401 - the shared reasons and checks are part of this module's vocabulary
    CLOUD_BAD_LAYOUT,
    CLOUD_NAN,
    CLOUD_NO_XYZ,
    CLOUD_TRUNCATED,
    ODOM_BAD,
    cloud_array,
    finite_points,
    odometry_pose,
)

IMAGE_ENCODING = "image: unknown encoding"
IMAGE_SIZE = "image: wrong size"
IMAGE_DECODE = "image: cannot decode"


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


def camera_input(payload: Any) -> CameraInput:
    """A payload from :func:`compressed_payload` / :func:`raw_payload` -> what the describer reads.

    Compressed bytes pass through undecoded: the describer decodes them at the size the network needs
    (on the GPU with ``decode: nvjpeg``) and reports bytes it cannot decode per camera. Raw images
    become RGB arrays.
    """
    try:
        if isinstance(payload, bytes):
            return payload
        return image_to_rgb(payload)
    except (InputShapeError, ImageError) as err:
        raise InputRejected(IMAGE_DECODE, str(err)) from err
