"""The vehicle turned left by whole camera slots: the one rule the yaw study, the yaw augmentation and the
keyframe demo share.

Slot j then shows what slot j - k showed (the camera list rolled by k) and the cloud turns the other way,
by the angle between the slots' cameras: ``SLOT_YAWS_DEG`` (nuScenes camera order: front, front right,
back right, back, back left, front left). In a range image that is a roll of the columns
(:func:`range_columns`), exact when the angle is a whole number of columns.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import numpy as np
import torch

from ...points import rotate_z

T = TypeVar("T")

#: Yaw of the vehicle (deg, left) when camera slot k (k = 1..5) looks where slot 0 looked.
SLOT_YAWS_DEG = (55.0, 110.0, 180.0, 250.0, 305.0)


def slot_yaw_deg(k: int) -> float:
    """The turn by k slots in degrees; k = 6 is the full turn, 360."""
    return 360.0 if k == len(SLOT_YAWS_DEG) + 1 else SLOT_YAWS_DEG[k - 1]


def turn_frame(images: Sequence[T], points: np.ndarray, k: int) -> tuple[list[T], np.ndarray]:
    """A raw frame (camera images in rig order, N x >=3 points) seen after turning left by k slots."""
    shift = k % len(images)
    rolled = list(images[-shift:]) + list(images[:-shift]) if shift else list(images)
    return rolled, rotate_z(points, -slot_yaw_deg(k))


def range_columns(yaw_deg: float, width: int) -> int:
    """Columns a range image shifts when the vehicle turns left by ``yaw_deg`` (the cloud by -yaw_deg)."""
    return round(yaw_deg * width / 360.0) % width


def turn_inputs(images: torch.Tensor, ranges: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched model inputs (B x C x 3 x H x W, B x 1 x h x w) seen after turning left by k slots:
    the preprocessed form of :func:`turn_frame` (cameras rolled by k, range columns by the slot's angle)."""
    if k % images.shape[1] == 0:
        return images, ranges
    shift = range_columns(slot_yaw_deg(k), ranges.shape[-1])
    return torch.roll(images, k, dims=1), torch.roll(ranges, shift, dims=-1)
