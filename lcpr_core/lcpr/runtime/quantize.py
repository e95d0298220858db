"""Static int8 quantisation of the exported LCPR graph (ONNX Runtime), calibrated on synthetic drives.

    lcpr_quantize [--weights FILE] [--calibration-seed 1] [--frames 48] [--nodes REGEX] [--method minmax]

The calibration frames are rendered from a synthetic drive of a *training* city (seed 1 by
default; seeds 7, 9, 21, 31 and 37 are held-out test cities and are refused), preprocessed exactly as the node
does, and fed to ONNX Runtime's static quantiser (QDQ format, per-channel int8 weights, uint8
activations, MinMax ranges) for the convolutions of the ResNet blocks and the image stem
(:data:`DEFAULT_NODES`). The result is
written next to the fp32 graph under the same hash (:mod:`.onnx_cache`), where
``model.precision: int8`` finds it. Its cosine to torch fp32 on the
calibration frames is printed; what it costs in Recall@1 is measured with
``lcpr_eval --precision int8`` on held-out drives (README, "Inference paths").
"""
from __future__ import annotations

import argparse
import logging
import os
import re
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import onnx
import torch

from msg_tools.progress import progress_iter

from ...errors import RuntimeSetupError
from .choose import cosine
from .onnx_cache import exported_graph, onnx_path

if TYPE_CHECKING:
    from ..describer import Describer

log = logging.getLogger(__name__)

TEST_SEEDS = (7, 9, 21, 31, 37)  # synthetic cities reserved for held-out figures (21: the corpus KITTI-00 route)
DEFAULT_OPS = ("Conv",)
#: Which nodes (of DEFAULT_OPS) are quantised, by name: the ResNet blocks of both branches and the image
#: stem; the range-image stem (conv_l), the fusion and attention stay fp32. The rule, fixed before any
#: held-out drive was run with it (README "Inference paths"): the highest descriptor cosine to torch fp32 on
#: a validation city (seed 3, bundled weights) among the variants of benchmarks/int8_variants.py that reach
#: 3.5x torch fp32 at the released size in the int8 path's own runtime. ``--nodes .`` quantises every
#: convolution (faster, cosine 0.86 at worst); the range-image stem is what costs most.
DEFAULT_NODES = r"^/(conv1_i|layer\d_[il])/"
METHODS = {"minmax": lambda m: m.MinMax, "percentile": lambda m: m.Percentile, "entropy": lambda m: m.Entropy}


def calibration_inputs(describer: Describer, *, seed: int, frames: int, image_size: tuple[int, int] = (400, 225),
                       progress: bool = True) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``frames`` preprocessed model inputs spread along a synthetic nuScenes-rig drive of ``seed``."""
    from citysim import SynthConfig, SyntheticDrive

    if seed in TEST_SEEDS:
        raise RuntimeSetupError(f"calibration seed {seed} is a held-out test city ({TEST_SEEDS}); choose another")
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", frames=max(frames * 3, 30), seed=seed,
                                       image_size=image_size, camera_drop=0.0))
    picks = np.linspace(0, len(drive) - 1, frames).round().astype(int)
    out = []
    for i in progress_iter(picks, total=len(picks), desc="calibration frames", unit="frame", enabled=progress):
        frame = drive.frame(int(i))
        images = [None if c is None else (c.rgb if c.rgb is not None else c.jpeg) for c in frame.cameras]
        points = np.stack([frame.cloud[k] for k in ("x", "y", "z")], axis=1).astype(np.float32)
        out.append(describer.inputs(images, points))
    return out


class _Reader:
    """onnxruntime.quantization.CalibrationDataReader over preprocessed inputs."""

    def __init__(self, inputs: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> None:
        self._items: Iterator[tuple[torch.Tensor, torch.Tensor]] = iter(inputs)

    def get_next(self) -> dict[str, np.ndarray] | None:
        item = next(self._items, None)
        if item is None:
            return None
        return {"images": item[0].numpy(), "ranges": item[1].numpy()}


def quantize(describer: Describer, inputs: Sequence[tuple[torch.Tensor, torch.Tensor]], *,
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


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lcpr_quantize", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", default=None, help="LCPR weights (default: the bundled trained weights)")
    p.add_argument("--calibration-seed", type=int, default=1, help="synthetic training city to calibrate on")
    p.add_argument("--frames", type=int, default=48, help="calibration frames")
    p.add_argument("--ops", nargs="+", default=list(DEFAULT_OPS), help="operator types to quantise (default Conv)")
    p.add_argument("--nodes", default=DEFAULT_NODES,
                   help=f"regular expression: names of the nodes to quantise (default {DEFAULT_NODES!r}: the "
                        "ResNet blocks and the image stem; '.' = every convolution, faster and further from fp32)")
    p.add_argument("--method", choices=sorted(METHODS), default="minmax", help="activation ranges (default minmax)")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from ...pretrained import default_weights
    from ..describer import Describer, ModelConfig

    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    weights = args.weights or default_weights()
    if not weights:
        print("lcpr_quantize: no --weights given and no bundled weights found", file=sys.stderr)
        return 2
    if args.frames < 1:
        print(f"lcpr_quantize: --frames {args.frames}; it must be >= 1", file=sys.stderr)
        return 2
    try:
        describer = Describer(ModelConfig(weights=str(weights), precision="fp32", threads=args.threads))
        inputs = calibration_inputs(describer, seed=args.calibration_seed, frames=args.frames,
                                    progress=not args.no_progress)
        target = quantize(describer, inputs, ops=args.ops, nodes=args.nodes, method=args.method)
        int8 = Describer(ModelConfig(weights=str(weights), precision="int8", threads=args.threads),
                         model=describer.model)
    except RuntimeSetupError as err:
        print(f"lcpr_quantize: {err}", file=sys.stderr)
        return 1
    cos = min(cosine(int8.describe_tensors(*x), describer.describe_tensors(*x)) for x in inputs)
    print(f"int8 graph: {target}\nlowest cosine to torch fp32 over the {len(inputs)} calibration frames: {cos:.6f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
