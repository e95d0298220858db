"""sensor_msgs/Image <-> numpy arrays, plus RGB and metric-depth views of an image message.

Colour conversions of camera-native encodings (Bayer mosaics, packed YUV 4:2:2, NV21)
are OpenCV's (``opencv-python-headless``): the demosaicing and YUV -> RGB that cv_bridge
and the camera drivers themselves use, tested here against independently built inputs.
"""
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
    # camera-native layouts (industrial and USB cameras); image_to_rgb converts them
    "bayer_rggb8": Encoding(np.dtype(np.uint8), 1),  # the raw mosaic, its 2 x 2 cell named row by row
    "bayer_bggr8": Encoding(np.dtype(np.uint8), 1),
    "bayer_gbrg8": Encoding(np.dtype(np.uint8), 1),
    "bayer_grbg8": Encoding(np.dtype(np.uint8), 1),
    "yuv422": Encoding(np.dtype(np.uint8), 2),  # U Y0 V Y1 per two pixels (ROS's yuv422 is UYVY)
    "uyvy": Encoding(np.dtype(np.uint8), 2),
    "yuv422_yuy2": Encoding(np.dtype(np.uint8), 2),  # Y0 U Y1 V
    "yuyv": Encoding(np.dtype(np.uint8), 2),
}
#: Planar encodings: ``image_to_array`` returns the (height * 3 / 2) x width planes (Y, then
#: interleaved V/U at half resolution); height and width must be even.
PLANAR_ENCODINGS: tuple[str, ...] = ("nv21",)
BAYER_ENCODINGS = ("bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8")
PACKED_YUV_ENCODINGS = ("yuv422", "uyvy", "yuv422_yuy2", "yuyv")
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", "8UC1", "8UC3",
                    *BAYER_ENCODINGS, *PACKED_YUV_ENCODINGS, *PLANAR_ENCODINGS)
DEPTH_ENCODINGS = ("16UC1", "32FC1")


def encoding_of(name: str) -> Encoding:
    """The layout of an encoding name (of one row of a planar one), or :class:`ImageEncodingError`
    listing the accepted names."""
    if name in PLANAR_ENCODINGS:
        return Encoding(np.dtype(np.uint8), 1)
    try:
        return ENCODINGS[name]
    except KeyError as err:
        raise ImageEncodingError(
            f"image encoding {name!r} is not supported; accepted: {', '.join([*ENCODINGS, *PLANAR_ENCODINGS])}"
        ) from err


def stored_rows(encoding: str, height: int, width: int) -> int:
    """Rows of ``step`` bytes an image of ``height`` holds (1.5 x height for a planar encoding), or
    :class:`ImageLayoutError` when a planar or packed-YUV image has an odd size."""
    if encoding in PLANAR_ENCODINGS:
        if height % 2 or width % 2:
            raise ImageLayoutError(f"{encoding} image of {width} x {height}; its width and height must be even")
        return height * 3 // 2
    if encoding in PACKED_YUV_ENCODINGS and width % 2:
        raise ImageLayoutError(f"{encoding} image of width {width}; packed YUV 4:2:2 needs an even width")
    return height


def check_layout(msg: Any) -> Encoding:
    """The encoding of an Image whose step and data fit its size, or the error naming what does not."""
    encoding = str(msg.encoding)
    enc = encoding_of(encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if min(height, width, step) < 0:
        raise ImageLayoutError(f"image of {width} x {height} with step {step}; accepted: sizes of 0 or more")
    row_bytes = width * enc.channels * enc.dtype.itemsize
    if step < row_bytes:
        raise ImageLayoutError(
            f"step {step} is smaller than width * channels * bytes = {width} * {enc.channels} * "
            f"{enc.dtype.itemsize} = {row_bytes} for encoding {encoding!r}"
        )
    rows = stored_rows(encoding, height, width)
    if len(msg.data) < step * rows:
        needed = f"step * height = {step} * {height}" if rows == height else f"step * height * 3/2 = {step} * {rows}"
        raise ImageLayoutError(f"data holds {len(msg.data)} bytes, fewer than {needed} ({encoding})")
    return enc


def image_to_array(msg: Any) -> np.ndarray:
    """An Image (rosbags or rclpy) -> H x W (1 channel) or H x W x C array in the encoding's dtype.

    Row padding (``step`` > width * pixel size) is dropped and multi-byte pixels are
    returned in native byte order whatever ``is_bigendian`` says. Packed YUV 4:2:2 gives
    H x W x 2 (the bytes of each pixel as stored), a planar encoding its (3H/2) x W planes.
    """
    enc = check_layout(msg)
    width, step = int(msg.width), int(msg.step)
    height = stored_rows(str(msg.encoding), int(msg.height), width)
    stored = enc.dtype.newbyteorder(">" if msg.is_bigendian else "<")
    data = as_uint8(msg.data)
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
    if encoding in PLANAR_ENCODINGS:
        if height % 3:
            raise ImageLayoutError(f"{encoding} needs its (3H/2) x W planes, got {height} rows")
        height = height * 2 // 3
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

    mono16 keeps its 8 most significant bits; Bayer mosaics are demosaiced (OpenCV's
    edge-aware interpolation) and YUV is converted with BT.601 limited-range coefficients,
    as cv_bridge does. Depth and other non-colour encodings raise :class:`ImageEncodingError`.
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
    pixels = image_to_array(msg)
    if not pixels.size:  # an empty image converts to an empty one (OpenCV refuses empty inputs)
        return np.zeros((int(msg.height), int(msg.width), 3), np.uint8)
    return _to_rgb(pixels, encoding)


def _to_rgb(pixels: np.ndarray, encoding: str) -> np.ndarray:
    if encoding in _CV2_CODES:
        import cv2  # local: only camera-native encodings need OpenCV

        return np.ascontiguousarray(cv2.cvtColor(np.ascontiguousarray(pixels), getattr(cv2, _CV2_CODES[encoding])))
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


#: OpenCV conversion per camera-native encoding. OpenCV names a Bayer pattern by the 2 x 2 cell
#: starting at the second row and column, so ROS's rggb (R at row 0, column 0) is its "BG".
_CV2_CODES = {
    "bayer_rggb8": "COLOR_BayerBG2RGB_EA", "bayer_bggr8": "COLOR_BayerRG2RGB_EA",
    "bayer_gbrg8": "COLOR_BayerGR2RGB_EA", "bayer_grbg8": "COLOR_BayerGB2RGB_EA",
    "yuv422": "COLOR_YUV2RGB_UYVY", "uyvy": "COLOR_YUV2RGB_UYVY",
    "yuv422_yuy2": "COLOR_YUV2RGB_YUY2", "yuyv": "COLOR_YUV2RGB_YUY2",
    "nv21": "COLOR_YUV2RGB_NV21",
}


def depth_to_metres(msg: Any) -> np.ndarray:
    """A 16UC1 (millimetres) or 32FC1 (metres) depth Image -> H x W float32 metres.

    0 marks unknown depth: 16UC1 zeros, and 32FC1 NaN, inf, zero or negative values.
    """
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        encoding_of(encoding)
        raise ImageEncodingError(f"encoding {encoding!r} is not a depth encoding; "
                                 f"accepted: {', '.join(DEPTH_ENCODINGS)}")
    pixels = image_to_array(msg)
    if encoding == "16UC1":
        return pixels.astype(np.float32) / np.float32(1000.0)
    depth = pixels.astype(np.float32, copy=True)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth
