"""sensor_msgs/CompressedImage (JPEG, PNG) <-> numpy arrays and encoded bytes.

The ``format`` field is written as plain ``"jpeg"`` or ``"png"``; when reading, the
bytes' own signature decides the codec, and a ``format`` naming the other codec is an
error rather than a guess.
"""
from __future__ import annotations

import io
from typing import Any, Literal

import numpy as np
from PIL import Image as PILImage

from .build import as_uint8, build_message
from .errors import ImageEncodingError, ImageError, ImageLayoutError
from .types import StampLike, header_values

JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FORMATS = ("jpeg", "png")


def sniff_format(data: bytes) -> str:
    """``"jpeg"`` or ``"png"`` from the leading bytes, else :class:`ImageEncodingError`."""
    if data[:3] == JPEG_MAGIC:
        return "jpeg"
    if data[:8] == PNG_MAGIC:
        return "png"
    raise ImageEncodingError(
        f"compressed bytes start with {bytes(data[:8])!r}, which is neither JPEG ({JPEG_MAGIC!r}) "
        f"nor PNG ({PNG_MAGIC!r}); accepted formats: {', '.join(FORMATS)}"
    )


def compressed_bytes(msg: Any) -> bytes:
    """The encoded image bytes of a CompressedImage, untouched."""
    return as_uint8(msg.data).tobytes()


def compressed_to_array(msg: Any) -> np.ndarray:
    """A CompressedImage -> H x W x 3 uint8 RGB, or H x W mono (uint8; uint16 for 16-bit PNG)."""
    data = compressed_bytes(msg)
    actual = sniff_format(data)
    declared = str(getattr(msg, "format", "")).lower()
    mentions = [f for f in FORMATS if f in declared or (f == "jpeg" and "jpg" in declared)]
    if mentions and actual not in mentions:
        raise ImageEncodingError(f"format {msg.format!r} names {mentions[0]} but the bytes are {actual}")
    return decode_image_bytes(data)


def decode_image_bytes(data: bytes) -> np.ndarray:
    """JPEG/PNG bytes -> RGB uint8 (colour) or mono (grey) array."""
    sniff_format(data)
    try:
        with PILImage.open(io.BytesIO(data)) as img:
            img.load()
            mode = img.mode
            if mode == "L":
                return np.asarray(img, dtype=np.uint8).copy()
            if mode.startswith("I;16"):
                return np.asarray(img).astype(np.uint16)
            if mode == "1":
                return np.asarray(img.convert("L"), dtype=np.uint8).copy()
            return np.asarray(img.convert("RGB"), dtype=np.uint8).copy()
    except (OSError, ValueError) as err:
        raise ImageError(f"cannot decode {len(data)} compressed image bytes: {err}") from err


def encode_image(arr: np.ndarray, *, format: Literal["jpeg", "png"] = "jpeg", quality: int = 90) -> bytes:
    """H x W x 3 uint8 RGB or H x W mono (uint8; uint16 for PNG) -> JPEG/PNG bytes."""
    if format not in FORMATS:
        raise ImageEncodingError(f"format {format!r} is not supported; accepted: {', '.join(FORMATS)}")
    arr = np.asarray(arr)
    colour = arr.ndim == 3 and arr.shape[2] == 3 and arr.dtype == np.uint8
    mono = arr.ndim == 2 and (arr.dtype == np.uint8 or (arr.dtype == np.uint16 and format == "png"))
    if not (colour or mono):
        raise ImageLayoutError(
            f"cannot encode a {arr.dtype} array of shape {arr.shape} as {format}; accepted: H x W x 3 uint8 RGB, "
            "H x W uint8, or H x W uint16 (png only)"
        )
    img = PILImage.fromarray(np.ascontiguousarray(arr))
    if not 1 <= int(quality) <= 100:
        raise ImageEncodingError(f"JPEG quality {quality} is outside the accepted range 1..100")
    buffer = io.BytesIO()
    if format == "jpeg":
        img.save(buffer, format="JPEG", quality=int(quality))
    else:
        img.save(buffer, format="PNG")
    return buffer.getvalue()


def array_to_compressed(
    arr: np.ndarray,
    *,
    format: Literal["jpeg", "png"] = "jpeg",
    quality: int = 90,
    frame_id: str,
    stamp: StampLike,
    msg_type: type | None = None,
) -> Any:
    """Encode an RGB/mono array as a JPEG or PNG CompressedImage."""
    data = encode_image(arr, format=format, quality=quality)
    return _compressed(data, format, frame_id=frame_id, stamp=stamp, msg_type=msg_type)


def compressed_from_bytes(data: bytes, *, frame_id: str, stamp: StampLike, msg_type: type | None = None) -> Any:
    """Wrap already encoded JPEG or PNG bytes in a CompressedImage without re-encoding."""
    return _compressed(bytes(data), sniff_format(data), frame_id=frame_id, stamp=stamp, msg_type=msg_type)


def compressed_jpeg_bytes(data: bytes, *, frame_id: str, stamp: StampLike, msg_type: type | None = None) -> Any:
    """Wrap original JPEG bytes (e.g. a dataset's camera file) in a CompressedImage, byte for byte."""
    if sniff_format(data) != "jpeg":
        raise ImageEncodingError(f"expected JPEG bytes (starting {JPEG_MAGIC!r}), got {bytes(data[:8])!r}")
    return _compressed(bytes(data), "jpeg", frame_id=frame_id, stamp=stamp, msg_type=msg_type)


def _compressed(data: bytes, fmt: str, *, frame_id: str, stamp: StampLike, msg_type: type | None) -> Any:
    values = {
        "header": header_values(frame_id=frame_id, stamp=stamp),
        "format": fmt,
        "data": np.frombuffer(data, dtype=np.uint8),
    }
    return build_message("sensor_msgs/msg/CompressedImage", values, msg_type=msg_type)
