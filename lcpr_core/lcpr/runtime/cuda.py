"""The network on a CUDA GPU: CUDA-graph replay of the paths in :mod:`.numerics`.

:class:`GraphBackend` captures one forward pass of a fixed batch (the node's: one frame, or its six turns)
in a CUDA graph and replays it: at batch 1 launching the network's ~200 kernels one by one costs more than
their arithmetic. :meth:`GraphBackend.reserve` captures another graph for a larger batch (offline
evaluation describes many frames per call); a batch between captured sizes is padded into the next larger
graph (rows are independent: the network is in eval mode). A larger batch runs eagerly; a capture that
fails leaves the eager path, with a warning.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...errors import RuntimeSetupError
from .backends import TorchBackend
from .numerics import CUDA_PRECISIONS, numerics

if TYPE_CHECKING:
    from ..models import LCPR
    from ..turn_average import TurnedNetwork

log = logging.getLogger(__name__)

#: auto on a GPU keeps the fastest path whose descriptors are at least this close to exact fp32
GPU_COSINE = 0.9999


def gpu_name(device: str | torch.device) -> str:
    """The GPU's name (every GPU speed figure names it)."""
    return torch.cuda.get_device_name(torch.device(device))


class GraphBackend:
    """CUDA graphs of one forward pass for fixed batches, replayed; a smaller batch is padded into the next
    captured size, a larger one runs eagerly."""

    def __init__(self, model: LCPR | TurnedNetwork, *, device: str, precision: str, batch: int,
                 warmup: int = 3) -> None:
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
