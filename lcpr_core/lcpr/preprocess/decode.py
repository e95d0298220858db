"""Camera images -> RGB uint8 pixels, decoded no larger than the network's input needs.

A 1600 x 900 JPEG shrunk to 704 x 256 (or 192 x 64) does not need all its pixels: libjpeg-turbo
can scale by 1/2, 1/4 or 1/8 while decoding (inside the inverse DCT), which skips most of the
work. :func:`decode_scaled` keeps the largest of those reductions that still leaves at least the
target size and decodes through ``simplejpeg`` (libjpeg-turbo's TurboJPEG API, faster than OpenCV's
decode: docs/keyframe_pipeline.md), or through OpenCV's reduced-size
decode where ``simplejpeg`` is not installed; the antialiased resize that follows (:mod:`.cameras`)
makes the rest of the way. Both release the GIL, so two threads decode two images at once. The
descriptor stays within cosine 0.9999 of the released PIL pipeline on the real nuScenes keyframes
(``test/lcpr_core/lcpr/test_camera_decode.py``).

Both decoders check the bytes first: a JPEG that does not end with its end-of-image marker is
refused as truncated, as PIL refuses it, instead of decoding to a grey lower half as libjpeg does.
"""
from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
from PIL import Image

from ...errors import InputShapeError, InvalidValueError

if TYPE_CHECKING:
    from .camera import CameraInput

JPEG_SOI = b"\xff\xd8"
JPEG_EOI = b"\xff\xd9"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: reductions libjpeg-turbo applies while decoding, largest first
REDUCTIONS = (8, 4, 2)
#: the JPEG decoders :func:`decode_scaled` can use; ``auto``: simplejpeg where it imports, else opencv
JPEG_BACKENDS = ("auto", "simplejpeg", "opencv")
# start-of-frame markers (baseline, progressive, lossless ...); 0xC4, 0xC8 and 0xCC are other segments
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def is_jpeg(data: bytes | bytearray | memoryview) -> bool:
    return bytes(data[:2]) == JPEG_SOI


def jpeg_size(data: bytes | bytearray | memoryview) -> tuple[int, int]:
    """(height, width) of a JPEG from its start-of-frame segment, without decoding; checks that it is whole.

    Raises :class:`InputShapeError` for bytes that are not a whole JPEG (no start-of-frame segment,
    or no end-of-image marker: a truncated file).
    """
    buf = bytes(data)
    if buf[:2] != JPEG_SOI:
        raise InputShapeError(f"{len(buf)} bytes starting {buf[:4]!r} are not a JPEG (no start-of-image marker)")
    if buf.rstrip(b"\0")[-2:] != JPEG_EOI:
        raise InputShapeError(f"JPEG of {len(buf)} bytes is truncated (no end-of-image marker)")
    pos = 2
    while pos + 4 <= len(buf):
        if buf[pos] != 0xFF:
            break
        marker = buf[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        length = int.from_bytes(buf[pos + 2:pos + 4], "big")
        if marker in _SOF and pos + 9 <= len(buf):
            height = int.from_bytes(buf[pos + 5:pos + 7], "big")
            width = int.from_bytes(buf[pos + 7:pos + 9], "big")
            if height > 0 and width > 0:
                return height, width
            break
        pos += 2 + length
    raise InputShapeError(f"JPEG of {len(buf)} bytes has no readable start-of-frame segment (corrupt header)")


def reduction(height: int, width: int, size: tuple[int, int]) -> int:
    """The largest of 8, 4, 2 that keeps an image of ``height`` x ``width`` at least ``size`` (h, w); else 1."""
    for factor in REDUCTIONS:
        if -(-height // factor) >= size[0] and -(-width // factor) >= size[1]:
            return factor
    return 1


@cache
def simplejpeg_module() -> Any | None:
    """The ``simplejpeg`` module, or None where it is not installed (OpenCV decodes then)."""
    try:
        import simplejpeg  # type: ignore[import-not-found, import-untyped, unused-ignore]
    except ImportError:
        return None
    return simplejpeg


def jpeg_backend() -> str:
    """Which library ``auto`` decodes JPEGs with here, and its version."""
    sj = simplejpeg_module()
    if sj is not None:
        return f"simplejpeg {getattr(sj, '__version__', '?')}"
    import cv2

    return f"opencv {cv2.__version__}"


def decode_scaled(data: bytes | bytearray | memoryview, size: tuple[int, int], *,
                  backend: str = "auto") -> np.ndarray:
    """JPEG (or PNG) bytes -> H x W x 3 RGB uint8, a JPEG decoded at the largest reduction that keeps ``size``.

    ``backend`` (:data:`JPEG_BACKENDS`): ``auto`` takes simplejpeg where it imports, else OpenCV.
    A JPEG simplejpeg refuses (a CMYK file, say) is tried by OpenCV before it is called corrupt.
    """
    if backend not in JPEG_BACKENDS:
        raise InvalidValueError(f"JPEG backend {backend!r}; accepted: {', '.join(JPEG_BACKENDS)}")
    if is_jpeg(data):
        height, width = jpeg_size(data)
        factor = reduction(height, width, size)
        sj = simplejpeg_module() if backend != "opencv" else None
        if backend == "simplejpeg" and sj is None:
            raise InvalidValueError("JPEG backend 'simplejpeg' is not installed (pip install simplejpeg); "
                                    "accepted here: auto, opencv")
        if sj is not None:
            try:  # the smallest libjpeg-turbo scale that keeps these minimums is exactly 1 / factor
                return np.asarray(sj.decode_jpeg(data, colorspace="RGB", min_height=-(-height // factor),
                                                 min_width=-(-width // factor)))
            except ValueError:
                pass
    elif bytes(data[:8]) == PNG_SIGNATURE:
        factor = 1
    else:
        raise InputShapeError(f"{len(data)} image bytes starting {bytes(data[:4])!r} are neither JPEG nor PNG")
    return _opencv_decode(data, factor)


def _opencv_decode(data: bytes | bytearray | memoryview, factor: int) -> np.ndarray:
    """OpenCV's decode at 1 / ``factor`` (1, 2, 4 or 8) -> H x W x 3 RGB uint8."""
    import cv2

    buf = np.frombuffer(data, np.uint8)
    # IMREAD_REDUCED_GRAYSCALE_<f> is the reduction bit alone; OpenCV >= 4.11 decodes straight to RGB
    reduced = {1: 0, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
               8: cv2.IMREAD_REDUCED_GRAYSCALE_8}[factor]
    rgb_flag = getattr(cv2, "IMREAD_COLOR_RGB", None)
    image = cv2.imdecode(buf, reduced | (cv2.IMREAD_COLOR if rgb_flag is None else rgb_flag))
    if image is None or image.ndim != 3 or image.shape[2] != 3:
        raise InputShapeError(f"cannot decode {len(buf)} image bytes as JPEG or PNG (corrupt data)")
    return image if rgb_flag is not None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def rgb_array(image: CameraInput, size: tuple[int, int]) -> np.ndarray:
    """Any camera input -> H x W x 3 RGB uint8 (encoded bytes decoded by :func:`decode_scaled`)."""
    if isinstance(image, (bytes, bytearray, memoryview)):
        return decode_scaled(image, size)
    if isinstance(image, Image.Image):
        return np.asarray(image.convert("RGB"), dtype=np.uint8)
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise InputShapeError(
            f"camera image is a {arr.dtype} array of shape {arr.shape}; expected uint8 H x W x 3 (RGB)")
    return arr

