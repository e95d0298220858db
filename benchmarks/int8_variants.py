"""Which convolutions to quantise: int8 variants by descriptor cosine on a validation city and by speed.

    python benchmarks/int8_variants.py                      # bundled weights: cosine on seed 3, ms
    python benchmarks/int8_variants.py --weights "" --cosine-frames 0   # seeded released size: ms only

Each variant is calibrated on a synthetic training city (seed 1) and compared with torch fp32
on frames of a validation city (seed 3): the lowest, 10th-percentile and median cosine. Recall@1
on the validation city (benchmarks/precision_cost.py on a seed-3 drive) chose the default of
``lcpr_quantize`` (lcpr_core.runtime.quantize.DEFAULT_NODES); see README "Inference paths".
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
from functools import partial

import numpy as np

from lcpr_core import Describer, ModelConfig
from lcpr_core.pretrained import default_weights
from lcpr_core.runtime import cpu_model
from lcpr_core.runtime.choose import cosine
from lcpr_core.runtime.quantize import calibration_inputs, quantize
from lcpr_core.timing import median_seconds

VARIANTS = {
    "every convolution": r".",
    "ResNet blocks + image stem": r"^/(conv1_i|layer\d_[il])/",
    "ResNet blocks + stems": r"^/(conv1_i|conv_l|layer\d_[il])/",
    "ResNet blocks": r"^/layer\d_[il]/",
    "image ResNet + image stem": r"^/(conv1_i|layer\d_i)/",
    "ResNet layers 2-4": r"^/layer[234]_[il]/",
    "image ResNet layers 2-4": r"^/layer[234]_i/",
}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=None, help="weights file; '' = seeded released size (default: bundled)")
    parser.add_argument("--calibration-frames", type=int, default=48)
    parser.add_argument("--cosine-frames", type=int, default=24)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    weights = str(default_weights()) if args.weights is None else args.weights
    base = ModelConfig(weights=weights, threads=args.threads)
    fp32 = Describer(dataclasses.replace(base, precision="fp32"))
    calibration = calibration_inputs(fp32, seed=1, frames=args.calibration_frames)
    validation = calibration_inputs(fp32, seed=3, frames=args.cosine_frames) if args.cosine_frames else []
    expected = [fp32.describe_tensors(*x) for x in validation]
    images, ranges = calibration[0]
    onnx = Describer(dataclasses.replace(base, precision="onnx"), model=fp32.model)
    reference = {"torch fp32": fp32, "onnx fp32": onnx}
    print(f"int8 variants, {weights or 'seeded weights'} ({fp32.config.image_size[0]} x {fp32.config.image_size[1]} "
          f"images, width {fp32.config.width}), {args.threads} threads, {cpu_model()}")
    print(f"{'variant':<30} {'ms/frame':>9} {'min cos':>8} {'p10 cos':>8} {'median':>9}")
    for name, d in reference.items():
        ms = statistics.median(median_seconds(partial(d.describe_tensors, images, ranges), repeats=args.repeats)
                               for _ in range(args.rounds))
        print(f"{name:<30} {1000 * ms:>9.1f}")
    for name, pattern in VARIANTS.items():
        quantize(fp32, calibration, nodes=pattern)
        q = Describer(dataclasses.replace(base, precision="int8"), model=fp32.model)
        ms = statistics.median(median_seconds(partial(q.describe_tensors, images, ranges), repeats=args.repeats)
                               for _ in range(args.rounds))
        cs = np.array([cosine(q.describe_tensors(*x), e) for x, e in zip(validation, expected, strict=True)])
        cos = f"{cs.min():>8.5f} {np.quantile(cs, 0.1):>8.5f} {np.median(cs):>9.6f}" if len(cs) else ""
        print(f"{name:<30} {1000 * ms:>9.1f} {cos}", flush=True)
    quantize(fp32, calibration)  # leave the default variant in place


if __name__ == "__main__":
    main()
