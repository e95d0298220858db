"""Camera-native frames built from the standards' definitions, independently of the code under test."""
from __future__ import annotations

import numpy as np


def smooth_rgb(height: int, width: int) -> np.ndarray:
    """A gradient image (no edges), where interpolation can be exact to a few levels."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([40 + 150 * x / width, 200 - 120 * y / height, 60 + 60 * (x + y) / (width + height)],
                    axis=2).round().astype(np.uint8)


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The raw frame of a Bayer sensor whose 2 x 2 cell is ``pattern`` read row by row (ROS's naming)."""
    raw = np.zeros(rgb.shape[:2], np.uint8)
    for (i, j), colour in zip(((0, 0), (0, 1), (1, 0), (1, 1)), pattern, strict=True):
        raw[i::2, j::2] = rgb[i::2, j::2, "rgb".index(colour)]
    return raw


def yuv601(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Y, U, V planes of BT.601 limited range ("video" levels), written from the standard's formulas."""
    r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    return tuple(np.clip(np.round(c), 0, 255).astype(np.uint8) for c in (y, u, v))  # type: ignore[return-value]


def blocky_rgb(height: int, width: int) -> np.ndarray:
    """Colours constant over 2 x 2 blocks, so chroma subsampling loses nothing."""
    small = np.random.default_rng(5).integers(30, 220, (height // 2, width // 2, 3), dtype=np.uint8)
    return np.repeat(np.repeat(small, 2, axis=0), 2, axis=1)


def packed_yuv422(rgb: np.ndarray, order: str) -> np.ndarray:
    """H x W x 2 bytes of packed 4:2:2 ("UYVY" or "YUYV") of an RGB image (chroma of even columns)."""
    y, u, v = yuv601(rgb)
    planes = {"Y0": y[:, 0::2], "Y1": y[:, 1::2], "U": u[:, 0::2], "V": v[:, 0::2]}
    names = ["Y0", "U", "Y1", "V"] if order == "YUYV" else ["U", "Y0", "V", "Y1"]
    return np.stack([planes[n] for n in names], axis=2).reshape(rgb.shape[0], rgb.shape[1], 2)


def nv21(rgb: np.ndarray) -> np.ndarray:
    """(3H/2) x W planes of NV21: Y, then V and U interleaved at half resolution (even rows and columns)."""
    y, u, v = yuv601(rgb)
    h, w = y.shape
    vu = np.stack([v[0::2, 0::2], u[0::2, 0::2]], axis=2).reshape(h // 2, w)
    return np.concatenate([y, vu])
