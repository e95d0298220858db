"""One forward pass, several ways: torch (fp32 or bf16), or an exported graph in ONNX Runtime or OpenVINO."""
from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from ...errors import RuntimeSetupError
from .heap import fix_mmap_threshold
from .numerics import CUDA_PRECISIONS, numerics

if TYPE_CHECKING:
    from ..models import LCPR
    from ..turn_average import TurnedNetwork


class Backend(Protocol):
    name: str  # the ModelConfig.precision value it implements
    runtime: str  # what runs it: torch, onnxruntime or openvino

    def __call__(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        """B x N x 3 x H x W images, B x 1 x h x w ranges -> B x 256 float32 descriptors."""


def graph_feeds(images: torch.Tensor, ranges: torch.Tensor) -> dict[str, np.ndarray]:
    """The exported graph's inputs (see .onnx_cache: ``images``, ``ranges``) as float32 arrays."""
    return {"images": images.detach().cpu().float().numpy(), "ranges": ranges.detach().cpu().float().numpy()}


class TorchBackend:
    """The torch model in fp32, tf32 (CUDA only) or under bf16 autocast; fp32 on a GPU has TF32 off (exact)."""

    def __init__(self, model: LCPR | TurnedNetwork, *, device: str = "cpu", precision: str = "fp32") -> None:
        if precision not in CUDA_PRECISIONS:
            raise RuntimeSetupError(f"torch precision {precision!r}; accepted: {', '.join(CUDA_PRECISIONS)}")
        if precision == "tf32" and torch.device(device).type != "cuda":
            raise RuntimeSetupError(f"model.precision='tf32' needs a CUDA device (model.device={device!r}); "
                                    "accepted on the CPU: auto, fp32, bf16, onnx, int8")
        self.model, self.device = model, torch.device(device)
        self.name, self.runtime = precision, "torch"

    def __call__(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        with numerics(self.device, self.name):
            desc = self.model(images.to(self.device, non_blocking=True), ranges.to(self.device, non_blocking=True))
        return desc.float().cpu().numpy()


class OrtBackend:
    """An exported LCPR graph run by ONNX Runtime on the CPU."""

    def __init__(self, path: str | os.PathLike[str], *, threads: int = 0, name: str = "onnx") -> None:
        try:
            import onnxruntime as ort
        except ImportError as err:
            raise RuntimeSetupError(f"model.precision={name!r} needs onnxruntime (pip install onnxruntime); "
                                    "accepted without it: fp32, bf16") from err
        fix_mmap_threshold()  # once per process: see .heap
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads  # 0 = one per core
        options.inter_op_num_threads = 1
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.log_severity_level = 3
        # no busy-waiting between runs: the decoding threads and the verifier need these cores between frames
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types for bad files
            raise RuntimeSetupError(f"ONNX Runtime cannot load {str(path)!r}: {err}") from err
        self.path, self.name, self.runtime = Path(path), name, "onnxruntime"

    def __call__(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        return np.asarray(self.session.run(["descriptor"], graph_feeds(images, ranges))[0], dtype=np.float32)


class OpenVinoBackend:
    """An exported LCPR graph (fp32, or int8 QDQ from lcpr_quantize) run by OpenVINO on the CPU.

    The inference precision is pinned to f32: on CPUs with bf16 support OpenVINO's default runs
    every unquantised layer in bf16, which is not the graph that was checked. The int8 QDQ pairs
    still run as int8 convolutions (VNNI / AMX), which makes this the faster int8 runtime on CPUs that
    have them (docs/studies/inference_paths.md).
    """

    def __init__(self, path: str | os.PathLike[str], *, threads: int = 0, name: str = "int8") -> None:
        try:
            import openvino as ov
        except ImportError as err:
            raise RuntimeSetupError("model.runtime='openvino' needs openvino (pip install openvino); "
                                    "accepted without it: onnxruntime, auto") from err
        fix_mmap_threshold()  # once per process: see .heap
        properties: dict[str, object] = {"INFERENCE_PRECISION_HINT": "f32", "PERFORMANCE_HINT": "LATENCY"}
        if threads:
            properties["INFERENCE_NUM_THREADS"] = threads
        try:
            self.compiled = ov.Core().compile_model(str(path), "CPU", properties)
        except Exception as err:  # OpenVINO raises RuntimeError subclasses of its own for bad files
            raise RuntimeSetupError(f"OpenVINO cannot load {str(path)!r}: {err}") from err
        self.request = self.compiled.create_infer_request()
        self.output = self.compiled.output("descriptor")
        self.path, self.name, self.runtime = Path(path), name, "openvino"

    def __call__(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        # a copy: the request reuses its output buffer
        return np.array(self.request.infer(graph_feeds(images, ranges))[self.output], dtype=np.float32)


class SplitBackend:
    """Runners that each compute a share of a frame's turns (consecutive turns, in order), run side by side.

    Each part is a single-threaded runner of a :class:`~lcpr_core.lcpr.turn_average.TurnedNetwork` graph
    restricted to its turns; their rows (turn-major) are joined in order, so the result is the whole
    turned network's. On few cores this can beat one session with as many intra-op threads: each part
    runs its convolutions start to end without waiting for the others (``precision: auto`` measures it).
    """

    def __init__(self, parts: Sequence[Backend], *, name: str = "onnx") -> None:
        if not parts:
            raise RuntimeSetupError("a split backend needs at least one part; got none")
        self.parts = list(parts)
        self.name, self.runtime = name, self.parts[0].runtime
        self._pool = ThreadPoolExecutor(max_workers=len(self.parts), thread_name_prefix="lcpr-turns")

    def __call__(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        # each part's rows are its turns' B rows each, turn-major: in turn order they join turn-major
        return np.concatenate(list(self._pool.map(lambda part: part(images, ranges), self.parts)))
