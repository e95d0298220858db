"""The message typestore msg_tools uses, and exact conversions of ROS time stamps.

Messages are built and (de)serialised with the ``rosbags`` typestore of ROS 2 Jazzy,
so no ROS installation is needed. Stamps travel as :class:`Stamp` (whole seconds and
nanoseconds, exact) or as float seconds; conversions round to the nearest nanosecond (exact rational
arithmetic), so ``stamp_to_sec(sec_to_stamp(t)) == t`` for every epoch-like float
(t >= 2**23 s, where doubles are coarser than 1 ns) and is within 0.5 ns otherwise.
Use :class:`Stamp` (or integer nanoseconds) where dataset stamps must stay exact.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Protocol, runtime_checkable

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from .errors import StampError

NS_PER_S = 1_000_000_000
_SEC_MIN, _SEC_MAX = -(2**31), 2**31 - 1  # builtin_interfaces/Time.sec is int32


@functools.cache
def typestore() -> Typestore:
    """The ROS 2 Jazzy typestore (created once, shared by every module)."""
    return get_typestore(Stores.ROS2_JAZZY)


def message_class(msgtype: str) -> type:
    """The rosbags class of a type name such as ``"sensor_msgs/msg/Image"``."""
    return typestore().types[msgtype]


@runtime_checkable
class TimeLike(Protocol):
    """Anything with ``sec`` and ``nanosec`` (rclpy's and rosbags' ``builtin_interfaces/Time``)."""

    sec: int
    nanosec: int


@dataclass(frozen=True, order=True)
class Stamp:
    """An exact ROS time: whole seconds and nanoseconds (0 <= nanosec < 1e9)."""

    sec: int
    nanosec: int

    def __post_init__(self) -> None:
        if not 0 <= self.nanosec < NS_PER_S:
            raise StampError(f"nanosec={self.nanosec} is outside the accepted range [0, {NS_PER_S})")
        if not _SEC_MIN <= self.sec <= _SEC_MAX:
            raise StampError(f"sec={self.sec} is outside the int32 range [{_SEC_MIN}, {_SEC_MAX}] of a ROS stamp")

    @classmethod
    def from_ns(cls, ns: int) -> Stamp:
        sec, nanosec = divmod(int(ns), NS_PER_S)
        return cls(sec, nanosec)

    @classmethod
    def from_sec(cls, t: float) -> Stamp:
        return sec_to_stamp(t)

    @property
    def ns(self) -> int:
        return self.sec * NS_PER_S + self.nanosec

    def to_sec(self) -> float:
        return self.ns / NS_PER_S  # int / int is correctly rounded


#: What stamp arguments accept: float (or int) seconds, a :class:`Stamp`, or a Time message.
StampLike = float | int | Stamp | TimeLike


def sec_to_stamp(t: float) -> Stamp:
    """Float seconds -> the nearest nanosecond :class:`Stamp` (exact rational rounding)."""
    if isinstance(t, bool) or not isinstance(t, (int, float)):
        raise StampError(f"a stamp in seconds must be a float or int, got {type(t).__name__} {t!r}")
    if not math.isfinite(t):
        raise StampError(f"stamp {t!r} is not finite; accepted: finite seconds")
    return Stamp.from_ns(round(Fraction(t) * NS_PER_S))


def ns_to_stamp(ns: int) -> Stamp:
    return Stamp.from_ns(ns)


def as_stamp(value: StampLike) -> Stamp:
    """Normalise any accepted stamp form to a :class:`Stamp`."""
    if isinstance(value, Stamp):
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return sec_to_stamp(value)
    if hasattr(value, "sec") and hasattr(value, "nanosec"):
        return Stamp(int(value.sec), int(value.nanosec))
    raise StampError(
        f"cannot use {type(value).__name__} {value!r} as a stamp; accepted: float seconds, Stamp, "
        "or a Time message with sec/nanosec"
    )


def _time_of(header_or_time: Any) -> Stamp:
    """A Header (has ``stamp``) or a Time (has ``sec``/``nanosec``) -> Stamp."""
    inner = getattr(header_or_time, "stamp", header_or_time)
    return as_stamp(inner)


def stamp_to_ns(header_or_time: Any) -> int:
    """Exact integer nanoseconds of a Header, a Time message or a :class:`Stamp`."""
    return _time_of(header_or_time).ns


def stamp_to_sec(header_or_time: Any) -> float:
    """Float seconds of a Header, a Time message or a :class:`Stamp` (correctly rounded)."""
    return _time_of(header_or_time).to_sec()


def header_values(*, frame_id: str, stamp: StampLike) -> dict[str, Any]:
    """The nested values of a ``std_msgs/Header`` for :func:`msg_tools.build.build_message`."""
    s = as_stamp(stamp)
    return {"stamp": {"sec": s.sec, "nanosec": s.nanosec}, "frame_id": str(frame_id)}
