"""Model inputs from a sample cache: uint8 images and float16 ranges -> normalised float32 tensors."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ...errors import InvalidValueError
from ..preprocess import IMAGENET_MEAN, IMAGENET_STD
from .augment import AugmentConfig, augment
from .cache import SampleCache
from .config import SplitConfig
from .split import Split, split_samples

_MEAN = torch.tensor(IMAGENET_MEAN).view(1, 1, 3, 1, 1)
_STD = torch.tensor(IMAGENET_STD).view(1, 1, 3, 1, 1)


def to_model_inputs(images: np.ndarray, cameras: np.ndarray, ranges: np.ndarray, *,
                    device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """B x C x H x W x 3 uint8, B x C presence, B x h x w ranges -> (B x C x 3 x H x W, B x 1 x h x w) float32.

    The same arithmetic as :func:`lcpr_core.lcpr.preprocess.camera_tensor` (scale to [0, 1],
    ImageNet normalisation); a missing camera is all zeros, as :func:`cameras_tensor` makes it.
    With ``device`` the uint8 images travel there first and are normalised there (a quarter of
    the bytes to copy, and the arithmetic on the GPU).
    """
    dev = torch.device("cpu") if device is None else torch.device(device)
    x = torch.from_numpy(np.ascontiguousarray(images)).to(dev).permute(0, 1, 4, 2, 3).float().div_(255)
    x = x.sub_(_MEAN.to(dev)).div_(_STD.to(dev))
    x *= torch.from_numpy(np.asarray(cameras, bool)).to(dev).view(*x.shape[:2], 1, 1, 1)
    r = torch.from_numpy(np.asarray(ranges, np.float32)).to(dev).unsqueeze(1)
    return x, r


@dataclass(frozen=True)
class TrainingData:
    """A sample cache together with its database / query split; with ``lidar_only`` every sample's camera
    slots are empty wherever its inputs are read (training, mining, validation, whitening), as
    ``lcpr_node``'s ``lidar_only`` gives them to the network."""

    cache: SampleCache
    split: Split
    lidar_only: bool = False

    @classmethod
    def from_cache(cls, cache: SampleCache, config: SplitConfig = SplitConfig(), *,
                   lidar_only: bool = False) -> TrainingData:
        return cls(cache=cache, split=split_samples(cache.positions, cache.stamps, cache.groups, config),
                   lidar_only=lidar_only)

    def __len__(self) -> int:
        return len(self.cache)

    def inputs(self, indices: Sequence[int] | np.ndarray, *, augmentation: AugmentConfig | None = None,
               rng: np.random.Generator | None = None,
               device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Model inputs of the given samples, in the given order (repeats allowed), on ``device`` (default
        the CPU); with ``augmentation`` (and its ``rng``) each sample possibly turned, relit or missing a
        camera (:mod:`.augment`)."""
        idx = np.asarray(indices, np.int64)
        order = np.argsort(idx, kind="stable")  # sorted reads are kinder to the memory map
        back = np.empty_like(order)
        back[order] = np.arange(len(idx))
        s = idx[order]
        imgs, cams, rngs = self.cache.images[s][back], self.cache.cameras[s][back], self.cache.ranges[s][back]
        if self.lidar_only:
            cams = np.zeros_like(cams)
        if augmentation is not None and augmentation.active:
            if rng is None:
                raise InvalidValueError("augmentation needs an rng (a numpy Generator); got None")
            imgs, cams, rngs = augment(imgs, cams, rngs, augmentation, rng)
        return to_model_inputs(imgs, cams, rngs, device=device)
