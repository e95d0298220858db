"""Which convolutions int8 hurts: descriptor cosine to torch fp32 with one group of convolutions left fp32.

    python benchmarks/int8_sensitivity.py [--weights FILE] [--calibration-frames 48] [--cosine-frames 24]

Every convolution is grouped by the module it belongs to (``/layer2_i``, ``/fusion3``, ...). For each
group the graph is quantised with every convolution *except* that group, calibrated on a synthetic
training city (seed 1), and compared with torch fp32 on frames of a validation city (seed 3): the
lowest, 10th-percentile and median cosine. The groups whose removal raises the cosine most are the
ones int8 hurts; leaving them fp32 is what ``lcpr_quantize --nodes`` is for. Validation data only:
the held-out drives of README "Inference paths" are never read here.
"""
from __future__ import annotations

import argparse
import dataclasses
import re
from collections import Counter

import numpy as np
import onnx

from lcpr_core import Describer, ModelConfig
from lcpr_core.pretrained import default_weights
from lcpr_core.runtime.choose import cosine
from lcpr_core.runtime.onnx_cache import exported_graph
from lcpr_core.runtime.quantize import calibration_inputs, quantize


def conv_groups(path: str) -> Counter[str]:
    """Module prefix -> number of convolutions, from the exported graph's node names."""
    graph = onnx.load(path).graph
    return Counter("/".join(n.name.split("/")[:2]) for n in graph.node if n.op_type == "Conv")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=None, help="weights file (default: bundled)")
    parser.add_argument("--calibration-frames", type=int, default=48)
    parser.add_argument("--cosine-frames", type=int, default=24)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    weights = str(default_weights()) if args.weights is None else args.weights
    base = ModelConfig(weights=weights, threads=args.threads)
    fp32 = Describer(dataclasses.replace(base, precision="fp32"))
    assert fp32.model is not None
    groups = conv_groups(str(exported_graph(fp32.config, fp32.model)))
    calibration = calibration_inputs(fp32, seed=1, frames=args.calibration_frames)
    validation = calibration_inputs(fp32, seed=3, frames=args.cosine_frames)
    expected = [fp32.describe_tensors(*x) for x in validation]

    def measure(pattern: str) -> str:
        quantize(fp32, calibration, nodes=pattern)
        q = Describer(dataclasses.replace(base, precision="int8"), model=fp32.model)
        cs = np.array([cosine(q.describe_tensors(*x), e) for x, e in zip(validation, expected, strict=True)])
        return f"{cs.min():>8.5f} {np.quantile(cs, 0.1):>8.5f} {np.median(cs):>9.6f}"

    print(f"int8 sensitivity, {weights}: cosine to torch fp32 on {len(validation)} validation frames (seed 3)")
    print(f"{'left fp32':<16} {'convs':>5} {'min cos':>8} {'p10 cos':>8} {'median':>9}")
    print(f"{'(none)':<16} {0:>5} {measure('.')}", flush=True)
    for group, count in sorted(groups.items()):
        pattern = rf"^(?!{re.escape(group)}/)"
        print(f"{group:<16} {count:>5} {measure(pattern)}", flush=True)
    quantize(fp32, calibration)  # leave lcpr_quantize's default graph in place


if __name__ == "__main__":
    main()
