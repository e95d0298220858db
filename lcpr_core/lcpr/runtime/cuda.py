"""The network on a CUDA GPU: an exact fp32 path, two named fast paths, and CUDA-graph replay.

- ``fp32``: float32 with TF32 off for cuDNN convolutions and matrix products. PyTorch lets cuDNN
  use TF32 by default, which moves the released network 7.7e-5 off the authors' reference
  vectors (outside the 1e-5 parity); with TF32 off it is 5.4e-7 (measured on an H100).
- ``tf32``: TF32 tensor cores for convolutions and matrix products.
- ``bf16``: bfloat16 autocast.

Each path sets the switches it needs around every call and restores them, so two describers in
one process (or a user's own model) keep their own. :class:`GraphBackend` captures one forward
pass of a fixed batch (the node's: one frame, or its six turns) in a CUDA graph and replays it:
the launch overhead of the network's ~200 kernels is most of a pass at batch 1. :meth:`GraphBackend.reserve`
captures another graph for a larger batch (offline evaluation describes many frames per call); a
batch between captured sizes is padded into the next larger graph (rows are independent: the
network is in eval mode). A larger batch runs eagerly; a capture that fails leaves the eager path,
with a warning.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ...errors import RuntimeSetupError

if TYPE_CHECKING:
    from ..models import LCPR
    from ..turn_average import TurnedNetwork

log = logging.getLogger(__name__)

CUDA_PRECISIONS = ("fp32", "tf32", "bf16")
#: auto on a GPU keeps the fastest path whose descriptors are at least this close to exact fp32
GPU_COSINE = 0.9999


@contextlib.contextmanager
def float32_math(*, tf32: bool) -> Iterator[None]:
    """cuDNN convolutions and CUDA matrix products in TF32 (``tf32``) or in full float32, then as before."""
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
    """The arithmetic ``precision`` names, for a forward pass on ``device`` (see the module doc)."""
    with contextlib.ExitStack() as stack:
        stack.enter_context(torch.inference_mode())
        if device.type == "cuda":
            stack.enter_context(float32_math(tf32=precision == "tf32"))
        stack.enter_context(torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16"))
        yield


def gpu_name(device: str | torch.device) -> str:
    """The GPU's name (every GPU speed figure names it)."""
    return torch.cuda.get_device_name(torch.device(device))


class GraphBackend:
    """CUDA graphs of one forward pass for fixed batches, replayed; a smaller batch is padded into the next
    captured size, a larger one runs eagerly."""

    def __init__(self, model: LCPR | TurnedNetwork, *, device: str, precision: str, batch: int,
                 warmup: int = 3) -> None:
        from .backends import TorchBackend

        if precision not in CUDA_PRECISIONS:
            raise RuntimeSetupError(f"precision={precision!r} cannot be captured; accepted: {CUDA_PRECISIONS}")
        self.eager = TorchBackend(model, device=device, precision=precision)
        self.name, self.runtime = precision, "torch"
        self.model, self.device, self.batch, self.warmup = model, torch.device(device), batch, warmup
        #: batch size -> (graph, its input images, its input ranges, its output), smallest first
        self._graphs: dict[int, tuple[torch.cuda.CUDAGraph, torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self.reserve(batch)

    def reserve(self, batch: int) -> bool:
        """Capture a graph for ``batch`` rows too (if not yet); False, with a warning, where the capture fails
        (out of memory, say): such batches then run eagerly."""
        if batch in self._graphs:
            return True
        images, ranges = self.model.example_inputs(batch)
        images, ranges = images.to(self.device), ranges.to(self.device)
        try:
            graph, out = self._capture(images, ranges)
        except (RuntimeError, torch.cuda.OutOfMemoryError) as err:
            log.warning("LCPR: CUDA graph capture of the %s network (batch %d) failed (%s); running it eagerly",
                        self.name, batch, err)
            torch.cuda.empty_cache()
            return False
        self._graphs[batch] = (graph, images, ranges, out)
        self._graphs = dict(sorted(self._graphs.items()))
        return True

    def _capture(self, images: torch.Tensor, ranges: torch.Tensor) -> tuple[torch.cuda.CUDAGraph, torch.Tensor]:
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side), numerics(self.device, self.name):
            for _ in range(self.warmup):  # cuDNN picks its kernels and the allocator its blocks before capture
                self.model(images, ranges)
        torch.cuda.current_stream(self.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with numerics(self.device, self.name), torch.cuda.graph(graph):
            out = self.model(images, ranges)
        return graph, out

    @property
    def captured(self) -> bool:
        """Whether a graph of the batch this backend was built for exists."""
        return self.batch in self._graphs

    @property
    def batches(self) -> tuple[int, ...]:
        """The batch sizes with a captured graph."""
        return tuple(self._graphs)

    def __call__(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        rows = images.shape[0]
        size = next((b for b in self._graphs if b >= rows), None)
        if size is None:
            return self.eager(images, ranges)
        graph, static_images, static_ranges, out = self._graphs[size]
        try:
            static_images[:rows].copy_(images, non_blocking=True)
            static_ranges[:rows].copy_(ranges, non_blocking=True)
            graph.replay()
            return out[:rows].float().cpu().numpy()
        except RuntimeError as err:  # a broken graph must not stop the node: the eager path stays
            log.warning("LCPR: CUDA graph replay failed (%s); running the network eagerly from now on", err)
            self._graphs.clear()
            return self.eager(images, ranges)
