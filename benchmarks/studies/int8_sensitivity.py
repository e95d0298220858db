"""Which convolutions int8 hurts: descriptor cosine to torch fp32 with one group of convolutions left fp32.

    python benchmarks/studies/int8_sensitivity.py [--weights FILE] [--calibration-frames 48] [--cosine-frames 24]

Every convolution is grouped by the module it belongs to (``/layer2_i``, ``/fusion3``, ...). For each
group the graph is quantised with every convolution *except* that group, calibrated on a synthetic
training city (seed 1), and compared with torch fp32 on frames of a validation city (seed 3): the
lowest, 10th-percentile and median cosine. The groups whose removal raises the cosine most are the
ones int8 hurts; leaving them fp32 is what ``lcpr_quantize --nodes`` is for. Validation data only:
the held-out drives of README "Inference paths" are never read here.
"""
from __future__ import annotations

import argparse
import re
from collections import Counter

import onnx

from lcpr_core.lcpr.runtime.onnx_cache import exported_graph
from lcpr_offline.lcpr_int8_study import Int8Bench, add_arguments


def conv_groups(path: str) -> Counter[str]:
    """Module prefix -> number of convolutions, from the exported graph's node names."""
    graph = onnx.load(path).graph
    return Counter("/".join(n.name.split("/")[:2]) for n in graph.node if n.op_type == "Conv")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser, weights_help="weights file (default: bundled)")
    bench = Int8Bench.from_args(parser.parse_args(argv))
    assert bench.fp32.model is not None
    groups = conv_groups(str(exported_graph(bench.fp32.config, bench.fp32.model)))
    print(f"int8 sensitivity, {bench.weights}: cosine to torch fp32 on {len(bench.validation)} validation frames "
          "(seed 3)")
    print(f"{'left fp32':<16} {'convs':>5} {'min cos':>8} {'p10 cos':>8} {'median':>9}")
    print(f"{'(none)':<16} {0:>5} {bench.cosines(bench.int8('.'))}", flush=True)
    for group, count in sorted(groups.items()):
        pattern = rf"^(?!{re.escape(group)}/)"
        print(f"{group:<16} {count:>5} {bench.cosines(bench.int8(pattern))}", flush=True)
    bench.restore_default()


if __name__ == "__main__":
    main()
