"""Build ROS messages from plain values, as rosbags objects or as rclpy objects.

Converters describe a message as nested plain values (dicts for nested messages,
lists of dicts for message sequences, bytes or numpy arrays for numeric arrays) and
:func:`build_message` turns them into

* a ``rosbags`` dataclass from the shared typestore (the default; no ROS needed), or
* an instance of ``msg_type`` when the caller passes a message class, e.g. rclpy's
  ``sensor_msgs.msg.PointCloud2``. Nested rclpy classes are found through the class's
  ``get_fields_and_field_types()``, so nothing from ROS is imported unless the caller
  already handed us a ROS class.
"""
from __future__ import annotations

import importlib
import re
from collections.abc import Mapping
from typing import Any, ClassVar, Protocol, TypeGuard

import numpy as np

from .errors import MessageError
from .types import message_class, typestore

# rosbags Nodetype values (stable across rosbags releases): BASE=1, NAME=2, ARRAY=3, SEQUENCE=4.
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4

_NUMPY_OF_ROS = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}

_RCLPY_NESTED = re.compile(r"([A-Za-z0-9_]+)/(?:msg/)?([A-Za-z0-9_]+)")


class _RosbagsMessage(Protocol):
    """What :func:`_is_rosbags_class` checks a message class for."""

    __msgtype__: ClassVar[str]


def build_message(msgtype: str, values: Mapping[str, Any], *, msg_type: type | None = None) -> Any:
    """A ``msgtype`` message (``"pkg/msg/Name"``) holding ``values``; unspecified fields get defaults."""
    if msg_type is None or _is_rosbags_class(msg_type):
        if msg_type is not None and msg_type.__msgtype__ != msgtype:
            raise MessageError(f"msg_type {msg_type.__msgtype__!r} cannot hold a {msgtype!r} message")
        return _build_rosbags(msgtype, values)
    return _build_foreign(msg_type, values)


def _is_rosbags_class(cls: type) -> TypeGuard[type[_RosbagsMessage]]:
    return hasattr(cls, "__msgtype__") and hasattr(cls, "__dataclass_fields__")


def _build_rosbags(msgtype: str, values: Mapping[str, Any]) -> Any:
    try:
        _consts, fields = typestore().fielddefs[msgtype]
    except KeyError as err:
        raise MessageError(f"message type {msgtype!r} is not in the ROS 2 Jazzy typestore") from err
    known = {name for name, _ in fields}
    unknown = set(values) - known
    if unknown:
        raise MessageError(f"{msgtype} has no field(s) {sorted(unknown)}; its fields are {sorted(known)}")
    kwargs = {}
    for name, desc in fields:
        kwargs[name] = _rosbags_value(desc, values[name]) if name in values else _rosbags_default(desc)
    return message_class(msgtype)(**kwargs)


def _rosbags_value(desc: tuple[Any, Any], value: Any) -> Any:
    kind, detail = int(desc[0]), desc[1]
    if kind == _NAME:
        return _build_rosbags(detail, value) if isinstance(value, Mapping) else value
    if kind == _BASE:
        return value
    (elem_kind, elem_detail), length = detail
    if int(elem_kind) == _NAME:
        return [_build_rosbags(elem_detail, v) if isinstance(v, Mapping) else v for v in value]
    ros_name = elem_detail[0]
    if ros_name == "string":
        return list(value)
    dtype = np.dtype(_NUMPY_OF_ROS[ros_name])
    try:
        if isinstance(value, (bytes, bytearray, memoryview)):
            arr = np.frombuffer(value, dtype=np.uint8).view(dtype) if dtype == np.uint8 else np.frombuffer(value, dtype)
        else:
            arr = np.asarray(value, dtype=dtype).reshape(-1)
    except (TypeError, ValueError, OverflowError) as err:
        raise MessageError(f"an array of {ros_name} values cannot hold {type(value).__name__} {value!r:.60}: "
                           f"{err}") from err
    if int(kind) == _ARRAY and arr.size != length:
        raise MessageError(f"a fixed array of {length} {ros_name} values got {arr.size} values")
    return arr


def _rosbags_default(desc: tuple[Any, Any]) -> Any:
    kind, detail = int(desc[0]), desc[1]
    if kind == _NAME:
        return _build_rosbags(detail, {})
    if kind == _BASE:
        name = detail[0]
        if name == "string":
            return ""
        if name == "bool":
            return False
        return 0.0 if name.startswith("float") else 0
    (elem_kind, elem_detail), length = detail
    if int(elem_kind) == _NAME:
        return [_build_rosbags(elem_detail, {}) for _ in range(length if kind == _ARRAY else 0)]
    if elem_detail[0] == "string":
        return [""] * (length if kind == _ARRAY else 0)
    return np.zeros(length if kind == _ARRAY else 0, dtype=_NUMPY_OF_ROS[elem_detail[0]])


def _build_foreign(msg_type: type, values: Mapping[str, Any]) -> Any:
    """Fill a default-constructed message of a generated ROS class (rclpy) attribute by attribute."""
    msg = msg_type()
    _fill_foreign(msg, values)
    return msg


def _fill_foreign(msg: Any, values: Mapping[str, Any]) -> None:
    field_types = _foreign_field_types(type(msg))
    for name, value in values.items():
        if name not in field_types:
            raise MessageError(f"{type(msg).__name__} has no field {name!r}; its fields are {sorted(field_types)}")
        if isinstance(value, Mapping):
            _fill_foreign(getattr(msg, name), value)
            continue
        if isinstance(value, list) and value and isinstance(value[0], Mapping):
            element_cls = _foreign_class(field_types[name])
            built = []
            for item in value:
                element = element_cls()
                _fill_foreign(element, item)
                built.append(element)
            value = built
        elif isinstance(value, np.ndarray):
            # rclpy turns bytes into array('B') at memcpy speed but checks numpy arrays element-wise.
            value = value.tobytes() if value.dtype == np.uint8 else value.tolist()
        elif isinstance(value, (bytearray, memoryview)):
            value = bytes(value)
        try:
            setattr(msg, name, value)
        except (AssertionError, TypeError, ValueError) as err:
            raise MessageError(f"{type(msg).__name__}.{name} does not accept {type(value).__name__} values") from err


def _foreign_field_types(cls: type) -> dict[str, str]:
    getter = getattr(cls, "get_fields_and_field_types", None)
    if getter is None:
        raise MessageError(
            f"msg_type {cls!r} is neither a rosbags message class nor a generated ROS 2 (rclpy) message class"
        )
    return dict(getter())


def _foreign_class(type_name: str) -> type:
    match = _RCLPY_NESTED.search(type_name)
    if match is None:
        raise MessageError(f"cannot find the message class of field type {type_name!r}")
    package, name = match.groups()
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError) as err:
        raise MessageError(f"cannot import {package}.msg.{name} for field type {type_name!r}") from err


def as_uint8(data: Any) -> np.ndarray:
    """A message's byte payload (numpy array, array.array, bytes, list of ints) as a read-only uint8 view."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            data = np.ascontiguousarray(data).view(np.uint8)
        return data.reshape(-1)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    if hasattr(data, "typecode") and hasattr(data, "itemsize"):  # array.array
        if data.itemsize != 1:
            raise MessageError(f"a byte payload must hold 1-byte items, got array typecode {data.typecode!r}")
        return np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)
    try:
        return np.asarray(data, dtype=np.uint8).reshape(-1)
    except (TypeError, ValueError, OverflowError) as err:
        raise MessageError(f"cannot read a byte payload from {type(data).__name__}") from err
