"""What an inference path costs in place recognition: lcpr_eval per path on held-out drives.

    python benchmarks/precision_cost.py out/int8/synth_s7.bag out/int8/synth_s9.bag \
        [--weights weights/lcpr_synth_narrow.pth] [--paths fp32 int8] [--out out/precision_cost]

Runs ``lcpr_eval`` (retrieval only: no verification, no Scan Context) once per bag and path
and prints the online Recall@1 and max F1 of each, with the difference to the first path.
The int8 graph must exist (``lcpr_quantize``; it calibrates on a synthetic *training* city,
seed 1 by default, never on these held-out drives).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lcpr_ros.evaluate import main as lcpr_eval


def online(report: Path) -> tuple[float, float]:
    method = json.loads(report.read_text())["methods"][0]["online"]
    return float(method["recall_at"]["1"]), float(method["max_f1"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--weights", default="weights/lcpr_synth_narrow.pth")
    parser.add_argument("--paths", nargs="+", default=["fp32", "int8"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("out/precision_cost"))
    args = parser.parse_args(argv)
    rows = []
    for bag in args.bags:
        scores = {}
        for path in args.paths:
            out = args.out / bag.stem / path
            rc = lcpr_eval([str(bag), "--weights", args.weights, "--precision", path, "--threads", str(args.threads),
                            "--no-verify", "--no-scan-context", "--quiet", "--out", str(out)])
            if rc != 0:
                print(f"lcpr_eval failed on {bag} with --precision {path} (exit {rc})", file=sys.stderr)
                return rc
            scores[path] = online(out / "report.json")
        rows.append((bag.stem, scores))
    first = args.paths[0]
    print(f"online protocol, {args.weights}; difference to {first} in points")
    print(f"{'drive':<14} {'path':<6} {'Recall@1':>9} {'diff':>6} {'max F1':>7} {'diff':>6}")
    for name, scores in rows:
        r0, f0 = scores[first]
        for path, (r1, f1) in scores.items():
            print(f"{name:<14} {path:<6} {r1:>9.3f} {100 * (r1 - r0):>+6.1f} {f1:>7.3f} {100 * (f1 - f0):>+6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
