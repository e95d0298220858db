"""Training augmentations matching what the paper says LCPR is robust to: yaw, lighting, a missing camera.

Applied to the cached training inputs of each optimiser step (never to the descriptors that mining or
validation compute), each sample independently:

- yaw: the vehicle turned by k whole camera slots (k uniform in 1..C-1): the C images rolled by k slots
  together with the range image's columns rolled by the slot's angle (:mod:`lcpr_core.lcpr.preprocess.turn`),
  which is the cloud turned by that angle;
- lighting: every image's brightness scaled by a factor uniform in ``brightness`` (as PIL's
  ImageEnhance.Brightness: a blend with black, clipped);
- camera drop: one camera, chosen at random, blacked out (a zero slot, as a camera that stopped sending);
- LiDAR occlusion: a quarter of the range image set to no return, as the paper's occlusion study: a
  90-degree sector at a random azimuth, the top quarter of the rows or the bottom quarter (one of the
  three, equally likely; :data:`LIDAR_QUARTERS`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...errors import InvalidValueError
from ..preprocess.range_image import NO_RETURN
from ..preprocess.turn import SLOT_YAWS_DEG, range_columns, slot_yaw_deg

#: The quarters of an h x w range image the occlusion augmentation and the robustness study black out:
#: name -> (rows, columns) of the quarter (the sector starts at column 0; :func:`occlude_lidar` turns it).
LIDAR_QUARTERS: dict[str, Callable[[int, int], tuple[slice, slice]]] = {
    "columns": lambda h, w: (slice(None), slice(0, w // 4)),  # a 90 deg sector, full height
    "top rows": lambda h, w: (slice(0, h // 4), slice(None)),  # the upper beams, all the way round
    "bottom rows": lambda h, w: (slice(h - h // 4, h), slice(None)),  # the lower beams
}


def lidar_quarter(part: str) -> Callable[[int, int], tuple[slice, slice]]:
    """The (rows, columns) of one of :data:`LIDAR_QUARTERS`; an unknown part is refused, naming the accepted ones."""
    try:
        return LIDAR_QUARTERS[part]
    except KeyError as err:
        raise InvalidValueError(f"LiDAR part {part!r}; expected one of {', '.join(map(repr, LIDAR_QUARTERS))}"
                                ) from err


def occlude_lidar(ranges: np.ndarray, part: str, *, start: int = 0) -> np.ndarray:
    """... x h x w range images with one of :data:`LIDAR_QUARTERS` set to no return (a copy).

    ``start``: the first column of the sector (``columns``); columns past the edge wrap round.
    """
    quarter = lidar_quarter(part)
    out = np.roll(ranges, -start, axis=-1)  # the sector at column 0, so it never splits at the edge
    out[(..., *quarter(*ranges.shape[-2:]))] = NO_RETURN
    return np.roll(out, start, axis=-1)


@dataclass(frozen=True)
class AugmentConfig:
    yaw: float = 0.0  # chance a sample is turned by whole camera slots
    lighting: float = 0.0  # chance its brightness is scaled
    brightness: tuple[float, float] = (0.3, 1.6)  # range of the brightness factor
    camera_drop: float = 0.0  # chance one of its cameras is blacked out
    lidar_occlusion: float = 0.0  # chance a quarter of its range image is blacked out

    def __post_init__(self) -> None:
        for name in ("yaw", "lighting", "camera_drop", "lidar_occlusion"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InvalidValueError(f"augment.{name}={value!r}; expected a probability in [0, 1]")
        low, high = self.brightness
        if not 0.0 < low <= high:
            raise InvalidValueError(f"augment.brightness={self.brightness}; expected 0 < low <= high")

    @property
    def active(self) -> bool:
        return self.yaw > 0 or self.lighting > 0 or self.camera_drop > 0 or self.lidar_occlusion > 0


def turn(images: np.ndarray, cameras: np.ndarray, ranges: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
    """One sample (C x H x W x 3, C, h x w) seen after turning left by k camera slots."""
    if k == 0:
        return images, cameras, ranges
    shift = range_columns(slot_yaw_deg(k), ranges.shape[-1])
    return np.roll(images, k, axis=0), np.roll(cameras, k, axis=0), np.roll(ranges, shift, axis=-1)


def augment(images: np.ndarray, cameras: np.ndarray, ranges: np.ndarray, config: AugmentConfig,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """B x C x H x W x 3 uint8 images, B x C presence, B x h x w ranges -> augmented copies."""
    images, cameras, ranges = images.copy(), cameras.copy(), ranges.copy()
    num_cameras = images.shape[1]
    if config.yaw > 0 and num_cameras != len(SLOT_YAWS_DEG) + 1:
        raise InvalidValueError(f"yaw augmentation needs the {len(SLOT_YAWS_DEG) + 1} nuScenes cameras; "
                                f"the samples have {num_cameras}")
    for b in range(len(images)):
        if rng.random() < config.yaw:
            k = int(rng.integers(1, num_cameras))
            images[b], cameras[b], ranges[b] = turn(images[b], cameras[b], ranges[b], k)
        if rng.random() < config.lighting:
            factor = rng.uniform(*config.brightness)
            images[b] = np.clip(images[b].astype(np.float32) * factor + 0.5, 0, 255).astype(np.uint8)
        if rng.random() < config.camera_drop:
            cameras[b, int(rng.integers(num_cameras))] = False
        if config.lidar_occlusion > 0 and rng.random() < config.lidar_occlusion:  # old recipes: same draws
            part = list(LIDAR_QUARTERS)[int(rng.integers(len(LIDAR_QUARTERS)))]
            ranges[b] = occlude_lidar(ranges[b], part, start=int(rng.integers(ranges.shape[-1])))
    return images, cameras, ranges
