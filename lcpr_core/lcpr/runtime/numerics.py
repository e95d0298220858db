"""The arithmetic of one forward pass, by ``model.precision``.

- ``fp32``: float32 with TF32 off for cuDNN convolutions and matrix products. PyTorch lets cuDNN use TF32
  by default, which moves the released network outside the 1e-5 parity with the authors' reference vectors
  (docs/studies/inference_paths.md has the measured deviations).
- ``tf32``: TF32 tensor cores for convolutions and matrix products (CUDA only).
- ``bf16``: bfloat16 autocast.

Each path sets the switches it needs around every call and restores them, so two describers in one process
(or a user's own model) keep their own. Both the eager path (:mod:`.backends`) and CUDA-graph replay
(:mod:`.cuda`) run under :func:`numerics`, so the switches live here, below both.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch

__all__ = ["CUDA_PRECISIONS", "float32_math", "numerics"]

CUDA_PRECISIONS = ("fp32", "tf32", "bf16")


@contextlib.contextmanager
def float32_math(*, tf32: bool) -> Iterator[None]:
    """cuDNN convolutions and CUDA matrix products in TF32 (``tf32``) or in full float32; the switches are
    restored afterwards."""
    conv: Any = getattr(torch.backends.cudnn, "conv", None)  # not in torch's type stubs
    new_api = conv is not None and hasattr(conv, "fp32_precision")
    if new_api:  # torch >= 2.9: the legacy allow_tf32 switches are deprecated
        saved = (conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision)
        mode = "tf32" if tf32 else "ieee"
        conv.fp32_precision = mode
        torch.backends.cuda.matmul.fp32_precision = mode
    else:
        saved = (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
        torch.backends.cudnn.allow_tf32 = tf32
        torch.backends.cuda.matmul.allow_tf32 = tf32
    try:
        yield
    finally:
        if new_api:
            conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision = saved
        else:
            torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@contextlib.contextmanager
def numerics(device: torch.device, precision: str) -> Iterator[None]:
    """The arithmetic ``precision`` names (see the module doc), for a forward pass on ``device``."""
    with contextlib.ExitStack() as stack:
        stack.enter_context(torch.inference_mode())
        if device.type == "cuda":
            stack.enter_context(float32_math(tf32=precision == "tf32"))
        stack.enter_context(torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16"))
        yield
