"""Static int8 quantisation of the exported LCPR graph (ONNX Runtime QDQ), from calibration inputs.

:func:`quantize` feeds preprocessed model inputs to ONNX Runtime's static quantiser (QDQ format,
per-channel int8 weights, uint8 activations, MinMax ranges by default) for the convolutions named
by :data:`DEFAULT_NODES`, and writes the result next to the fp32 graph under the same hash
(:mod:`.onnx_cache`), where ``model.precision: int8`` finds it. Where the calibration inputs come
from is the caller's: the ``lcpr_quantize`` command (:mod:`lcpr_offline.lcpr_quantize`) renders
them from a synthetic training city.
"""
from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
import onnx
import torch

from ...errors import RuntimeSetupError
from .onnx_cache import exported_graph, onnx_path

if TYPE_CHECKING:
    from ..config import ModelConfig
    from ..models import LCPR

DEFAULT_OPS = ("Conv",)
#: Which nodes (of DEFAULT_OPS) are quantised, by name: the ResNet blocks of both branches and the image
#: stem; the range-image stem (conv_l), the fusion and attention stay fp32. The rule, fixed before any
#: held-out drive was run with it (docs/studies/inference_paths.md): the highest descriptor cosine to torch fp32 on
#: a validation city (seed 3, bundled weights) among the variants of benchmarks/studies/int8_variants.py that reach
#: 3.5x torch fp32 at the released size in the int8 path's own runtime. ``--nodes .`` quantises every
#: convolution (faster, cosine 0.86 at worst); the range-image stem is what costs most.
DEFAULT_NODES = r"^/(conv1_i|layer\d_[il])/"
METHODS = {"minmax": lambda m: m.MinMax, "percentile": lambda m: m.Percentile, "entropy": lambda m: m.Entropy}


class Network(Protocol):
    """What :func:`quantize` reads of a describer: the configuration the graph is hashed by, and its network."""

    config: ModelConfig
    model: LCPR | None


class _Reader:
    """onnxruntime.quantization.CalibrationDataReader over preprocessed inputs."""

    def __init__(self, inputs: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> None:
        self._items: Iterator[tuple[torch.Tensor, torch.Tensor]] = iter(inputs)

    def get_next(self) -> dict[str, np.ndarray] | None:
        item = next(self._items, None)
        if item is None:
            return None
        return {"images": item[0].numpy(), "ranges": item[1].numpy()}


def quantize(describer: Network, inputs: Sequence[tuple[torch.Tensor, torch.Tensor]], *,
             ops: Sequence[str] = DEFAULT_OPS, nodes: str = DEFAULT_NODES, method: str = "minmax") -> Path:
    """Write the int8 graph of ``describer``'s config (atomically) and return its path."""
    from onnxruntime.quantization import (
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    config, model = describer.config, describer.model
    assert model is not None
    source = exported_graph(config, model)
    target = onnx_path(config, "int8")
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".int8-") as tmp:
        prepared, written = Path(tmp) / "prepared.onnx", Path(tmp) / "int8.onnx"
        quant_pre_process(str(source), str(prepared), skip_symbolic_shape=True)
        pattern = re.compile(nodes)
        chosen = [n.name for n in onnx.load(str(prepared)).graph.node if n.op_type in ops and pattern.search(n.name)]
        if not chosen:
            raise RuntimeSetupError(f"no {'/'.join(ops)} node matches {nodes!r}; nothing would be quantised")
        quantize_static(str(prepared), str(written), _Reader(inputs), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        op_types_to_quantize=list(ops), nodes_to_quantize=chosen,
                        calibrate_method=METHODS[method](CalibrationMethod),
                        extra_options={"CalibPercentile": 99.99} if method == "percentile" else {})
        os.chmod(written, 0o644)
        os.replace(written, target)
    return target
