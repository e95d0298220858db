"""Keyframes between robots: what one detector sends its peers, and its wire form.

A robot's detector exports each of its keyframes as a :class:`PeerKeyframe` (stamp, session,
descriptor, pose, the weights that made the descriptor, the compact cloud for verification);
another robot's detector takes it with :meth:`~lcpr_core.detector.LoopDetector.add_peer_keyframe`,
stores it as a map entry of the peer's session and matches it against its own map.

The wire form (:func:`encode_peer_keyframe` / :func:`decode_peer_keyframe`) is one self-describing
byte record, read without anything else::

    b"LCPRKF1\\n" | uint32 LE header length | UTF-8 JSON header | descriptor | pose | cloud

The JSON header holds ``session``, ``stamp`` (s), ``weights_id``, ``dim``, ``pose`` (true when the
16 float64 LE of world_T_lidar, row-major, follow the dim float32 LE of the descriptor) and ``cloud``
(null, or ``{"encoding", "points", "bytes"}``). Cloud encodings (:data:`CLOUD_ENCODINGS`):

- ``i16cm_dz`` (the default): int16 centimetres (the grid the map keeps clouds on, so the peer stores
  exactly the sender's cloud and verifies exactly as it would), each axis delta-coded along the
  point order, the bytes split into low and high planes, zlib-compressed: 3.2-3.4 bytes a point;
- ``i16cm``: the same int16 centimetres uncompressed, 6 bytes a point;
- ``f32``: float32 metres, 12 bytes a point.

``benchmarks/tools/keyframe_bytes.py`` measures the bytes per keyframe and the verdicts of each
form against the local cloud's.
"""
from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InvalidValueError, PeerKeyframeError
from ..verification.clouds import dequantise, quantise

__all__ = ["CLOUD_ENCODINGS", "DEFAULT_ENCODING", "MAGIC", "PeerKeyframe", "PeerKeyframeError",
           "decode_peer_keyframe", "encode_cloud", "decode_cloud", "encode_peer_keyframe"]

MAGIC = b"LCPRKF1\n"
CLOUD_ENCODINGS: tuple[str, ...] = ("i16cm_dz", "i16cm", "f32")
DEFAULT_ENCODING = "i16cm_dz"
_LEN = struct.Struct("<I")
_MAX_HEADER = 1 << 16  # bytes: a header is a few hundred
_ZLIB_LEVEL = 6  # level 9 saves under 1 % more here at twice the time


@dataclass(frozen=True)
class PeerKeyframe:
    """One keyframe as a peer robot sends it.

    ``pose``: world_T_lidar (4 x 4, the peer's own odometry frame and LiDAR), None when unknown: the
    receiver only stitches a peer's keyframes with each other, never with its own. ``cloud``: the compact
    cloud (M x 3 float32 metres, LiDAR frame, on the map's int16 centimetre grid), None when the peer sends
    none (its candidates are then not verified). ``weights_id``: the LCPR weights that made ``descriptor``
    (``Describer.weights_id``); descriptors of other weights are not comparable.
    """

    stamp: float
    session: str
    descriptor: np.ndarray  # (D,) float32
    pose: np.ndarray | None
    weights_id: str
    cloud: np.ndarray | None = None


def encode_cloud(xyz: np.ndarray, encoding: str = DEFAULT_ENCODING) -> bytes:
    """M x 3 metres -> the bytes of ``encoding`` (the int16 ones round to the centimetre grid)."""
    pts = np.asarray(xyz).reshape(-1, 3)
    if encoding == "f32":
        return np.ascontiguousarray(pts, "<f4").tobytes()
    q = quantise(pts)
    if encoding == "i16cm":
        return np.ascontiguousarray(q, "<i2").tobytes()
    if encoding == "i16cm_dz":
        # int16 wraps: the deltas are decoded by the same wrapping sum (exact for every int16 cloud)
        delta = np.diff(q.astype(np.int16), axis=0, prepend=np.zeros((1, 3), np.int16)).astype("<i2")
        planes = np.ascontiguousarray(delta.T).view(np.uint8).reshape(3, -1, 2).transpose(0, 2, 1)
        return zlib.compress(np.ascontiguousarray(planes).tobytes(), _ZLIB_LEVEL)
    raise InvalidValueError(f"cloud encoding {encoding!r}; accepted: {', '.join(CLOUD_ENCODINGS)}")


def decode_cloud(data: bytes, points: int, encoding: str) -> np.ndarray:
    """:func:`encode_cloud`'s bytes of ``points`` points -> M x 3 float32 metres (PeerKeyframeError if they do
    not fit)."""
    if encoding == "f32":
        raw, width = data, 12
    elif encoding == "i16cm":
        raw, width = data, 6
    elif encoding == "i16cm_dz":
        try:
            raw = zlib.decompressobj().decompress(data, 6 * points + 1)
        except zlib.error as err:
            raise PeerKeyframeError(f"the cloud's {len(data)} bytes do not inflate: {err}") from err
        width = 6
    else:
        raise PeerKeyframeError(f"cloud encoding {encoding!r}; accepted: {', '.join(CLOUD_ENCODINGS)}")
    if len(raw) != width * points:
        raise PeerKeyframeError(f"the cloud holds {len(raw)} bytes for {points} points; {encoding} takes "
                                f"{width * points}")
    if encoding == "f32":
        return np.frombuffer(raw, "<f4").reshape(points, 3).astype(np.float32)
    if encoding == "i16cm":
        return dequantise(np.frombuffer(raw, "<i2").reshape(points, 3))
    planes = np.frombuffer(raw, np.uint8).reshape(3, 2, points).transpose(0, 2, 1)
    delta = np.ascontiguousarray(planes).view("<i2").reshape(3, points).T
    q = np.cumsum(delta, axis=0, dtype=np.int16)  # the wrapping sum undoes the wrapping differences
    return dequantise(q)


def encode_peer_keyframe(kf: PeerKeyframe, *, encoding: str = DEFAULT_ENCODING) -> bytes:
    """The wire record of a peer keyframe (module docstring)."""
    desc = np.ascontiguousarray(np.asarray(kf.descriptor).reshape(-1), "<f4")
    cloud_bytes = b""
    cloud: dict[str, Any] | None = None
    if kf.cloud is not None:
        cloud_bytes = encode_cloud(kf.cloud, encoding)
        cloud = {"encoding": encoding, "points": int(np.asarray(kf.cloud).reshape(-1, 3).shape[0]),
                 "bytes": len(cloud_bytes)}
    header = {"session": kf.session, "stamp": float(kf.stamp), "weights_id": kf.weights_id, "dim": int(desc.size),
              "pose": kf.pose is not None, "cloud": cloud}
    head = json.dumps(header, separators=(",", ":")).encode()
    pose = b"" if kf.pose is None else np.asarray(kf.pose, "<f8").reshape(16).tobytes()
    return b"".join((MAGIC, _LEN.pack(len(head)), head, desc.tobytes(), pose, cloud_bytes))


def decode_peer_keyframe(data: bytes) -> PeerKeyframe:
    """A wire record -> the keyframe; PeerKeyframeError names what does not fit. Values are read, not judged:
    :meth:`~lcpr_core.detector.LoopDetector.add_peer_keyframe` refuses sizes, sessions and weights it cannot use."""
    buf = bytes(data)
    if not buf.startswith(MAGIC) or len(buf) < len(MAGIC) + _LEN.size:
        raise PeerKeyframeError(f"{len(buf)} bytes starting {buf[:8]!r}; a peer keyframe record starts {MAGIC!r}")
    at = len(MAGIC)
    (size,) = _LEN.unpack_from(buf, at)
    at += _LEN.size
    if size > _MAX_HEADER or at + size > len(buf):
        raise PeerKeyframeError(f"header of {size} bytes in a record of {len(buf)}; expected at most "
                                f"{min(_MAX_HEADER, len(buf) - at)}")
    try:
        header = json.loads(buf[at:at + size].decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise PeerKeyframeError(f"the record's header is not JSON: {err}") from err
    at += size
    header = _checked_header(header)
    dim, cloud = header["dim"], header["cloud"]
    sizes = [4 * dim, 128 if header["pose"] else 0, 0 if cloud is None else cloud["bytes"]]
    if at + sum(sizes) != len(buf):
        raise PeerKeyframeError(f"the record holds {len(buf) - at} bytes after its header; its header announces "
                                f"{sum(sizes)} (descriptor {sizes[0]}, pose {sizes[1]}, cloud {sizes[2]})")
    desc = np.frombuffer(buf, "<f4", dim, at).astype(np.float32)
    at += sizes[0]
    pose = np.frombuffer(buf, "<f8", 16, at).reshape(4, 4).copy() if header["pose"] else None
    at += sizes[1]
    xyz = None if cloud is None else decode_cloud(buf[at:], cloud["points"], cloud["encoding"])
    return PeerKeyframe(stamp=header["stamp"], session=header["session"], descriptor=desc, pose=pose,
                        weights_id=header["weights_id"], cloud=xyz)


def _checked_header(header: object) -> dict[str, Any]:
    """The record's header with its fields' types checked (PeerKeyframeError naming the first that is wrong)."""
    if not isinstance(header, dict):
        raise PeerKeyframeError(f"the record's header is {type(header).__name__}; expected a JSON object")
    kinds: dict[str, tuple[type, ...]] = {"session": (str,), "stamp": (int, float), "weights_id": (str,),
                                          "dim": (int,), "pose": (bool,), "cloud": (dict, type(None))}
    for key, types in kinds.items():
        value = header.get(key)
        if not isinstance(value, types) or (key != "pose" and isinstance(value, bool)):
            names = " or ".join(t.__name__ for t in types)
            raise PeerKeyframeError(f"header field {key!r} is {value!r}; expected {names}")
    if not 0 <= header["dim"] <= 65536:
        raise PeerKeyframeError(f"header field 'dim' is {header['dim']}; accepted: 0..65536")
    if not math.isfinite(header["stamp"]):
        raise PeerKeyframeError(f"header field 'stamp' is {header['stamp']}; expected a finite time in seconds")
    cloud = header["cloud"]
    if cloud is not None:
        for key in ("points", "bytes"):
            value = cloud.get(key)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 1 << 26:
                raise PeerKeyframeError(f"header field cloud.{key} is {value!r}; expected an integer 0..{1 << 26}")
        if cloud.get("encoding") not in CLOUD_ENCODINGS:
            raise PeerKeyframeError(f"header field cloud.encoding is {cloud.get('encoding')!r}; accepted: "
                                    f"{', '.join(CLOUD_ENCODINGS)}")
    header["stamp"] = float(header["stamp"])
    return header
