"""PointCloud2 <-> structured arrays: property-based roundtrips over layouts, and every error path."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msg_tools import (
    MissingFieldError,
    PointCloudDataError,
    PointFieldDatatypeError,
    PointFieldLayoutError,
    array_to_pointcloud2,
    pointcloud2_to_array,
)
from msg_tools.types import message_class

DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
PointCloud2 = message_class("sensor_msgs/msg/PointCloud2")
PointField = message_class("sensor_msgs/msg/PointField")
Header = message_class("std_msgs/msg/Header")
Time = message_class("builtin_interfaces/msg/Time")


@dataclass
class Layout:
    fields: list[tuple[str, int, int, int]]  # name, offset, datatype, count
    point_step: int
    height: int
    width: int
    row_pad: int
    bigendian: bool
    seed: int


@st.composite
def layouts(draw: st.DrawFn) -> Layout:
    names = draw(st.lists(st.sampled_from(["x", "y", "z", "intensity", "ring", "t", "label", "rgb", "n"]),
                          min_size=1, max_size=6, unique=True))
    fields, offset = [], 0
    for name in names:
        datatype = draw(st.integers(1, 8))
        count = draw(st.integers(1, 3))
        offset += draw(st.integers(0, 3))  # gap before the field
        fields.append((name, offset, datatype, count))
        offset += np.dtype(DTYPES[datatype]).itemsize * count
    if draw(st.booleans()):
        fields.reverse()  # offsets need not follow field order
    return Layout(
        fields=fields,
        point_step=offset + draw(st.integers(0, 5)),
        height=draw(st.integers(1, 3)),
        width=draw(st.integers(0, 5)),
        row_pad=draw(st.integers(0, 7)),
        bigendian=draw(st.booleans()),
        seed=draw(st.integers(0, 2**31)),
    )


def _values(layout: Layout) -> dict[str, np.ndarray]:
    """Native values per field, floats including NaN and inf."""
    rng = np.random.default_rng(layout.seed)
    out = {}
    for name, _offset, datatype, count in layout.fields:
        shape = (layout.height, layout.width) + ((count,) if count > 1 else ())
        dtype = np.dtype(DTYPES[datatype])
        if dtype.kind == "f":
            v = rng.normal(scale=100.0, size=shape).astype(dtype)
            v[rng.random(shape) < 0.1] = np.nan
            v[rng.random(shape) < 0.05] = np.inf
        else:
            info = np.iinfo(dtype)
            v = rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)
        out[name] = v
    return out


def _message(layout: Layout, values: dict[str, np.ndarray]) -> Any:
    """Pack values byte by byte, independently of the code under test."""
    order: Literal[">", "<"] = ">" if layout.bigendian else "<"
    row_step = layout.point_step * layout.width + layout.row_pad
    buf = bytearray(row_step * layout.height)
    for r in range(layout.height):
        for c in range(layout.width):
            base = r * row_step + c * layout.point_step
            for name, offset, datatype, _count in layout.fields:
                raw = np.asarray(values[name][r, c]).astype(np.dtype(DTYPES[datatype]).newbyteorder(order)).tobytes()
                buf[base + offset: base + offset + len(raw)] = raw
    fields = [PointField(name=n, offset=o, datatype=d, count=k) for n, o, d, k in layout.fields]
    return PointCloud2(
        header=Header(stamp=Time(sec=1, nanosec=2), frame_id="lidar"), height=layout.height, width=layout.width,
        fields=fields, is_bigendian=layout.bigendian, point_step=layout.point_step, row_step=row_step,
        data=np.frombuffer(bytes(buf), dtype=np.uint8), is_dense=False,
    )


def _assert_fields_equal(arr: np.ndarray, values: dict[str, np.ndarray], shape: tuple[int, ...]) -> None:
    assert arr.dtype.names is not None
    assert set(arr.dtype.names) == set(values)
    for name, expected in values.items():
        got = arr[name]
        assert got.dtype == expected.dtype and got.dtype.isnative
        assert np.array_equal(got, expected.reshape(shape + expected.shape[2:]), equal_nan=expected.dtype.kind == "f")


@settings(max_examples=60, deadline=None)
@given(layouts())
def test_any_field_layout_reads_back_its_values_and_roundtrips(layout: Layout) -> None:
    values = _values(layout)
    msg = _message(layout, values)
    arr = pointcloud2_to_array(msg)
    shape = (layout.height, layout.width) if layout.height > 1 else (layout.width,)
    assert arr.shape == shape
    assert arr.dtype.itemsize == layout.point_step
    _assert_fields_equal(arr, values, shape)

    again = array_to_pointcloud2(arr, frame_id="lidar", stamp=1.5)
    assert [(f.name, f.offset, f.datatype, f.count) for f in again.fields] == layout.fields
    assert again.point_step == layout.point_step and again.height == layout.height
    _assert_fields_equal(pointcloud2_to_array(again), values, shape)


@settings(max_examples=30, deadline=None)
@given(layouts())
def test_dropping_nonfinite_points_keeps_exactly_the_finite_ones(layout: Layout) -> None:
    names = [f[0] for f in layout.fields]
    if not {"x", "y", "z"} <= set(names):
        layout.fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 8, 1)]
        layout.point_step = max(layout.point_step, 16)
    values = _values(layout)
    arr = pointcloud2_to_array(_message(layout, values), keep_nonfinite=False)
    finite = np.ones((layout.height, layout.width), dtype=bool)
    for axis in "xyz":
        ok = np.isfinite(values[axis])
        finite &= ok.all(axis=2) if ok.ndim == 3 else ok
    assert arr.shape == (int(finite.sum()),)
    for name, expected in values.items():
        assert np.array_equal(arr[name], expected[finite], equal_nan=True)


def test_a_padded_big_endian_cloud_comes_back_native() -> None:
    layout = Layout([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 16, 7, 1), ("ring", 20, 4, 1)],
                    point_step=32, height=1, width=4, row_pad=3, bigendian=True, seed=3)
    arr = pointcloud2_to_array(_message(layout, _values(layout)))
    assert arr.dtype.fields is not None and arr.dtype.names is not None
    assert arr.dtype.fields["intensity"][1] == 16 and all(arr.dtype[n].isnative for n in arr.dtype.names)


def test_an_organised_array_makes_an_organised_cloud() -> None:
    arr = np.zeros((2, 3), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    arr["x"] = np.arange(6).reshape(2, 3)
    msg = array_to_pointcloud2(arr, frame_id="l", stamp=0.0)
    assert (msg.height, msg.width, msg.row_step) == (2, 3, 36)
    assert np.array_equal(pointcloud2_to_array(msg), arr)


def _simple(**overrides: object) -> Any:
    layout = Layout([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)], 12, 1, 2, 0, False, 0)
    msg = _message(layout, _values(layout))
    for key, value in overrides.items():
        setattr(msg, key, value)
    return msg


def test_data_shorter_than_row_step_times_height_is_refused() -> None:
    msg = _simple()
    msg.data = msg.data[:-1]
    with pytest.raises(PointCloudDataError, match="23 bytes, fewer than row_step \\* height"):
        pointcloud2_to_array(msg)


def test_overlapping_fields_are_refused() -> None:
    msg = _simple(fields=[PointField(name="x", offset=0, datatype=7, count=1),
                          PointField(name="y", offset=2, datatype=7, count=1)])
    with pytest.raises(PointFieldLayoutError, match="'x' and 'y' overlap"):
        pointcloud2_to_array(msg)


def test_a_field_beyond_point_step_is_refused() -> None:
    msg = _simple(fields=[PointField(name="x", offset=8, datatype=8, count=1)])
    with pytest.raises(PointFieldLayoutError, match=r"bytes \[8, 16\) but point_step is 12"):
        pointcloud2_to_array(msg)


def test_an_unknown_datatype_is_refused_with_the_accepted_ones() -> None:
    msg = _simple(fields=[PointField(name="x", offset=0, datatype=9, count=1)])
    with pytest.raises(PointFieldDatatypeError, match="datatype 9; accepted datatypes: 1 \\(INT8\\)"):
        pointcloud2_to_array(msg)


def test_a_missing_coordinate_is_refused_when_required() -> None:
    msg = _simple(fields=[PointField(name="x", offset=0, datatype=7, count=1),
                          PointField(name="y", offset=4, datatype=7, count=1)])
    assert pointcloud2_to_array(msg).dtype.names == ("x", "y")
    with pytest.raises(MissingFieldError, match=r"no field\(s\) \['z'\]"):
        pointcloud2_to_array(msg, require_xyz=True)
    with pytest.raises(MissingFieldError):
        pointcloud2_to_array(msg, keep_nonfinite=False)


def test_rows_shorter_than_a_row_of_points_are_refused() -> None:
    with pytest.raises(PointFieldLayoutError, match="row_step 20 is smaller"):
        pointcloud2_to_array(_simple(row_step=20))


def test_arrays_without_a_ros_datatype_are_refused() -> None:
    with pytest.raises(PointFieldDatatypeError, match="dtype complex64"):
        array_to_pointcloud2(np.zeros(2, dtype=[("x", "c8")]), frame_id="l", stamp=0.0)
    with pytest.raises(PointFieldLayoutError, match="structured dtype"):
        array_to_pointcloud2(np.zeros((2, 3), dtype=np.float32), frame_id="l", stamp=0.0)


def test_an_rclpy_point_cloud_converts_both_ways() -> None:
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    cloud = np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2", (2,))])
    cloud["x"] = [1, 2, 3, 4]
    cloud["ring"][:, 1] = 7
    msg = array_to_pointcloud2(cloud, frame_id="velodyne", stamp=12.25, msg_type=sensor_msgs.PointCloud2)
    assert isinstance(msg, sensor_msgs.PointCloud2)
    assert (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == ("velodyne", 12, 250_000_000)
    assert np.array_equal(pointcloud2_to_array(msg), cloud)

    hand_made = sensor_msgs.PointCloud2()  # built the way a ROS node would, data as array('B')
    hand_made.height, hand_made.width, hand_made.point_step, hand_made.row_step = 1, 2, 8, 16
    hand_made.fields = [sensor_msgs.PointField(name="x", offset=0, datatype=7, count=1),
                        sensor_msgs.PointField(name="y", offset=4, datatype=7, count=1)]
    hand_made.data = np.array([[1.0, 2.0], [3.0, 4.0]], dtype="<f4").tobytes()
    arr = pointcloud2_to_array(hand_made)
    assert arr["x"].tolist() == [1.0, 3.0] and arr["y"].tolist() == [2.0, 4.0]


def test_a_dense_native_cloud_is_read_with_one_copy_and_equals_the_field_by_field_read():
    from msg_tools.pointcloud import _copy_fields
    from msg_tools.pointfields import fields_to_dtype, read_field_specs

    arr = np.zeros(500, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    for k, name in enumerate(("x", "y", "z", "intensity")):
        arr[name] = np.arange(500) * (k + 1)
    msg = array_to_pointcloud2(arr, frame_id="l", stamp=0.0)
    fast = pointcloud2_to_array(msg)
    stored = fields_to_dtype(read_field_specs(msg.fields), point_step=int(msg.point_step), is_bigendian=False)
    slow = _copy_fields(np.frombuffer(bytes(msg.data), np.uint8), stored, stored, (1, 500), int(msg.row_step))
    assert np.array_equal(fast, slow.reshape(-1)) and np.array_equal(fast, arr)
    assert not np.shares_memory(fast, np.asarray(msg.data))  # a copy: the message's buffer may be reused


def test_points_of_zero_bytes_are_refused_naming_the_point_step() -> None:
    """Found by fuzzing: a cloud without fields, point_step 0 and some data let numpy's ValueError out."""
    msg = _simple(fields=[], point_step=0, row_step=0, width=3)
    with pytest.raises(PointFieldLayoutError, match="point_step 0"):
        pointcloud2_to_array(msg)


def test_an_empty_cloud_without_fields_reads_as_no_points() -> None:
    msg = _simple(fields=[], point_step=0, row_step=0, width=0, height=0, data=np.zeros(0, np.uint8))
    assert pointcloud2_to_array(msg).size == 0
