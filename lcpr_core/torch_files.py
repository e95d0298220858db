"""Reading PyTorch weight files safely, for both networks: nothing loaded from disk can run code."""
from __future__ import annotations

import os
import pickle
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from .errors import CheckpointError

__all__ = ["check_state_dict", "load_checkpoint", "read_state_dict"]


def load_checkpoint(path: str | os.PathLike[str], *, mmap: bool = False) -> object:
    """The object in a PyTorch file, loaded with ``weights_only=True`` so it cannot run code.

    ``mmap``: map the tensors instead of reading them (cheap when only a small entry is wanted);
    files in torch's legacy (pre-zip) format cannot be mapped and are read whole.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"weights file {str(path)!r} does not exist")
    try:
        try:
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
        except RuntimeError:
            if not mmap:
                raise
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        raise CheckpointError(
            f"{str(path)!r} holds objects other than tensors and plain containers; it is refused "
            f"because loading it could run code (weights_only=True): {err}"
        ) from err
    except (RuntimeError, EOFError, OSError, ValueError) as err:
        raise CheckpointError(f"{str(path)!r} is not a readable PyTorch file: {err}") from err


def read_state_dict(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Load a weights file without running code from it.

    Accepts the released format ``{'epoch', 'net': state_dict, 'scheduler'}``,
    ``{'state_dict': ...}``, and a plain state dict; a ``module.`` prefix
    (DataParallel) is removed.
    """
    path = Path(path)
    obj = load_checkpoint(path)
    state = _find_state_dict(obj, path)
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    return state


def _find_state_dict(obj: object, path: Path) -> dict[str, torch.Tensor]:
    if isinstance(obj, Mapping):
        for key in ("net", "state_dict", "model"):
            inner = obj.get(key)
            if isinstance(inner, Mapping):
                obj = inner
                break
        if obj and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
            return dict(obj)
    raise CheckpointError(
        f"{str(path)!r} holds no state dict: expected a dict of tensors, or one under 'net' "
        f"(released LCPR checkpoints) or 'state_dict'; found {type(obj).__name__}"
    )


def check_state_dict(model: nn.Module, state: Mapping[str, torch.Tensor], *, source: str = "state dict") -> None:
    """Raise CheckpointError listing missing, unexpected and mis-shaped keys, if any."""
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    misshaped = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
        for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)
    ]
    if missing or unexpected or misshaped:
        parts = [f"{source} does not fit {type(model).__name__} ({len(own)} keys)"]
        for label, items in (("missing", missing), ("unexpected", unexpected), ("mis-shaped", misshaped)):
            if items:
                shown = ", ".join(items[:8]) + (f", ... ({len(items) - 8} more)" if len(items) > 8 else "")
                parts.append(f"{len(items)} {label}: {shown}")
        raise CheckpointError("; ".join(parts))
