"""Fitting a checkpoint's descriptor whitening on the frames of its training bags (``lcpr_train --whiten``)."""
from __future__ import annotations

import dataclasses
import os

import numpy as np
import torch

from ..checkpoint import trained_lidar_only
from ..describer import ModelConfig, build_model
from ..whitening import DEFAULT_DIMS, DEFAULT_POWER, Whitening, fit_whitening, write_whitened
from .config import checkpoint_inputs
from .dataset import TrainingData
from .train import describe_samples


def whiten_checkpoint(
    checkpoint: str | os.PathLike[str],
    target: str | os.PathLike[str],
    data: TrainingData,
    *,
    power: float = DEFAULT_POWER,
    dims: int = DEFAULT_DIMS,
    batch: int = 16,
    device: str = "cpu",
    progress: bool = True,
) -> Whitening:
    """Describe every frame of ``data`` with ``checkpoint``, fit the whitening and write ``target``.

    Fit it on the training bags' frames, never on the cities it is evaluated on, preprocessed at the
    checkpoint's own input sizes (:func:`~.config.checkpoint_inputs`: the cache to build); weights trained
    for LiDAR-only frames describe them with every camera slot empty, as they will be used.
    """
    if trained_lidar_only(checkpoint) and not data.lidar_only:
        data = dataclasses.replace(data, lidar_only=True)
    model = build_model(ModelConfig(weights=os.fspath(checkpoint), precision="fp32")).to(torch.device(device))
    desc = describe_samples(model, data, np.arange(len(data)), batch=batch, device=device, progress=progress,
                            desc="describe for whitening")
    whitening = fit_whitening(desc, power=power, dims=dims)
    write_whitened(checkpoint, target, whitening)
    return whitening


__all__ = ["checkpoint_inputs", "whiten_checkpoint"]
