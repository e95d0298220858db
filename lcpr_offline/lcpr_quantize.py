"""``lcpr_quantize``: the int8 graph of LCPR (ONNX Runtime), calibrated on a synthetic drive.

    lcpr_quantize [--weights FILE] [--calibration-seed 1] [--frames 48] [--nodes REGEX] [--method minmax]

The calibration frames are rendered from a synthetic drive of a *training* city (seed 1 by
default; seeds 7, 9, 21, 31 and 37 are held-out test cities and are refused), preprocessed exactly as the node
does, and fed to ONNX Runtime's static quantiser (QDQ format, per-channel int8 weights, uint8
activations, MinMax ranges) for the convolutions of the ResNet blocks and the image stem
(:data:`~lcpr_core.lcpr.runtime.quantize.DEFAULT_NODES`). The result is
written next to the fp32 graph under the same hash (:mod:`lcpr_core.lcpr.runtime.onnx_cache`), where
``model.precision: int8`` finds it. Its cosine to torch fp32 on the
calibration frames is printed; what it costs in Recall@1 is measured with
``lcpr_eval --precision int8`` on held-out drives (docs/studies/inference_paths.md).
"""
from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

import numpy as np
import torch

from citysim import SynthConfig, SyntheticDrive
from lcpr_common.progress import progress_iter
from lcpr_core.errors import RuntimeSetupError
from lcpr_core.lcpr.describer import Describer, ModelConfig
from lcpr_core.lcpr.runtime.choose import cosine
from lcpr_core.lcpr.runtime.quantize import DEFAULT_NODES, DEFAULT_OPS, METHODS, quantize
from lcpr_core.pretrained import default_weights

__all__ = ["TEST_SEEDS", "calibration_inputs", "main", "quantize"]  # quantize: importable beside its inputs

TEST_SEEDS = (7, 9, 21, 31, 37)  # synthetic cities reserved for held-out figures (21: the corpus KITTI-00 route)


def calibration_inputs(describer: Describer, *, seed: int, frames: int, image_size: tuple[int, int] = (400, 225),
                       progress: bool = True) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``frames`` preprocessed model inputs spread along a synthetic nuScenes-rig drive of ``seed``."""
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
