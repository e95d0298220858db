"""Camera images -> the normalised tensors LCPR reads (PIL bilinear resize, ImageNet stats)."""
from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np
import torch
from PIL import Image

from ...errors import InputShapeError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NUSCENES_CAMERAS = (
    "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT",
)

CameraInput = np.ndarray | bytes | bytearray | memoryview | Image.Image


def decode_image(data: bytes | bytearray | memoryview, *, draft_size: tuple[int, int] | None = None) -> Image.Image:
    """JPEG/PNG bytes -> RGB PIL image.

    draft_size=(width, height) lets the JPEG decoder scale by 1/2, 1/4 or 1/8 while
    decoding (keeping at least that size): faster, but the pixels differ from a full
    decode followed by the resize (``benchmarks/tools/keyframe_pipeline.py`` measures the stages).
    """
    try:
        img = Image.open(io.BytesIO(bytes(data)))
        if draft_size is not None:
            img.draft("RGB", draft_size)
        return img.convert("RGB")
    except (OSError, ValueError) as err:
        raise InputShapeError(f"cannot decode {len(data)} image bytes as JPEG or PNG: {err}") from err


def to_pil(image: CameraInput, *, draft_size: tuple[int, int] | None = None) -> Image.Image:
    """An RGB uint8 H x W x 3 array, encoded bytes or a PIL image -> RGB PIL image."""
    if isinstance(image, Image.Image):
        return image.convert("RGB")
    if isinstance(image, (bytes, bytearray, memoryview)):
        return decode_image(image, draft_size=draft_size)
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise InputShapeError(
            f"camera image is a {arr.dtype} array of shape {arr.shape}; expected uint8 H x W x 3 (RGB)"
        )
    return Image.fromarray(arr, mode="RGB")


def camera_tensor(
    image: CameraInput, *, size: tuple[int, int] = (256, 704), fast_decode: bool = False
) -> torch.Tensor:
    """One camera image -> 3 x H x W float32, as the released pipeline makes it.

    size is (height, width). fast_decode uses JPEG draft mode (see :func:`decode_image`).
    """
    height, width = size
    pil = to_pil(image, draft_size=(width, height) if fast_decode else None)
    pil = pil.resize((width, height), Image.Resampling.BILINEAR)
    x = torch.from_numpy(np.asarray(pil, dtype=np.uint8).copy()).permute(2, 0, 1).float().div(255)
    mean = torch.tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(3, 1, 1)
    return x.sub_(mean).div_(std)


def cameras_tensor(
    images: Sequence[CameraInput | None],
    *,
    size: tuple[int, int] = (256, 704),
    fast_decode: bool = False,
) -> torch.Tensor:
    """N camera images (nuScenes order) -> N x 3 x H x W.

    A None entry stands for a camera that sent nothing: its slot is all zeros, as in
    the paper's occlusion study.
    """
    slots = [
        torch.zeros(3, *size) if img is None else camera_tensor(img, size=size, fast_decode=fast_decode)
        for img in images
    ]
    if not slots:
        raise InputShapeError("no camera images given; expected one per camera (6 for nuScenes)")
    return torch.stack(slots)
