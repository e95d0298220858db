"""What made a map's descriptors: a short hash of the weights, stored in both methods' map files."""
from __future__ import annotations

import hashlib
from collections.abc import Mapping

import numpy as np
import torch


def tensors_id(tensors: Mapping[str, torch.Tensor | np.ndarray]) -> str:
    """16 hex digits of SHA-256 over each named tensor's name, dtype, shape and bytes, in name order."""
    h = hashlib.sha256()
    for name, value in sorted(tensors.items()):
        t = (value if isinstance(value, torch.Tensor) else torch.from_numpy(np.asarray(value))).detach().cpu()
        t = t.contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)};".encode())
        h.update(t.numpy().tobytes() if t.dtype != torch.bfloat16 else t.float().numpy().tobytes())
    return h.hexdigest()[:16]
