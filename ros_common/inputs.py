"""One call per message kind the nodes take: msg_tools' layout check, the finite filter, and a refusal
with a short, stable reason.

- PointCloud2 with x, y, z: :func:`cloud_points` -> N x 3 float32 points and how many had NaN/inf;
- PointCloud2 with x, y, z and ``label``: :func:`labelled_cloud` -> points, uint32 labels, NaN/inf count;
- CompressedImage: :func:`compressed_payload` -> its JPEG/PNG bytes, undecoded;
- colour Image: :func:`raw_payload` -> the message, its layout checked; on the worker, either payload
  goes through :func:`camera_input` -> what the describer reads;
- depth Image: :func:`depth_image` -> H x W float32 metres; label Image: :func:`label_image` -> uint32 ids;
- CameraInfo: :func:`intrinsics` -> (K, width, height);
- Odometry: :func:`odometry_pose` -> 4 x 4 pose, or :func:`offer_odometry` into an odometry buffer;
- a peer's ``~/keyframes`` UInt8MultiArray: :func:`peer_keyframe` -> its PeerKeyframe.

Works on rclpy and rosbags messages alike (msg_tools reads attribute names only). Every refusal is an
:class:`~ros_common.errors.InputRejected` whose ``reason`` is one of the constants below; the nodes count
the reasons in /diagnostics and warn once per reason. No other exception comes out of these calls.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from lcpr_core.detector import PeerKeyframe, PeerKeyframeError, decode_peer_keyframe
from msg_tools.camera_info import camera_info_to_model
from msg_tools.compressed import compressed_bytes, sniff_format
from msg_tools.errors import (
    ImageEncodingError,
    ImageLayoutError,
    MissingFieldError,
    MsgToolsError,
    PointCloudDataError,
)
from msg_tools.image import COLOUR_ENCODINGS, check_layout, depth_to_metres, image_to_array, image_to_rgb
from msg_tools.pointcloud import finite_mask, pointcloud2_to_array
from msg_tools.transforms import odometry_to_pose

from .errors import InputRejected
from .poses import OdometryBuffer
from .stamps import NS_PER_S, stamp_ns

CLOUD_NO_XYZ = "cloud: no x/y/z fields"
CLOUD_NO_LABEL = "cloud: no label field"
CLOUD_TRUNCATED = "cloud: truncated data"
CLOUD_BAD_LAYOUT = "cloud: bad layout"
CLOUD_NAN = "cloud: NaN points removed"  # not a drop: the points are removed, the cloud is used
IMAGE_ENCODING = "image: unknown encoding"
IMAGE_SIZE = "image: wrong size"
IMAGE_DECODE = "image: cannot decode"
DEPTH_ENCODING = "depth: unknown encoding"
DEPTH_BAD = "depth: bad image"
LABELS_ENCODING = "labels: unknown encoding"
LABELS_BAD = "labels: bad image"
CAMERA_INFO_BAD = "camera_info: bad"
ODOM_BAD = "odometry: bad pose"
PEER_UNREADABLE = "peer keyframe: unreadable"
#: ``layout.dim[0].label`` of a ``~/keyframes`` message (std_msgs/UInt8MultiArray holding one record)
KEYFRAME_FORMAT = "lcpr_keyframe/1"

LABEL_ENCODINGS = ("mono8", "8UC1", "mono16", "16UC1", "32SC1")
DEPTH_IMAGE_ENCODINGS = ("32FC1", "16UC1")
_FLOAT32_MAX = float(np.finfo(np.float32).max)

# -- point clouds -----------------------------------------------------------------------------------


def cloud_points(msg: Any) -> tuple[np.ndarray, int]:
    """PointCloud2 -> (N x 3 float32 points, number of points with NaN/inf x, y or z removed).

    Zero (no-return) points are removed too, without being counted: a driver's convention, not a fault.
    """
    points, _, nonfinite = finite_points(cloud_array(msg))
    return points, nonfinite


def labelled_cloud(msg: Any) -> tuple[np.ndarray, np.ndarray, int]:
    """PointCloud2 with x, y, z and ``label`` -> (N x 3 float32 finite points, N uint32 labels, removed)."""
    cloud = _structured(msg)
    names = cloud.dtype.names or ()
    if "label" not in names:
        raise InputRejected(CLOUD_NO_LABEL, f"the cloud has fields {list(names)}; a 'label' field "
                                            "(SemanticKITTI id per point, uint32) is required")
    if _has_runs(cloud, ("x", "y", "z", "label")) or cloud.dtype["label"].kind not in "iu":
        raise InputRejected(CLOUD_BAD_LAYOUT, "x, y, z and label must be single values per point, label an integer")
    points, keep, nonfinite = finite_points(cloud)
    labels = cloud["label"][keep].astype(np.int64).astype(np.uint32)
    return points, labels, nonfinite


def cloud_array(msg: Any) -> np.ndarray:
    """PointCloud2 -> its points as a structured (N,) array whose x, y and z are single values, refusing
    missing x/y/z, truncated data and layouts msg_tools cannot read."""
    cloud = _structured(msg)
    if _has_runs(cloud, ("x", "y", "z")):
        raise InputRejected(CLOUD_BAD_LAYOUT, "x, y and z must be single values per point (PointField count 1)")
    return cloud


def finite_points(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(N x 3 float32 points with finite x, y, z other than the origin; the (len(cloud),) mask of them;
    how many points had NaN/inf x, y or z), for a :func:`cloud_array` cloud.

    x = y = z = 0 is how Ouster's and several other drivers mark a beam without a return in an
    organised cloud: it is no measurement and never becomes a range-image pixel or a map point.
    A float64 coordinate beyond float32's range would become infinite: it counts as non-finite.
    """
    finite = finite_mask(cloud)
    for name in ("x", "y", "z"):
        if cloud.dtype[name].kind == "f" and cloud.dtype[name].itemsize > 4:
            finite &= np.abs(cloud[name]) <= _FLOAT32_MAX
    keep = finite & ~((cloud["x"] == 0) & (cloud["y"] == 0) & (cloud["z"] == 0))
    points = np.stack([cloud["x"][keep], cloud["y"][keep], cloud["z"][keep]], axis=1).astype(np.float32)
    return points, keep, int(finite.size - np.count_nonzero(finite))


def _structured(msg: Any) -> np.ndarray:
    """msg_tools' read of a PointCloud2 with x, y and z, flattened; its errors become reasons."""
    try:
        return pointcloud2_to_array(msg, require_xyz=True).reshape(-1)
    except MissingFieldError as err:
        raise InputRejected(CLOUD_NO_XYZ, str(err)) from err
    except PointCloudDataError as err:
        raise InputRejected(CLOUD_TRUNCATED, str(err)) from err
    except MsgToolsError as err:  # PointCloudError and the other layouts msg_tools refuses
        raise InputRejected(CLOUD_BAD_LAYOUT, str(err)) from err


def _has_runs(cloud: np.ndarray, names: tuple[str, ...]) -> bool:
    """Whether any of the fields holds several values per point (a PointField count above 1)."""
    return any(cloud.dtype[name].shape for name in names)


# -- colour images (lcpr_node) ------------------------------------------------------------------------


def compressed_payload(msg: Any) -> bytes:
    """CompressedImage -> its JPEG/PNG bytes (decoded later, by the worker)."""
    try:
        data = compressed_bytes(msg)
    except MsgToolsError as err:
        raise InputRejected(IMAGE_DECODE, str(err)) from err
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


def camera_input(payload: Any) -> bytes | np.ndarray:
    """A payload from :func:`compressed_payload` / :func:`raw_payload` -> what the describer reads.

    Compressed bytes pass through undecoded: the describer decodes them at the size the network needs
    (on the GPU with ``decode: nvjpeg``) and reports bytes it cannot decode per camera. Raw images
    become RGB arrays.
    """
    if isinstance(payload, bytes):
        return payload
    try:
        return image_to_rgb(payload)
    except MsgToolsError as err:
        raise InputRejected(IMAGE_DECODE, str(err)) from err


# -- depth, labels and intrinsics (vseq2pc_node) -----------------------------------------------------


def depth_image(msg: Any) -> np.ndarray:
    """32FC1 (m) or 16UC1 (mm) Image -> H x W float32 metres (0 = unknown)."""
    encoding = str(msg.encoding)
    if encoding not in DEPTH_IMAGE_ENCODINGS:
        raise InputRejected(DEPTH_ENCODING, f"encoding {encoding!r}; accepted: 32FC1 (metres), 16UC1 (millimetres)")
    try:
        return depth_to_metres(msg)
    except ImageEncodingError as err:
        raise InputRejected(DEPTH_ENCODING, str(err)) from err
    except MsgToolsError as err:
        raise InputRejected(DEPTH_BAD, str(err)) from err


def label_image(msg: Any) -> np.ndarray:
    """Label Image -> H x W uint32 SemanticKITTI ids (32SC1 carries uint32 bits)."""
    encoding = str(msg.encoding)
    if encoding not in LABEL_ENCODINGS:
        raise InputRejected(LABELS_ENCODING, f"encoding {encoding!r}; accepted: {', '.join(LABEL_ENCODINGS)}")
    try:
        pixels = image_to_array(msg)
    except MsgToolsError as err:
        raise InputRejected(LABELS_BAD, str(err)) from err
    if encoding == "32SC1":
        return pixels.view(np.uint32)
    return pixels.astype(np.uint32)


def intrinsics(msg: Any) -> tuple[np.ndarray, int, int]:
    """CameraInfo -> (3 x 3 K, width, height)."""
    try:
        model = camera_info_to_model(msg, name="camera")
    except MsgToolsError as err:
        raise InputRejected(CAMERA_INFO_BAD, str(err)) from err
    return model.K, model.width, model.height


# -- odometry ---------------------------------------------------------------------------------------


def odometry_pose(msg: Any) -> np.ndarray:
    """Odometry -> its finite 4 x 4 world_T_base."""
    try:
        pose = odometry_to_pose(msg)
    except MsgToolsError as err:
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


# -- peer keyframes (lcpr_node's ~/keyframes) ----------------------------------------------------------


def peer_keyframe(msg: Any) -> PeerKeyframe:
    """std_msgs/UInt8MultiArray from a peer's ``~/keyframes`` -> its keyframe (the record of
    :mod:`lcpr_core.lcpr.peers`); whether this detector can use it is the detector's to judge."""
    dims = getattr(getattr(msg, "layout", None), "dim", None) or []
    label = str(dims[0].label) if len(dims) else ""
    if label != KEYFRAME_FORMAT:
        raise InputRejected(PEER_UNREADABLE, f"layout.dim[0].label {label!r}; a peer keyframe carries "
                                             f"{KEYFRAME_FORMAT!r}")
    try:
        return decode_peer_keyframe(bytes(msg.data))
    except (PeerKeyframeError, TypeError, ValueError) as err:
        raise InputRejected(PEER_UNREADABLE, str(err)) from err


__all__ = [
    "CAMERA_INFO_BAD", "CLOUD_BAD_LAYOUT", "KEYFRAME_FORMAT", "PEER_UNREADABLE",
    "CLOUD_NAN", "CLOUD_NO_LABEL", "CLOUD_NO_XYZ", "CLOUD_TRUNCATED",
    "DEPTH_BAD", "DEPTH_ENCODING", "DEPTH_IMAGE_ENCODINGS", "IMAGE_DECODE", "IMAGE_ENCODING", "IMAGE_SIZE",
    "LABELS_BAD", "LABELS_ENCODING", "LABEL_ENCODINGS", "ODOM_BAD",
    "camera_input", "cloud_array", "cloud_points", "compressed_payload", "depth_image", "finite_points",
    "intrinsics", "label_image", "labelled_cloud", "odometry_pose", "offer_odometry", "peer_keyframe", "raw_payload",
]
