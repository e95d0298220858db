"""Header stamps read straight from serialised CDR bytes, without deserialising the message.

Every message type msg_tools synchronises (PointCloud2, Image, CompressedImage,
CameraInfo, Odometry) starts with a ``std_msgs/Header``, whose stamp (int32 sec,
uint32 nanosec) follows the 4-byte CDR encapsulation header.
"""
from __future__ import annotations

import struct

from ..errors import BagError

_LITTLE = struct.Struct("<iI")
_BIG = struct.Struct(">iI")


def header_stamp_ns(raw: bytes | memoryview) -> int:
    """Header stamp (ns) of a serialised message that starts with a std_msgs/Header."""
    if len(raw) < 12:
        raise BagError(f"a serialised message of {len(raw)} bytes is too short to hold a header stamp (12 bytes)")
    kind = bytes(raw[:2])
    if kind == b"\x00\x01":
        sec, nanosec = _LITTLE.unpack_from(raw, 4)
    elif kind == b"\x00\x00":
        sec, nanosec = _BIG.unpack_from(raw, 4)
    else:
        raise BagError(f"CDR encapsulation {kind!r} is not supported; accepted: plain CDR big/little endian")
    return sec * 1_000_000_000 + nanosec
