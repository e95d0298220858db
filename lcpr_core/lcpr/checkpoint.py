"""Reading and writing LCPR weights: released checkpoints, plain state dicts, ImageNet ResNet-18."""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from ..atomic import save_torch
from ..errors import CheckpointError
from ..torch_files import check_state_dict, load_checkpoint, read_state_dict

log = logging.getLogger(__name__)

#: torchvision resnet18 prefix -> LCPR prefixes it initialises (the paper uses ImageNet
#: ResNet-18 blocks in both branches; conv_l has no counterpart and stays random).
IMAGENET_PREFIXES: dict[str, tuple[str, ...]] = {
    "conv1.": ("conv1_i.",),
    "bn1.": ("bn1_i.",),
    "layer1.": ("layer1_i.",),
    "layer2.": ("layer2_i.", "layer2_l."),
    "layer3.": ("layer3_i.", "layer3_l."),
    "layer4.": ("layer4_i.", "layer4_l."),
}
#: Checkpoint entry marking weights trained with every camera slot empty (``lcpr_train --lidar-only``): they
#: are meant for LiDAR-only frames, and their whitening is fitted on such frames.
LIDAR_ONLY = "lidar_only"


def read_released(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A checkpoint in the released layout (a dict with a 'net' state dict), e.g. to copy with changes."""
    obj = load_checkpoint(path)
    if not isinstance(obj, dict) or "net" not in obj:
        raise CheckpointError(f"{str(path)!r} is not a released-format checkpoint (no 'net' entry)")
    return obj


def copy_with(source: str | os.PathLike[str], target: str | os.PathLike[str], entries: Mapping[str, Any]) -> int:
    """Copy released-format checkpoint ``source`` to ``target`` with ``entries`` set (atomic, readable by all);
    returns bytes. How the descriptor post-processing (whitening, turn averaging) is added to weights."""
    obj = read_released(source)
    obj.update(entries)
    return save_torch(obj, target, shared=True)


def trained_lidar_only(path: str | os.PathLike[str]) -> bool:
    """Whether a weights file was trained for LiDAR-only frames (its :data:`LIDAR_ONLY` entry)."""
    obj = load_checkpoint(path, mmap=True)
    return isinstance(obj, Mapping) and bool(obj.get(LIDAR_ONLY, False))


def load_weights(model: nn.Module, path: str | os.PathLike[str]) -> nn.Module:
    """Load a released checkpoint or a state dict into ``model``, checking every key and shape."""
    state = read_state_dict(path)
    check_state_dict(model, state, source=f"weights file {str(path)!r}")
    model.load_state_dict(state)
    log.info("loaded weights from %s (%d tensors)", path, len(state))
    return model


def save_checkpoint(
    model: nn.Module,
    path: str | os.PathLike[str],
    *,
    epoch: int = 0,
    scheduler: Mapping[str, object] | None = None,
    extra: Mapping[str, object] | None = None,
) -> None:
    """Write ``{'epoch', 'net', 'scheduler', ...}`` (the released layout) atomically."""
    payload: dict[str, object] = {"epoch": epoch, "net": model.state_dict(), "scheduler": dict(scheduler or {})}
    payload.update(extra or {})
    save_torch(payload, path)


def init_from_imagenet(model: nn.Module, path: str | os.PathLike[str]) -> nn.Module:
    """Initialise the ResNet blocks of both branches from a torchvision resnet18 state dict file."""
    resnet = read_state_dict(path)
    own = model.state_dict()
    mapped: dict[str, torch.Tensor] = {}
    for src_prefix, dst_prefixes in IMAGENET_PREFIXES.items():
        for key, value in resnet.items():
            if key.startswith(src_prefix):
                for dst in dst_prefixes:
                    mapped[dst + key[len(src_prefix):]] = value
    wanted = [k for k in own if any(k.startswith(d) for ds in IMAGENET_PREFIXES.values() for d in ds)]
    missing = [k for k in wanted if k not in mapped]
    misshaped = [k for k in wanted if k in mapped and mapped[k].shape != own[k].shape]
    if missing or misshaped:
        raise CheckpointError(
            f"{str(path)!r} is not a torchvision resnet18 state dict: {len(missing)} missing "
            f"({', '.join(missing[:5])}), {len(misshaped)} mis-shaped ({', '.join(misshaped[:5])})"
        )
    model.load_state_dict({k: mapped[k] for k in wanted}, strict=False)
    log.info("initialised %d tensors of the ResNet blocks from ImageNet weights %s", len(wanted), path)
    return model
