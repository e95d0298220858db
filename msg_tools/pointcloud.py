"""sensor_msgs/PointCloud2 <-> numpy structured arrays.

Reading keeps the message's point layout: the returned dtype has one field per
PointField (``count > 1`` becomes a subarray field), the message's offsets and
``itemsize == point_step``, in native byte order. Writing uses the array's dtype as
the layout, so a read-write roundtrip reproduces the message's fields exactly.
"""
from __future__ import annotations

import sys
from typing import Any

import numpy as np

from .build import as_uint8, build_message
from .errors import MissingFieldError, PointCloudDataError, PointCloudError, PointFieldLayoutError
from .pointfields import dtype_to_field_specs, fields_to_dtype, native_dtype, read_field_specs
from .types import StampLike, header_values

XYZ = ("x", "y", "z")


def pointcloud2_to_array(msg: Any, *, keep_nonfinite: bool = True, require_xyz: bool = False) -> np.ndarray:
    """A PointCloud2 (rosbags or rclpy) -> native-endian structured array.

    Shape is ``(height, width)`` for organised clouds (height > 1) and ``(width,)``
    otherwise. With ``keep_nonfinite=False`` points whose x, y or z is NaN/inf are
    dropped and the result is 1-D. Trailing bytes beyond ``row_step * height`` are
    ignored; a shorter buffer raises :class:`PointCloudDataError`.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    negative = {k: v for k, v in (("height", height), ("width", width), ("point_step", point_step),
                                  ("row_step", row_step)) if v < 0}
    if negative:
        raise PointFieldLayoutError(f"{negative} cannot be negative; accepted: sizes of 0 or more")
    stored = fields_to_dtype(read_field_specs(msg.fields), point_step=point_step, is_bigendian=bool(msg.is_bigendian))
    names = stored.names or ()
    missing = [n for n in XYZ if n not in names]
    if missing and (require_xyz or not keep_nonfinite):
        why = "require_xyz=True" if require_xyz else "keep_nonfinite=False needs x, y and z to judge points"
        raise MissingFieldError(f"the cloud has no field(s) {missing} ({why}); its fields are {list(names)}")
    if width and height and point_step == 0:
        raise PointFieldLayoutError(f"point_step 0 with {width} x {height} points; accepted: point_step >= 1, "
                                    "the bytes of one point")
    if width and height and row_step < width * point_step:
        raise PointFieldLayoutError(
            f"row_step {row_step} is smaller than width * point_step = {width} * {point_step}; rows would overlap"
        )
    data = as_uint8(msg.data)
    needed = row_step * height
    if data.size < needed:
        raise PointCloudDataError(
            f"data holds {data.size} bytes, fewer than row_step * height = {row_step} * {height} = {needed}"
        )
    native = native_dtype(stored)
    shape = (height, width)
    fields: dict[str, Any] = dict(stored.fields or {})
    dense = row_step == width * point_step and sum(fields[n][0].itemsize for n in names) == point_step
    if height and width and dense and native == stored:  # already native, no padding: one copy of the buffer
        # the bytes copied, then viewed: a structured copy goes point by point (0.4 ms against 0.02 for 29k
        # 22-byte points, AMD EPYC)
        out = data[:height * width * point_step].copy().view(stored).reshape(shape)
    else:
        out = _copy_fields(data, stored, native, shape, row_step)
    if not keep_nonfinite:
        return out[finite_mask(out)].reshape(-1)
    return out if height > 1 else out.reshape(-1)


def _copy_fields(data: np.ndarray, stored: np.dtype, native: np.dtype, shape: tuple[int, int],
                 row_step: int) -> np.ndarray:
    """Field by field into a zeroed native array: byte order converted, padding left zero."""
    out = np.zeros(shape, dtype=native)
    height, width = shape
    point_step = stored.itemsize
    names = stored.names or ()
    if height and width:
        view = np.ndarray(shape, dtype=stored, buffer=data, offset=0, strides=(row_step, point_step))
        for name in names:
            out[name] = view[name]
    return out


def finite_mask(cloud: np.ndarray) -> np.ndarray:
    """True where x, y and z (every element, for subarray fields) are finite."""
    mask = np.ones(cloud.shape, dtype=bool)
    for name in XYZ:
        finite = np.isfinite(cloud[name])
        if finite.ndim > cloud.ndim:  # subarray field: every element must be finite
            finite = finite.all(axis=tuple(range(cloud.ndim, finite.ndim)))
        mask &= finite
    return mask


def array_to_pointcloud2(
    arr: np.ndarray, *, frame_id: str, stamp: StampLike, msg_type: type | None = None
) -> Any:
    """A structured array (1-D, or 2-D = organised) -> PointCloud2.

    The array's dtype is the point layout: names, offsets and ``itemsize`` become the
    PointFields and ``point_step``; data is written in native byte order. ``msg_type``
    (e.g. rclpy's ``sensor_msgs.msg.PointCloud2``) selects the message class; by
    default a rosbags message is built.
    """
    if not isinstance(arr, np.ndarray):
        raise PointCloudError(f"expected a numpy structured array, got {type(arr).__name__}")
    if arr.ndim not in (1, 2):
        raise PointCloudError(f"a point array must be 1-D (unorganised) or 2-D (organised), got shape {arr.shape}")
    specs = dtype_to_field_specs(arr.dtype)
    native = native_dtype(arr.dtype)
    if arr.dtype != native:
        converted = np.zeros(arr.shape, dtype=native)
        for name in native.names or ():
            converted[name] = arr[name]
        arr = converted
    arr = np.ascontiguousarray(arr)
    height, width = arr.shape if arr.ndim == 2 else (1, arr.shape[0])
    names = native.names or ()
    dense = bool(finite_mask(arr).all()) if all(n in names for n in XYZ) else True
    values = {
        "header": header_values(frame_id=frame_id, stamp=stamp),
        "height": height,
        "width": width,
        "fields": [spec.values() for spec in specs],
        "is_bigendian": sys.byteorder == "big",
        "point_step": native.itemsize,
        "row_step": native.itemsize * width,
        "data": arr.reshape(-1).view(np.uint8),
        "is_dense": dense,
    }
    return build_message("sensor_msgs/msg/PointCloud2", values, msg_type=msg_type)


def xyz_cloud(points: np.ndarray, **extra: np.ndarray) -> np.ndarray:
    """N x 3 coordinates (+ named per-point columns) -> a packed structured cloud (x, y, z float32, ...)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise PointCloudError(f"points must be N x 3 (or wider), got shape {pts.shape}")
    if pts.dtype.kind not in "iuf":
        raise PointCloudError(f"points must be integers or floats, got {pts.dtype}; nothing is cast silently")
    columns: dict[str, np.ndarray] = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}
    for name, values in extra.items():
        values = np.asarray(values)
        if values.shape[:1] != (pts.shape[0],):
            raise PointCloudError(f"column {name!r} has shape {values.shape}; expected {pts.shape[0]} rows")
        columns[name] = values
    dtype = np.dtype([(n, np.float32 if n in XYZ else v.dtype, v.shape[1:]) for n, v in columns.items()])
    out = np.zeros(pts.shape[0], dtype=dtype)
    for name, values in columns.items():
        out[name] = values
    return out
