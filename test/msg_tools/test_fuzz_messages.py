"""Every public msg_tools conversion, fed seeded random malformed input: only msg_tools' own errors come out.

Messages -> numpy (point clouds, images, compressed images, camera info, odometry, transforms, stamps,
CDR headers, PCD files) and numpy -> messages (the builders, the encoders, poses). A conversion may
refuse its input with a :class:`~msg_tools.errors.MsgToolsError`; anything else escaping fails the test.
What converts must convert back: a read message built again reads the same. See ``message_fuzz`` for
the messages and the settings (1,000 seeded examples per test).
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from message_fuzz import (
    FLOATS,
    FUZZ,
    IMAGE_ENCODINGS,
    NAMES,
    Header,
    bytes_of,
    camera_infos,
    compressed_images,
    encoded_bytes,
    images,
    matrices,
    odometries,
    point_clouds,
    stamps,
    tf_messages,
)
from msg_tools import (
    CameraImage,
    CameraModel,
    MsgToolsError,
    SensorFrame,
    array_to_compressed,
    array_to_image,
    array_to_pointcloud2,
    camera_info_to_model,
    compressed_bytes,
    compressed_from_bytes,
    compressed_jpeg_bytes,
    compressed_to_array,
    depth_to_metres,
    image_to_array,
    image_to_rgb,
    model_to_camera_info,
    odometry_to_pose,
    pointcloud2_to_array,
    pose_to_odometry,
    poses_from_frames,
    sec_to_stamp,
    stamp_to_ns,
    stamp_to_sec,
    xyz_cloud,
)
from msg_tools.bags.cdr import header_stamp_ns
from msg_tools.bags.writer import label_image
from msg_tools.build import as_uint8, build_message
from msg_tools.camera_info import intrinsics_matrix
from msg_tools.compressed import decode_image_bytes, encode_image, sniff_format
from msg_tools.geometry import (
    check_pose,
    interpolate_pose,
    invert_pose,
    matrix_to_quaternion,
    pose_from_parts,
    pose_to_parts,
    quaternion_to_matrix,
    slerp,
)
from msg_tools.image import check_layout
from msg_tools.pcd import pcd_xyz, read_pcd
from msg_tools.pointcloud import finite_mask
from msg_tools.transforms import read_transforms, transform_to_matrix, transforms_message
from msg_tools.types import Stamp, as_stamp, header_values

T = TypeVar("T")
# NaN, infinities and values near 1e308 are fed on purpose: numpy's warnings about them are expected
pytestmark = [pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning"),
              pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")]


def own_errors_only(convert: Callable[..., T], *args: Any, **kwargs: Any) -> T | None:
    """``convert``'s result, or None where it refused the input with msg_tools' own error."""
    try:
        return convert(*args, **kwargs)
    except MsgToolsError:
        return None


def same_fields(a: np.ndarray, b: np.ndarray) -> bool:
    """Same shape, field names and values of every field, bit for bit (NaN payloads included), in any byte order."""
    def native(values: np.ndarray) -> bytes:
        return np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("=")).tobytes()

    names = a.dtype.names or ()
    return a.shape == b.shape and names == b.dtype.names and all(native(a[n]) == native(b[n]) for n in names)


# -- messages -> numpy, and back ------------------------------------------------------------------------


@FUZZ
@given(point_clouds(), st.booleans(), st.booleans())
def test_point_clouds_convert_and_back_or_raise_msg_tools_errors(msg: Any, keep_nonfinite: bool,
                                                                  require_xyz: bool) -> None:
    cloud = own_errors_only(pointcloud2_to_array, msg, keep_nonfinite=keep_nonfinite, require_xyz=require_xyz)
    if cloud is None:
        return
    assert cloud.ndim in (1, 2) and cloud.dtype.itemsize == msg.point_step
    if {"x", "y", "z"} <= set(cloud.dtype.names or ()):
        assert finite_mask(cloud).shape == cloud.shape
    again = own_errors_only(array_to_pointcloud2, cloud, frame_id="lidar", stamp=0.0)
    if again is None:
        assert not cloud.dtype.names  # the only read a message cannot be built from: no fields at all
        return
    assert same_fields(pointcloud2_to_array(again), cloud)


@FUZZ
@given(st.one_of(images(), images(("32FC1", "16UC1"))))
def test_images_convert_and_back_or_raise_msg_tools_errors(msg: Any) -> None:
    own_errors_only(check_layout, msg)
    rgb = own_errors_only(image_to_rgb, msg)
    if rgb is not None:
        assert rgb.shape == (msg.height, msg.width, 3) and rgb.dtype == np.uint8
    depth = own_errors_only(depth_to_metres, msg)
    if depth is not None:
        assert depth.shape == (msg.height, msg.width) and depth.dtype == np.float32
        assert np.isfinite(depth).all() and (depth >= 0).all()
    pixels = own_errors_only(image_to_array, msg)
    if pixels is None:
        return
    again = array_to_image(pixels, encoding=msg.encoding, frame_id="cam", stamp=0.0)
    assert (again.height, again.width) == (msg.height, msg.width)
    assert np.array_equal(image_to_array(again), pixels, equal_nan=pixels.dtype.kind == "f")


@FUZZ
@given(compressed_images())
def test_compressed_images_decode_and_encode_again_or_raise_msg_tools_errors(msg: Any) -> None:
    data = compressed_bytes(msg)
    own_errors_only(sniff_format, data)
    own_errors_only(compressed_from_bytes, data, frame_id="cam", stamp=0.0)
    own_errors_only(compressed_jpeg_bytes, data, frame_id="cam", stamp=0.0)
    own_errors_only(decode_image_bytes, data)
    rgb = own_errors_only(image_to_rgb, msg)
    if rgb is not None:
        assert rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.uint8
    pixels = own_errors_only(compressed_to_array, msg)
    if pixels is None:
        return
    png = array_to_compressed(pixels, format="png", frame_id="cam", stamp=0.0)
    assert np.array_equal(compressed_to_array(png), pixels)


@FUZZ
@given(camera_infos(), st.booleans(), st.one_of(st.none(), matrices()))
def test_camera_infos_convert_and_back_or_raise_msg_tools_errors(msg: Any, ignore_distortion: bool,
                                                                  base_T_cam: np.ndarray | None) -> None:
    own_errors_only(intrinsics_matrix, msg.k)
    model = own_errors_only(camera_info_to_model, msg, name="cam", base_T_cam=base_T_cam,
                            ignore_distortion=ignore_distortion)
    if model is None:
        return
    again = camera_info_to_model(model_to_camera_info(model, stamp=0.0), name="cam")
    assert np.array_equal(again.K, model.K) and (again.width, again.height) == (model.width, model.height)


@FUZZ
@given(odometries())
def test_odometry_converts_and_back_or_raises_msg_tools_errors(msg: Any) -> None:
    pose = own_errors_only(odometry_to_pose, msg)
    if pose is None:
        return
    again = own_errors_only(pose_to_odometry, pose, stamp=Stamp(1, 2), frame_id="odom", child_frame_id="base")
    if again is None:
        assert not np.isfinite(pose).all()  # only a pose with NaN or inf cannot be written
        return
    assert np.allclose(odometry_to_pose(again), pose, atol=1e-9)


@FUZZ
@given(tf_messages())
def test_transforms_convert_and_back_or_raise_msg_tools_errors(msg: Any) -> None:
    for item in msg.transforms:
        own_errors_only(transform_to_matrix, item.transform)
    read = own_errors_only(read_transforms, msg)
    if read is None:
        return
    again = own_errors_only(transforms_message, read, stamp=0.0)
    if again is not None:
        assert [(p, c) for p, c, _ in read_transforms(again)] == [(p, c) for p, c, _ in read]


@FUZZ
@given(st.builds(Header, stamp=stamps(), frame_id=NAMES),
       st.one_of(FLOATS, st.integers(-(2**40), 2**40), st.none(), st.text(max_size=3), st.booleans(), stamps()))
def test_stamps_convert_or_raise_msg_tools_errors(header: Any, value: Any) -> None:
    ns = own_errors_only(stamp_to_ns, header)
    if ns is not None:
        assert own_errors_only(stamp_to_sec, header) == ns / 1_000_000_000
        assert as_stamp(header.stamp).ns == ns
    own_errors_only(stamp_to_ns, header.stamp)
    own_errors_only(sec_to_stamp, value)
    own_errors_only(as_stamp, value)
    own_errors_only(header_values, frame_id="f", stamp=value)
    if isinstance(value, int) and not isinstance(value, bool):
        own_errors_only(Stamp, value, value % 1_000_000_007)
        own_errors_only(Stamp.from_ns, value)


@FUZZ
@given(st.one_of(st.binary(max_size=24), st.binary(max_size=20).map(lambda b: b"\x00\x01\x00\x00" + b),
                 st.binary(max_size=20).map(lambda b: b"\x00\x00\x00\x00" + b)))
def test_cdr_header_stamps_read_or_raise_msg_tools_errors(raw: bytes) -> None:
    ns = own_errors_only(header_stamp_ns, raw)
    if ns is not None:
        assert isinstance(ns, int)


# -- PCD files -------------------------------------------------------------------------------------------

@st.composite
def pcd_files(draw: st.DrawFn) -> bytes:
    """A PCD file: a header whose lines may be missing, disagree or name odd types, then data of any length."""
    fields = draw(st.lists(st.sampled_from(["x", "y", "z", "intensity", "rgb"]), min_size=0, max_size=4))
    types = [draw(st.sampled_from(["F", "I", "U", "X"])) for _ in fields]
    sizes = [draw(st.sampled_from([1, 2, 4, 8, 3])) for _ in fields]
    counts = [draw(st.sampled_from([1, 1, 2, 0])) for _ in fields]
    points = draw(st.one_of(st.integers(0, 4), st.sampled_from([-1, 10**9])))
    lines = ["# .PCD v0.7", "VERSION 0.7", f"FIELDS {' '.join(fields)}", f"SIZE {' '.join(map(str, sizes))}",
             f"TYPE {' '.join(types)}", f"COUNT {' '.join(map(str, counts))}", f"WIDTH {points}", "HEIGHT 1",
             f"POINTS {draw(st.sampled_from([str(points), 'many', '']))}",
             f"DATA {draw(st.sampled_from(['ascii', 'binary', 'binary_compressed', '']))}"]
    lines = [line for line in lines if draw(st.integers(0, 9))]  # now and then a line is missing
    body = draw(st.one_of(st.binary(max_size=64), st.lists(st.sampled_from(["1", "-2.5", "nan", "inf", "x", "\n"]),
                                                            max_size=24).map(lambda words: " ".join(words).encode())))
    if not draw(st.integers(0, 19)):
        return draw(st.binary(max_size=80))
    return ("\n".join(lines) + "\n").encode() + body


def test_pcd_files_read_or_raise_msg_tools_errors(tmp_path: Path) -> None:
    path = tmp_path / "cloud.pcd"

    @FUZZ
    @given(pcd_files())
    def read(content: bytes) -> None:
        path.write_bytes(content)
        cloud = own_errors_only(read_pcd, path)
        if cloud is not None:
            xyz = own_errors_only(pcd_xyz, cloud)
            assert xyz is None or xyz.shape == (len(cloud), 3)

    read()


# -- numpy -> messages ----------------------------------------------------------------------------------

BASE_DTYPES = ["u1", "i1", "<u2", ">i2", "<u4", ">i4", "<f4", ">f4", "<f8", "i8", "u8", "f2", "c8", "?"]


@st.composite
def raw_arrays(draw: st.DrawFn, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """An array of ``dtype`` and ``shape`` whose bytes are random (NaN, inf and subnormals appear)."""
    size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if not dtype.itemsize:
        return np.zeros(shape, dtype)
    return np.frombuffer(draw(st.binary(min_size=size, max_size=size)), dtype=dtype).reshape(shape).copy()


SHAPES = st.one_of(st.lists(st.integers(0, 4), min_size=0, max_size=4).map(tuple))


@st.composite
def structured_dtypes(draw: st.DrawFn) -> np.dtype:
    """Named fields of ROS and non-ROS types, sometimes subarrays, padding or a nested record."""
    names = draw(st.lists(st.sampled_from(["x", "y", "z", "label", "intensity", "t"]), unique=True, max_size=4))
    fields: list[Any] = []
    for name in names:
        base: Any = draw(st.sampled_from(BASE_DTYPES))
        if not draw(st.integers(0, 14)):
            base = [("a", "<f4")]
        shape = draw(st.sampled_from([(), (), (), (2,), (2, 2), (0,)]))
        fields.append((name, base, shape) if shape else (name, base))
    dtype = np.dtype(fields)
    if draw(st.booleans()):  # the same fields with gaps between them and after the last
        formats = [dtype[name] for name in dtype.names or ()]
        offsets, offset = [], 0
        for fmt in formats:
            offset += draw(st.sampled_from([0, 1, 3]))
            offsets.append(offset)
            offset += fmt.itemsize
        layout: dict[str, Any] = {"names": list(dtype.names or ()), "formats": formats, "offsets": offsets,
                                  "itemsize": offset + draw(st.integers(0, 3))}
        dtype = np.dtype(layout)  # type: ignore[call-overload]
    return dtype


@FUZZ
@given(st.data())
def test_point_arrays_become_clouds_that_read_back_or_raise_msg_tools_errors(data: st.DataObject) -> None:
    dtype = data.draw(structured_dtypes())
    cloud = data.draw(raw_arrays(dtype, data.draw(st.sampled_from([(0,), (3,), (2, 3), (), (1, 1, 2)]))))
    msg = own_errors_only(array_to_pointcloud2, cloud, frame_id="lidar", stamp=0.0)
    if msg is not None:
        assert same_fields(pointcloud2_to_array(msg), cloud)
    points = data.draw(raw_arrays(np.dtype(data.draw(st.sampled_from(BASE_DTYPES))),
                                  data.draw(st.sampled_from([(3, 3), (0, 3), (2, 4), (3,), (2, 2), (1, 3, 1)]))))
    extra = {"label": data.draw(raw_arrays(np.dtype("<u4"), data.draw(st.sampled_from([(3,), (2,), (3, 2)]))))}
    columns = own_errors_only(xyz_cloud, points, **extra)
    if columns is not None:
        assert columns.shape == points.shape[:1]


@FUZZ
@given(st.data())
def test_pixel_arrays_become_images_that_read_back_or_raise_msg_tools_errors(data: st.DataObject) -> None:
    encoding = data.draw(st.one_of(st.sampled_from(IMAGE_ENCODINGS), st.text(max_size=5)))
    dtype = np.dtype(data.draw(st.sampled_from(BASE_DTYPES)))
    pixels = data.draw(raw_arrays(dtype, data.draw(st.lists(st.integers(0, 5), min_size=1, max_size=4).map(tuple))))
    msg = own_errors_only(array_to_image, pixels, encoding=encoding, frame_id="cam", stamp=0.0)
    if msg is not None:
        back = image_to_array(msg)
        assert back.tobytes() == pixels.astype(back.dtype).tobytes()
    fmt = data.draw(st.sampled_from(["jpeg", "png", "gif"]))
    quality = data.draw(st.sampled_from([90, 1, 100, 0, 101, -5]))
    encoded = own_errors_only(encode_image, pixels, format=fmt, quality=quality)
    if encoded is not None:
        assert sniff_format(encoded) == fmt
        own_errors_only(array_to_compressed, pixels, format=fmt, quality=quality,
                        frame_id="cam", stamp=0.0)
    own_errors_only(label_image, pixels)


@FUZZ
@given(st.lists(FLOATS, min_size=0, max_size=10), st.integers(-3, 5), st.integers(-3, 5),
       st.one_of(matrices(), st.none()), NAMES)
def test_camera_models_become_camera_infos_or_raise_msg_tools_errors(k: list[float], width: int, height: int,
                                                                     base_T_cam: np.ndarray | None,
                                                                     frame_id: str) -> None:
    K = np.asarray(k + [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0][len(k):], dtype=np.float64)
    if len(k) < 9 and K.size == 9:
        K = K.reshape(3, 3)
    model = CameraModel(name="cam", frame_id=frame_id, width=width, height=height, K=K,
                        base_T_cam=np.eye(4) if base_T_cam is None else base_T_cam)
    msg = own_errors_only(model_to_camera_info, model, stamp=0.0)
    if msg is not None:
        again = own_errors_only(camera_info_to_model, msg, name="cam")
        assert again is None or np.array_equal(again.K, np.asarray(K).reshape(3, 3))


@FUZZ
@given(matrices(), matrices(), st.floats(0, 1), st.lists(FLOATS, min_size=0, max_size=5),
       NAMES, NAMES)
def test_poses_become_messages_and_quaternions_or_raise_msg_tools_errors(a: np.ndarray, b: np.ndarray, alpha: float,
                                                                        q: list[float], parent: str,
                                                                        child: str) -> None:
    own_errors_only(check_pose, a)
    parts = own_errors_only(pose_to_parts, a)
    if parts is not None:
        assert np.allclose(pose_from_parts(*parts), a, atol=1e-4)  # check_pose accepts rotations within 1e-5
    own_errors_only(quaternion_to_matrix, q)
    own_errors_only(pose_from_parts, q[:3], q)
    own_errors_only(matrix_to_quaternion, a[:3, :3] if a.ndim == 2 else a)
    if own_errors_only(check_pose, a) is not None and own_errors_only(check_pose, b) is not None:
        own_errors_only(interpolate_pose, a, b, alpha)
        assert np.allclose(invert_pose(a) @ a, np.eye(4), atol=1e-6)
        qa, qb = pose_to_parts(a)[1], pose_to_parts(b)[1]
        own_errors_only(slerp, qa, qb, alpha)
    own_errors_only(pose_to_odometry, a, stamp=0.0)
    own_errors_only(transforms_message, [(parent, child, a), (child, parent, b)], stamp=0.0)


@FUZZ
@given(st.one_of(st.binary(max_size=16), st.lists(st.integers(-300, 300), max_size=6),
                 st.lists(st.floats(allow_nan=True), max_size=4), st.text(max_size=4), st.none(),
                 st.builds(lambda v: np.asarray(v, dtype=np.float32), st.lists(st.floats(-1, 1), max_size=4))),
       st.sampled_from(["numpy", "array", "bytes", "as is"]))
def test_byte_payloads_of_any_kind_read_or_raise_msg_tools_errors(value: Any, kind: str) -> None:
    payload = bytes_of(value, kind) if isinstance(value, bytes) and kind != "as is" else value
    data = own_errors_only(as_uint8, payload)
    if data is not None:
        assert data.dtype == np.uint8 and data.ndim == 1
    own_errors_only(build_message, "sensor_msgs/msg/CompressedImage", {"format": "png", "data": payload})


@FUZZ
@given(st.lists(st.tuples(FLOATS, st.one_of(st.none(), matrices())), max_size=4), st.booleans(),
       encoded_bytes(), st.booleans())
def test_frames_give_poses_or_raise_msg_tools_errors(items: list[tuple[float, np.ndarray | None]],
                                                     skip_missing: bool, jpeg: bytes, with_rgb: bool) -> None:
    frames = [SensorFrame(stamp=stamp, cameras=[], cloud=np.zeros(0, [("x", "f4"), ("y", "f4"), ("z", "f4")]),
                          pose=pose) for stamp, pose in items]
    poses = own_errors_only(poses_from_frames, frames, skip_missing=skip_missing)
    if poses is not None:
        assert poses[0].shape[1:] == (4, 4) and len(poses[0]) == len(poses[1]) == len(poses[2])
    own_errors_only(CameraImage, 0.0, "cam", rgb=np.zeros((1, 1, 3), np.uint8) if with_rgb else None,
                    jpeg=jpeg if with_rgb == bool(len(jpeg) % 2) else None)
