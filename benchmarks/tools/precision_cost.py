"""What an inference path costs in place recognition: lcpr_eval per path on held-out drives.

    python benchmarks/tools/precision_cost.py out/int8/synth_s7.bag out/int8/synth_s9.bag \
        [--weights weights/lcpr_synth_narrow.pth] [--paths fp32 int8] [--out out/precision_cost]
    python benchmarks/tools/precision_cost.py out/int8/synth_s3.bag --paths fp32 int8 \
        --int8-nodes . '^/layer\\d_[il]/'        # int8 variants, each quantised before it runs

Runs ``lcpr_eval`` (retrieval only: no verification, no Scan Context) once per bag and path
and prints the online Recall@1 and max F1 of each, with the difference to the first path,
and the mean over the bags. The int8 graph must exist (``lcpr_quantize``; it calibrates on a
synthetic *training* city, seed 1 by default, never on these drives); with ``--int8-nodes``
this script makes it, once per pattern (``lcpr_quantize --nodes``), and leaves the last one in place.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lcpr_common.cli import tool_main


@tool_main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--weights", default="weights/lcpr_synth_narrow.pth")
    parser.add_argument("--paths", nargs="+", default=["fp32", "int8"])
    parser.add_argument("--int8-nodes", nargs="+", default=None, metavar="REGEX",
                        help="quantise with each pattern (lcpr_quantize --nodes) and run int8 once per pattern")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("out/precision_cost"))
    args = parser.parse_args(argv)

    from lcpr_core.evaluation.eval_report import online
    from lcpr_offline.lcpr_quantize import main as lcpr_quantize
    from lcpr_ros.evaluate import main as lcpr_eval

    runs: list[tuple[str, str, str | None]] = []  # (label, precision, nodes to quantise first)
    for path in args.paths:
        if path == "int8" and args.int8_nodes:
            runs += [(f"int8[{nodes}]", "int8", nodes) for nodes in args.int8_nodes]
        else:
            runs.append((path, path, None))
    scores: dict[str, dict[str, tuple[float, float]]] = {bag.stem: {} for bag in args.bags}
    for label, precision, nodes in runs:
        if nodes is not None and lcpr_quantize(["--weights", args.weights, "--nodes", nodes, "--no-progress",
                                                 "--threads", str(args.threads)]) != 0:
            print(f"lcpr_quantize failed with --nodes {nodes!r}", file=sys.stderr)
            return 1
        for bag in args.bags:
            out = args.out / bag.stem / label.replace("/", "_")
            rc = lcpr_eval([str(bag), "--weights", args.weights, "--precision", precision, "--threads",
                            str(args.threads), "--no-verify", "--no-scan-context", "--quiet", "--out", str(out)])
            if rc != 0:
                print(f"lcpr_eval failed on {bag} with --precision {precision} (exit {rc})", file=sys.stderr)
                return rc
            scores[bag.stem][label] = online(out / "report.json")
    first = runs[0][0]
    width = max(len(label) for label, _, _ in runs) + 1
    print(f"online protocol, {args.weights}; difference to {first} in points")
    print(f"{'drive':<14} {'path':<{width}} {'Recall@1':>9} {'diff':>6} {'max F1':>7} {'diff':>6}")
    mean = {label: (sum(v[label][0] for v in scores.values()) / len(scores),
                    sum(v[label][1] for v in scores.values()) / len(scores)) for label, _, _ in runs}
    for name, row in [*scores.items(), ("mean", mean)]:
        r0, f0 = row[first]
        for label, (r1, f1) in row.items():
            print(f"{name:<14} {label:<{width}} {r1:>9.3f} {100 * (r1 - r0):>+6.1f} "
                  f"{f1:>7.3f} {100 * (f1 - f0):>+6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
