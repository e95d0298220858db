"""sensor_msgs/Image <-> numpy arrays, plus RGB and metric-depth views of an image message."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from .build import as_uint8, build_message
from .errors import ImageEncodingError, ImageLayoutError
from .types import StampLike, header_values


@dataclass(frozen=True)
class Encoding:
    """How one ``sensor_msgs/image_encodings`` name lays out a pixel."""

    dtype: np.dtype
    channels: int


#: Supported encodings. ``image_to_array`` returns exactly this dtype and channel count.
ENCODINGS: dict[str, Encoding] = {
    "rgb8": Encoding(np.dtype(np.uint8), 3),
    "bgr8": Encoding(np.dtype(np.uint8), 3),
    "rgba8": Encoding(np.dtype(np.uint8), 4),
    "bgra8": Encoding(np.dtype(np.uint8), 4),
    "mono8": Encoding(np.dtype(np.uint8), 1),
    "mono16": Encoding(np.dtype(np.uint16), 1),
    "8UC1": Encoding(np.dtype(np.uint8), 1),
    "8UC3": Encoding(np.dtype(np.uint8), 3),
    "16UC1": Encoding(np.dtype(np.uint16), 1),  # depth in millimetres (0 = unknown)
    "16SC1": Encoding(np.dtype(np.int16), 1),
    "32SC1": Encoding(np.dtype(np.int32), 1),
    "32FC1": Encoding(np.dtype(np.float32), 1),  # depth in metres (NaN/0 = unknown)
    "64FC1": Encoding(np.dtype(np.float64), 1),
}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", "8UC1", "8UC3")
DEPTH_ENCODINGS = ("16UC1", "32FC1")


def encoding_of(name: str) -> Encoding:
    """The layout of an encoding name, or :class:`ImageEncodingError` listing the accepted names."""
    try:
        return ENCODINGS[name]
    except KeyError as err:
        raise ImageEncodingError(
            f"image encoding {name!r} is not supported; accepted: {', '.join(ENCODINGS)}"
        ) from err


def image_to_array(msg: Any) -> np.ndarray:
    """An Image (rosbags or rclpy) -> H x W (1 channel) or H x W x C array in the encoding's dtype.

    Row padding (``step`` > width * pixel size) is dropped and multi-byte pixels are
    returned in native byte order whatever ``is_bigendian`` says.
    """
    enc = encoding_of(str(msg.encoding))
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    stored = enc.dtype.newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = width * enc.channels * enc.dtype.itemsize
    if step < row_bytes:
        raise ImageLayoutError(
            f"step {step} is smaller than width * channels * bytes = {width} * {enc.channels} * "
            f"{enc.dtype.itemsize} = {row_bytes} for encoding {msg.encoding!r}"
        )
    data = as_uint8(msg.data)
    if data.size < step * height:
        raise ImageLayoutError(f"data holds {data.size} bytes, fewer than step * height = {step} * {height}")
    shape = (height, width, enc.channels)
    if height and width:
        strides = (step, enc.channels * enc.dtype.itemsize, enc.dtype.itemsize)
        view = np.ndarray(shape, dtype=stored, buffer=data, offset=0, strides=strides)
        out = view.astype(enc.dtype)  # copies, contiguous, native byte order
    else:
        out = np.zeros(shape, dtype=enc.dtype)
    return out[:, :, 0] if enc.channels == 1 else out


def array_to_image(
    arr: np.ndarray, *, encoding: str, frame_id: str, stamp: StampLike, msg_type: type | None = None
) -> Any:
    """An H x W (x C) array -> Image. The array's dtype and channels must match ``encoding`` exactly."""
    enc = encoding_of(encoding)
    arr = np.asarray(arr)
    if arr.ndim == 3 and enc.channels == 1 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    expected = "H x W" if enc.channels == 1 else f"H x W x {enc.channels}"
    if arr.ndim != (2 if enc.channels == 1 else 3) or (enc.channels > 1 and arr.shape[2] != enc.channels):
        raise ImageLayoutError(f"encoding {encoding!r} needs an {expected} array, got shape {arr.shape}")
    if arr.dtype.newbyteorder("=") != enc.dtype:
        raise ImageEncodingError(
            f"encoding {encoding!r} holds {enc.dtype} pixels but the array is {arr.dtype}; "
            f"convert it first (nothing is cast silently)"
        )
    data = np.ascontiguousarray(arr, dtype=enc.dtype)  # native byte order
    height, width = data.shape[:2]
    values = {
        "header": header_values(frame_id=frame_id, stamp=stamp),
        "height": height,
        "width": width,
        "encoding": encoding,
        "is_bigendian": int(sys.byteorder == "big" and enc.dtype.itemsize > 1),
        "step": width * enc.channels * enc.dtype.itemsize,
        "data": data.reshape(-1).view(np.uint8),
    }
    return build_message("sensor_msgs/msg/Image", values, msg_type=msg_type)


def image_to_rgb(msg: Any) -> np.ndarray:
    """An Image in a colour or mono encoding, or a CompressedImage -> H x W x 3 uint8 RGB.

    mono16 keeps its 8 most significant bits. Depth and other non-colour encodings
    raise :class:`ImageEncodingError`.
    """
    if not hasattr(msg, "encoding") and hasattr(msg, "format"):
        from .compressed import compressed_to_array  # local: compressed imports image helpers

        decoded = compressed_to_array(msg)
        return _to_rgb(decoded, "rgb8" if decoded.ndim == 3 else ("mono16" if decoded.dtype == np.uint16 else "mono8"))
    encoding = str(msg.encoding)
    if encoding not in COLOUR_ENCODINGS:
        encoding_of(encoding)  # unknown names get the full list
        raise ImageEncodingError(
            f"encoding {encoding!r} is not a colour or mono encoding; accepted: {', '.join(COLOUR_ENCODINGS)}"
        )
    return _to_rgb(image_to_array(msg), encoding)


def _to_rgb(pixels: np.ndarray, encoding: str) -> np.ndarray:
    if encoding in ("rgb8", "8UC3"):
        return np.ascontiguousarray(pixels)
    if encoding == "bgr8":
        return np.ascontiguousarray(pixels[:, :, ::-1])
    if encoding == "rgba8":
        return np.ascontiguousarray(pixels[:, :, :3])
    if encoding == "bgra8":
        return np.ascontiguousarray(pixels[:, :, 2::-1])
    if encoding == "mono16":
        pixels = (pixels >> 8).astype(np.uint8)
    return np.repeat(pixels[:, :, None], 3, axis=2)


def depth_to_metres(msg: Any) -> np.ndarray:
    """A 16UC1 (millimetres) or 32FC1 (metres) depth Image -> H x W float32 metres.

    0 marks unknown depth: 16UC1 zeros, and 32FC1 NaN, inf, zero or negative values.
    """
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        encoding_of(encoding)
        raise ImageEncodingError(f"encoding {encoding!r} is not a depth encoding; accepted: {', '.join(DEPTH_ENCODINGS)}")
    pixels = image_to_array(msg)
    if encoding == "16UC1":
        return pixels.astype(np.float32) / np.float32(1000.0)
    depth = pixels.astype(np.float32, copy=True)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth
