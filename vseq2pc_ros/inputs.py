"""Messages -> arrays for VSeq2PC, refusing bad ones with a short, stable reason.

Every refusal is an :class:`~ros_common.errors.InputRejected` whose ``reason`` is one of
the constants below; the node counts them in /diagnostics and warns once per reason.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from msg_tools.camera_info import camera_info_to_model
from msg_tools.errors import CameraInfoError, ImageEncodingError, ImageError
from msg_tools.image import depth_to_metres, image_to_array
from ros_common.errors import InputRejected
from ros_common.inputs import (  # noqa: F401 - the shared reasons are part of this module's vocabulary
    CLOUD_BAD_LAYOUT,
    CLOUD_NAN,
    CLOUD_NO_XYZ,
    CLOUD_TRUNCATED,
    cloud_array,
    finite_points,
    odometry_pose,
)

CLOUD_NO_LABEL = "cloud: no label field"
DEPTH_ENCODING = "depth: unknown encoding"
DEPTH_BAD = "depth: bad image"
LABELS_ENCODING = "labels: unknown encoding"
LABELS_BAD = "labels: bad image"
CAMERA_INFO_BAD = "camera_info: bad"
SIZE_MISMATCH = "camera: image sizes differ"

LABEL_ENCODINGS = ("mono8", "8UC1", "mono16", "16UC1", "32SC1")


def labelled_cloud(msg: Any) -> tuple[np.ndarray, np.ndarray, int]:
    """PointCloud2 with x, y, z and ``label`` -> (N x 3 float32 finite points, N uint32 labels, removed)."""
    cloud = cloud_array(msg)
    names = cloud.dtype.names or ()
    if "label" not in names:
        raise InputRejected(CLOUD_NO_LABEL, f"the cloud has fields {list(names)}; a 'label' field "
                                            "(SemanticKITTI id per point, uint32) is required")
    if any(cloud.dtype[n].shape for n in ("x", "y", "z", "label")) or cloud.dtype["label"].kind not in "iu":
        raise InputRejected(CLOUD_BAD_LAYOUT, "x, y, z and label must be single values per point, label an integer")
    points, keep, nonfinite = finite_points(cloud)
    labels = cloud["label"][keep].astype(np.int64).astype(np.uint32)
    return points, labels, nonfinite


def depth_image(msg: Any) -> np.ndarray:
    """32FC1 (m) or 16UC1 (mm) Image -> H x W float32 metres (0 = unknown)."""
    encoding = str(msg.encoding)
    if encoding not in ("32FC1", "16UC1"):
        raise InputRejected(DEPTH_ENCODING, f"encoding {encoding!r}; accepted: 32FC1 (metres), 16UC1 (millimetres)")
    try:
        return depth_to_metres(msg)
    except ImageEncodingError as err:
        raise InputRejected(DEPTH_ENCODING, str(err)) from err
    except ImageError as err:
        raise InputRejected(DEPTH_BAD, str(err)) from err


def label_image(msg: Any) -> np.ndarray:
    """Label Image -> H x W uint32 SemanticKITTI ids (32SC1 carries uint32 bits)."""
    encoding = str(msg.encoding)
    if encoding not in LABEL_ENCODINGS:
        raise InputRejected(LABELS_ENCODING, f"encoding {encoding!r}; accepted: {', '.join(LABEL_ENCODINGS)}")
    try:
        pixels = image_to_array(msg)
    except ImageError as err:
        raise InputRejected(LABELS_BAD, str(err)) from err
    if encoding == "32SC1":
        return pixels.view(np.uint32)
    return pixels.astype(np.uint32)


def intrinsics(msg: Any) -> tuple[np.ndarray, int, int]:
    """CameraInfo -> (3 x 3 K, width, height)."""
    try:
        model = camera_info_to_model(msg, name="camera")
    except CameraInfoError as err:
        raise InputRejected(CAMERA_INFO_BAD, str(err)) from err
    return model.K, model.width, model.height
