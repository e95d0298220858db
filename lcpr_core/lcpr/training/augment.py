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
  three, equally likely; :data:`LIDAR_QUARTERS`);
- LiDAR field of view: up to a quarter of the rows at the top and up to three eighths at the bottom set
  to no return, each count uniform (a real sensor whose beams span less than the range image's
  geometry: a KITTI HDL-64E leaves nuScenes' top rows empty, a VLP-16 both ends);
- sparse LiDAR: every second row set to no return (a sensor with half the beams) or, equally likely, a
  share of the returns uniform in ``sparse_share`` dropped at random (far, dark or wet surfaces).
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
    lidar_fov: float = 0.0  # chance its range image loses rows at the top and the bottom
    lidar_sparse: float = 0.0  # chance it loses every second row or a random share of its returns
    sparse_share: tuple[float, float] = (0.1, 0.5)  # range of the share of returns dropped

    def __post_init__(self) -> None:
        for name in ("yaw", "lighting", "camera_drop", "lidar_occlusion", "lidar_fov", "lidar_sparse"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InvalidValueError(f"augment.{name}={value!r}; expected a probability in [0, 1]")
        low, high = self.brightness
        if not 0.0 < low <= high:
            raise InvalidValueError(f"augment.brightness={self.brightness}; expected 0 < low <= high")
        low, high = self.sparse_share
        if not 0.0 <= low <= high < 1.0:
            raise InvalidValueError(f"augment.sparse_share={self.sparse_share}; expected 0 <= low <= high < 1")

    @property
    def active(self) -> bool:
        return any(p > 0 for p in (self.yaw, self.lighting, self.camera_drop, self.lidar_occlusion, self.lidar_fov,
                                   self.lidar_sparse))


def narrow_fov(ranges: np.ndarray, top: int, bottom: int) -> np.ndarray:
    """... x h x w range images with their ``top`` first and ``bottom`` last rows set to no return (a copy)."""
    out = ranges.copy()
    h = ranges.shape[-2]
    if not (0 <= top and 0 <= bottom and top + bottom < h):
        raise InvalidValueError(f"top={top}, bottom={bottom}; expected counts >= 0 leaving a row of the {h}")
    out[..., :top, :] = NO_RETURN
    out[..., h - bottom:, :] = NO_RETURN
    return out


def sparsify(ranges: np.ndarray, rng: np.random.Generator, share: tuple[float, float]) -> np.ndarray:
    """One h x w range image with every second row (from a random first one) or a random share of its
    pixels set to no return (a copy), each equally likely."""
    out = ranges.copy()
    if rng.random() < 0.5:
        out[int(rng.integers(2))::2] = NO_RETURN
    else:
        out[rng.random(out.shape) < rng.uniform(*share)] = NO_RETURN
    return out


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
        if config.lidar_fov > 0 and rng.random() < config.lidar_fov:  # (guarded: earlier recipes' draws unchanged)
            h = ranges.shape[-2]
            ranges[b] = narrow_fov(ranges[b], int(rng.integers(h // 4 + 1)), int(rng.integers(3 * h // 8 + 1)))
        if config.lidar_sparse > 0 and rng.random() < config.lidar_sparse:
            ranges[b] = sparsify(ranges[b], rng, config.sparse_share)
    return images, cameras, ranges
