"""Malformed ROS messages for the fuzz tests, as a driver bug or a hand-built message would send them.

Messages are rosbags dataclasses filled field by field (msg_tools' builders are bypassed, being under
test), so a field may hold what no well-behaved publisher sends: sizes of 0, huge or negative, a
``step`` or ``row_step`` that does not fit, data a few bytes short or long, unknown encodings and
datatypes, NaN and infinity, empty and repeated fields. Each strategy mixes such wild values with
near-valid messages (sizes that fit, give or take a few bytes), so that the fuzz also reaches the
conversions past the first checks. Sizes stay small: a whole fuzz file runs in well under a minute.

:data:`FUZZ` is the settings every fuzz test uses: seeded (``derandomize``), no deadline, and 1,000
examples per test (``LCPR_FUZZ_EXAMPLES`` overrides the count, e.g. for a quick local run).
"""
from __future__ import annotations

import array
import dataclasses
import importlib
import io
import os
import struct
import zlib
from typing import Any

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from PIL import Image as PILImage

from msg_tools.image import ENCODINGS, PLANAR_ENCODINGS
from msg_tools.types import message_class

settings.register_profile(
    "fuzz", max_examples=int(os.environ.get("LCPR_FUZZ_EXAMPLES", "1000")), derandomize=True, deadline=None,
    database=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                          HealthCheck.filter_too_much, HealthCheck.large_base_example],
)
FUZZ = settings.get_profile("fuzz")

Header = message_class("std_msgs/msg/Header")
Time = message_class("builtin_interfaces/msg/Time")
Image = message_class("sensor_msgs/msg/Image")
CompressedImage = message_class("sensor_msgs/msg/CompressedImage")
PointCloud2 = message_class("sensor_msgs/msg/PointCloud2")
PointField = message_class("sensor_msgs/msg/PointField")
CameraInfo = message_class("sensor_msgs/msg/CameraInfo")
RegionOfInterest = message_class("sensor_msgs/msg/RegionOfInterest")
Odometry = message_class("nav_msgs/msg/Odometry")
PoseWithCovariance = message_class("geometry_msgs/msg/PoseWithCovariance")
TwistWithCovariance = message_class("geometry_msgs/msg/TwistWithCovariance")
Pose = message_class("geometry_msgs/msg/Pose")
Twist = message_class("geometry_msgs/msg/Twist")
Point = message_class("geometry_msgs/msg/Point")
Quaternion = message_class("geometry_msgs/msg/Quaternion")
Vector3 = message_class("geometry_msgs/msg/Vector3")
Transform = message_class("geometry_msgs/msg/Transform")
TransformStamped = message_class("geometry_msgs/msg/TransformStamped")
TFMessage = message_class("tf2_msgs/msg/TFMessage")

#: sizes (height, width, step, counts...): small ones, and the edges of uint32 and beyond
SIZES = st.one_of(st.integers(0, 6), st.sampled_from([-1, 2**31 - 1, 2**32 - 1, 2**40]))
#: float fields: anything a double holds, NaN and infinities included
FLOATS = st.one_of(st.floats(-1e3, 1e3), st.floats(allow_nan=True, allow_infinity=True),
                   st.sampled_from([0.0, -0.0, 1.0, float("nan"), float("inf"), -float("inf"), 1e308]))
NAMES = st.one_of(st.sampled_from(["", "map", "odom", "base_link", "cam", "lidar"]), st.text(max_size=6))
IMAGE_ENCODINGS = (*ENCODINGS, *PLANAR_ENCODINGS)


def bytes_of(data: bytes, kind: str) -> Any:
    """A byte payload as the message libraries hold it: numpy uint8 (rosbags), array('B') (rclpy) or bytes."""
    if kind == "numpy":
        return np.frombuffer(data, dtype=np.uint8).copy()
    if kind == "array":
        return array.array("B", data)
    return data


PAYLOAD_KINDS = st.sampled_from(["numpy", "array", "bytes"])


@st.composite
def payloads(draw: st.DrawFn, length: int | None = None, *, max_size: int = 64) -> Any:
    if length is None:
        data = draw(st.binary(max_size=max_size))
    else:
        data = draw(st.binary(min_size=length, max_size=length))
    return bytes_of(data, draw(PAYLOAD_KINDS))


@st.composite
def stamps(draw: st.DrawFn) -> Any:
    sec = draw(st.one_of(st.integers(0, 2**31 - 1), st.sampled_from([-1, -(2**31), 2**31, 2**40])))
    nanosec = draw(st.one_of(st.integers(0, 999_999_999), st.sampled_from([-1, 10**9, 2**32 - 1])))
    return Time(sec=sec, nanosec=nanosec)


#: a few headers, good and bad (the stamps have a fuzz test of their own; a message's header is seldom its fault)
HEADERS = [Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame)
           for sec, nanosec, frame in [(1_700_000_000, 5, "lidar"), (0, 0, ""), (-1, 10**9, "\x00"),
                                       (2**31, 2**32 - 1, "cam")]]


def headers(*, stamped: bool = False) -> st.SearchStrategy[Any]:
    """One of :data:`HEADERS`, or with ``stamped`` any stamp (for callbacks that order messages by stamp)."""
    if stamped:
        return st.builds(Header, stamp=stamps(), frame_id=NAMES)
    return st.sampled_from(HEADERS)


# -- Image ------------------------------------------------------------------------------------------


def _pixel_bytes(encoding: str) -> int:
    enc = ENCODINGS.get(encoding)
    return 1 if enc is None else enc.channels * enc.dtype.itemsize


@st.composite
def images(draw: st.DrawFn, encodings: tuple[str, ...] = IMAGE_ENCODINGS, *, stamped: bool = False) -> Any:
    """sensor_msgs/Image: a known or unknown encoding; near-valid or wild sizes, step and data."""
    encoding = draw(st.one_of(st.sampled_from(encodings), st.sampled_from(IMAGE_ENCODINGS),
                              st.text(max_size=10)))
    if draw(st.booleans()):  # near-valid: step and data fit the size, give or take a few bytes
        height, width = draw(st.integers(0, 6)), draw(st.integers(0, 6))
        step = max(0, width * _pixel_bytes(encoding) + draw(st.integers(-2, 3)))
        rows = height * 3 // 2 if encoding in PLANAR_ENCODINGS else height
        length = max(0, step * rows + draw(st.sampled_from([0, 0, 0, -1, 1, -3, 5])))
    else:
        height, width, step = draw(SIZES), draw(SIZES), draw(SIZES)
        length = draw(st.integers(0, 80))
    return Image(header=draw(headers(stamped=stamped)), height=height, width=width, encoding=encoding,
                 is_bigendian=draw(st.sampled_from([0, 1, 2, -1])), step=step, data=draw(payloads(length)))


# -- CompressedImage ---------------------------------------------------------------------------------


def _encoded(mode: str, fmt: str, size: tuple[int, int] = (5, 3)) -> bytes:
    img = PILImage.new(mode, size)
    img.putdata([(k * 37) % 251 for k in range(size[0] * size[1])] if mode in ("L", "P", "I;16", "1", "I")
                else [tuple((k * c) % 251 for c in range(1, len(mode) + 1)) for k in range(size[0] * size[1])])
    out = io.BytesIO()
    img.save(out, format=fmt)
    return out.getvalue()


def _png_header(width: int, height: int, depth: int = 8, colour: int = 2) -> bytes:
    """A PNG that stops after its IHDR chunk, which claims ``width`` x ``height``."""
    body = b"IHDR" + struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + body + struct.pack(">I", zlib.crc32(body))


ENCODED = [
    _encoded("RGB", "JPEG"), _encoded("L", "JPEG"), _encoded("CMYK", "JPEG"),
    _encoded("RGB", "PNG"), _encoded("RGBA", "PNG"), _encoded("L", "PNG"), _encoded("LA", "PNG"),
    _encoded("P", "PNG"), _encoded("1", "PNG"), _encoded("I;16", "PNG"),
    _encoded("RGB", "PNG", (1, 1)),
    _png_header(100_000, 100_000), _png_header(2**31 - 1, 1), _png_header(0, 0), _png_header(3, 2, 16, 0),
]


@st.composite
def encoded_bytes(draw: st.DrawFn) -> bytes:
    """JPEG/PNG bytes: whole, truncated, with a corrupted byte, a bare signature with junk, or junk."""
    kind = draw(st.sampled_from(["whole", "truncated", "corrupted", "signature", "junk"]))
    if kind == "junk":
        return draw(st.binary(max_size=40))
    if kind == "signature":
        return draw(st.sampled_from([b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n"])) + draw(st.binary(max_size=40))
    data = draw(st.sampled_from(ENCODED))
    if kind == "truncated":
        return data[:draw(st.integers(0, len(data)))]
    if kind == "corrupted":
        at = draw(st.integers(0, len(data) - 1))
        return data[:at] + bytes([draw(st.integers(0, 255))]) + data[at + 1:]
    return data


@st.composite
def compressed_images(draw: st.DrawFn, *, stamped: bool = False) -> Any:
    fmt = draw(st.one_of(st.sampled_from(["jpeg", "png", "jpg", "rgb8; jpeg compressed bgr8", "PNG", "", "tiff"]),
                         st.text(max_size=8)))
    data = bytes_of(draw(encoded_bytes()), draw(PAYLOAD_KINDS))
    return CompressedImage(header=draw(headers(stamped=stamped)), format=fmt, data=data)


# -- PointCloud2 -------------------------------------------------------------------------------------

_DATATYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
FIELD_NAMES = st.sampled_from(["x", "y", "z", "label", "intensity", "ring", ""])


@st.composite
def wild_fields(draw: st.DrawFn) -> list[Any]:
    return draw(st.lists(st.builds(
        PointField, name=FIELD_NAMES,
        offset=st.one_of(st.integers(0, 24), st.sampled_from([-4, 2**31 - 1, 2**32 - 1])),
        datatype=st.one_of(st.integers(0, 9), st.sampled_from([255, -1])),
        count=st.one_of(st.integers(0, 3), st.sampled_from([-1, 2**31 - 1]))), max_size=5))


@st.composite
def packed_fields(draw: st.DrawFn) -> tuple[list[Any], int]:
    """Fields laid one after another (x, y, z usually among them), and the bytes they span."""
    names = draw(st.lists(FIELD_NAMES.filter(bool), unique=True, max_size=5))
    if draw(st.integers(0, 3)):  # mostly a cloud a node could use
        names = ["x", "y", "z", *[n for n in names if n not in "xyz"]]
    fields, offset = [], 0
    for name in names:
        datatype = draw(st.sampled_from(sorted(_DATATYPE_SIZES)))
        count = draw(st.sampled_from([1, 1, 1, 1, 2, 3]))
        offset += draw(st.sampled_from([0, 0, 0, 1, 4]))
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=count))
        offset += _DATATYPE_SIZES[datatype] * count
    return fields, offset


@st.composite
def point_clouds(draw: st.DrawFn, *, stamped: bool = False) -> Any:
    """sensor_msgs/PointCloud2: near-valid packed layouts (random bytes: NaN and inf appear) or wild ones."""
    if draw(st.booleans()):
        fields, span = draw(packed_fields())
        point_step = max(0, span + draw(st.sampled_from([0, 0, 0, 2, -1])))
        height, width = draw(st.sampled_from([0, 1, 1, 1, 2, 3])), draw(st.integers(0, 6))
        row_step = max(0, width * point_step + draw(st.sampled_from([0, 0, 0, 3, -1])))
        length = max(0, row_step * height + draw(st.sampled_from([0, 0, 0, -1, 1, -5])))
        data = draw(payloads(length))
    else:
        fields = draw(wild_fields())
        height, width, point_step, row_step = draw(SIZES), draw(SIZES), draw(SIZES), draw(SIZES)
        data = draw(payloads())
    return PointCloud2(header=draw(headers(stamped=stamped)), height=height, width=width, fields=fields,
                       is_bigendian=draw(st.booleans()), point_step=point_step, row_step=row_step,
                       data=data, is_dense=draw(st.booleans()))


# -- CameraInfo, Odometry, TFMessage -----------------------------------------------------------------


@st.composite
def float_arrays(draw: st.DrawFn, size: int, *, near: list[float] | None = None) -> np.ndarray:
    """``size`` doubles (sometimes another count); with ``near``, often those values, or them with one changed."""
    kind = draw(st.sampled_from(["near", "one changed", "random"] if near is not None else ["random"]))
    if near is not None and kind != "random":
        values = list(near)
        if kind == "one changed":
            values[draw(st.integers(0, size - 1))] = draw(FLOATS)
    else:
        values = draw(st.lists(FLOATS, min_size=size, max_size=size))
    if not draw(st.integers(0, 9)):
        values = draw(st.lists(FLOATS, max_size=12))
    return np.asarray(values, dtype=np.float64)


PINHOLE = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]


@st.composite
def camera_infos(draw: st.DrawFn, *, stamped: bool = False) -> Any:
    distortion = draw(st.one_of(st.just(np.zeros(5)), st.just(np.zeros(0)),
                                st.lists(FLOATS, max_size=8).map(np.asarray)))
    sizes = st.one_of(st.integers(1, 6), SIZES)
    return CameraInfo(
        header=draw(headers(stamped=stamped)), height=draw(sizes), width=draw(sizes),
        distortion_model=draw(st.sampled_from(["plumb_bob", "", "equidistant"])),
        d=np.asarray(distortion, dtype=np.float64), k=draw(float_arrays(9, near=PINHOLE)), r=np.eye(3).reshape(-1),
        p=np.zeros(12), binning_x=0, binning_y=0,
        roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


@st.composite
def quaternions(draw: st.DrawFn) -> tuple[float, float, float, float]:
    if draw(st.booleans()):
        q = np.asarray(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
        return tuple(float(v) for v in q)  # type: ignore[return-value]
    return tuple(draw(st.lists(FLOATS, min_size=4, max_size=4)))  # type: ignore[return-value]


@st.composite
def odometries(draw: st.DrawFn, *, stamped: bool = False) -> Any:
    x, y, z = draw(st.lists(FLOATS, min_size=3, max_size=3))
    qx, qy, qz, qw = draw(quaternions())
    pose = PoseWithCovariance(pose=Pose(position=Point(x=x, y=y, z=z),
                                        orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                              covariance=np.zeros(36))
    twist = TwistWithCovariance(twist=Twist(linear=Vector3(x=0.0, y=0.0, z=0.0),
                                            angular=Vector3(x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36))
    return Odometry(header=draw(headers(stamped=stamped)), child_frame_id=draw(NAMES), pose=pose, twist=twist)


@st.composite
def transform_stampeds(draw: st.DrawFn) -> Any:
    x, y, z = draw(st.lists(FLOATS, min_size=3, max_size=3))
    qx, qy, qz, qw = draw(quaternions())
    return TransformStamped(header=draw(headers()), child_frame_id=draw(NAMES),
                            transform=Transform(translation=Vector3(x=x, y=y, z=z),
                                                rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)))


@st.composite
def tf_messages(draw: st.DrawFn) -> Any:
    return TFMessage(transforms=draw(st.lists(transform_stampeds(), max_size=3)))


@st.composite
def matrices(draw: st.DrawFn) -> np.ndarray:
    """Candidate 4 x 4 poses: rigid ones (rotation from a quaternion), perturbed ones, other shapes."""
    kind = draw(st.sampled_from(["rigid", "rigid", "perturbed", "shape"]))
    if kind == "shape":
        shape = draw(st.sampled_from([(3, 3), (4,), (0,), (4, 4, 1), (3, 4)]))
        return np.full(shape, draw(FLOATS))
    q = np.asarray(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
    if np.linalg.norm(q) < 1e-3:
        q = np.array([0.0, 0.0, 0.0, 1.0])
    q = q / np.linalg.norm(q)
    x, y, z, w = q
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
    if kind == "perturbed":
        T[draw(st.integers(0, 3)), draw(st.integers(0, 3))] = draw(FLOATS)
    return T


def as_rclpy(msg: Any) -> Any | None:
    """The rclpy message (what a node's subscription hands over) holding the same field values as a
    rosbags message; None where a value lies outside its field's type (a uint32 below 0, an int32 stamp
    beyond 2**31), which no subscription can deliver. Imports the ROS message package only when called."""
    package, _, name = msg.__msgtype__.split("/")
    out = getattr(importlib.import_module(f"{package}.msg"), name)(check_fields=True)
    for item in dataclasses.fields(msg):
        if item.name == "__msgtype__" or item.name.isupper():
            continue
        value = getattr(msg, item.name)
        if dataclasses.is_dataclass(value):
            value = as_rclpy(value)
        elif isinstance(value, list) and value and dataclasses.is_dataclass(value[0]):
            value = [as_rclpy(v) for v in value]
            if any(v is None for v in value):
                return None
        elif isinstance(value, np.ndarray):
            value = value.tobytes() if value.dtype == np.uint8 else value.tolist()
        if value is None:
            return None
        try:
            setattr(out, item.name, value)
        except (AssertionError, TypeError, ValueError, OverflowError):
            return None
    return out
