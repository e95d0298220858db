"""Which convolutions to quantise: int8 variants by descriptor cosine on a validation city and by speed.

    python benchmarks/studies/int8_variants.py                      # bundled weights: cosine on seed 3, ms
    python benchmarks/studies/int8_variants.py --weights "" --cosine-frames 0   # seeded released size: ms only

Each variant is calibrated on a synthetic training city (seed 1) and compared with torch fp32
on frames of a validation city (seed 3): the lowest, 10th-percentile and median cosine. Recall@1
on the validation city (benchmarks/tools/precision_cost.py on a seed-3 drive) chose the default of
``lcpr_quantize`` (lcpr_core.lcpr.runtime.quantize.DEFAULT_NODES); see README "Inference paths".
"""
from __future__ import annotations

import argparse
import statistics
from functools import partial

from lcpr_core import Describer
from lcpr_core.lcpr.runtime import cpu_model
from lcpr_core.timing import median_seconds
from lcpr_offline.lcpr_int8_study import Int8Bench, add_arguments

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
    add_arguments(parser, weights_help="weights file; '' = seeded released size (default: bundled)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    bench = Int8Bench.from_args(args)
    images, ranges = bench.calibration[0]
    config = bench.fp32.config

    def ms(describer: Describer) -> float:
        return 1000 * statistics.median(
            median_seconds(partial(describer.describe_tensors, images, ranges), repeats=args.repeats)
            for _ in range(args.rounds))

    print(f"int8 variants, {bench.weights or 'seeded weights'} ({config.image_size[0]} x {config.image_size[1]} "
          f"images, width {config.width}), {args.threads} threads, {cpu_model()}")
    print(f"{'variant':<30} {'ms/frame':>9} {'min cos':>8} {'p10 cos':>8} {'median':>9}  runtime")
    for name, d in {"torch fp32": bench.fp32, "onnx fp32": bench.describer("onnx")}.items():
        print(f"{name:<30} {ms(d):>9.1f} {'':>27}  {d.runtime}")
    for name, pattern in VARIANTS.items():
        q = bench.int8(pattern)
        if q is None:
            print(f"{name:<30} {bench.cosines(q)}", flush=True)
            continue
        print(f"{name:<30} {ms(q):>9.1f} {bench.cosines(q):>27}  {q.runtime}", flush=True)
    bench.restore_default()


if __name__ == "__main__":
    main()
