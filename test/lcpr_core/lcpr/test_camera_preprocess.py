"""Camera preprocessing matches the released pipeline and accepts arrays and encoded bytes."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from PIL import Image

from lcpr_core import InputShapeError, camera_tensor, cameras_tensor
from lcpr_core.lcpr.preprocess import IMAGENET_MEAN, IMAGENET_STD


def gradient_image(h: int = 90, w: int = 160) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([xx * 255 // w, yy * 255 // h, (xx + yy) % 256], axis=-1).astype(np.uint8)


def encoded(array: np.ndarray, fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format=fmt)
    return buf.getvalue()


def test_an_array_is_resized_bilinearly_and_normalised_with_imagenet_statistics():
    array = gradient_image()
    out = camera_tensor(array, size=(32, 64))
    resized = np.asarray(Image.fromarray(array).resize((64, 32), Image.Resampling.BILINEAR), dtype=np.float32) / 255
    expected = (resized - np.array(IMAGENET_MEAN, np.float32)) / np.array(IMAGENET_STD, np.float32)
    assert out.shape == (3, 32, 64) and out.dtype == torch.float32
    np.testing.assert_allclose(out.permute(1, 2, 0).numpy(), expected, atol=1e-6)


def test_png_bytes_give_the_same_tensor_as_the_array():
    array = gradient_image()
    torch.testing.assert_close(camera_tensor(encoded(array, "PNG")), camera_tensor(array))


def test_jpeg_draft_decoding_stays_close_to_the_full_decode():
    array = np.kron(gradient_image(), np.ones((10, 10, 1), np.uint8))  # 900 x 1600
    jpeg = encoded(array, "JPEG")
    full, fast = camera_tensor(jpeg), camera_tensor(jpeg, fast_decode=True)
    assert full.shape == fast.shape == (3, 256, 704)
    assert (full - fast).abs().mean() < 0.05


def test_a_missing_camera_becomes_a_zero_slot():
    cams = cameras_tensor([gradient_image(), None], size=(32, 64))
    assert cams.shape == (2, 3, 32, 64)
    assert cams[1].abs().sum() == 0 and cams[0].abs().sum() > 0


def test_bad_images_are_refused_with_their_shape_or_cause():
    with pytest.raises(InputShapeError, match=r"float32 array of shape \(4, 4, 3\)"):
        camera_tensor(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(InputShapeError, match="mono|shape \\(4, 4\\)"):
        camera_tensor(np.zeros((4, 4), np.uint8))
    with pytest.raises(InputShapeError, match="cannot decode 9 image bytes"):
        camera_tensor(b"not a jpg")
