"""One line per lcpr_eval report: each method's online Recall@1, max F1 and its threshold.

    python benchmarks/tools/eval_table.py OUT        # reads OUT/eval_*/report.json, in name order

Used by benchmarks/studies/lcpr_train_corpus.sh and lcpr_gpu_released.sh to print their results.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lcpr_common.cli import tool_main


def report_line(path: Path) -> str:
    """'<folder> <method>: R@1 .. max F1 .. thr .. | ...' for one report.json."""
    methods = {m["name"]: m.get("online") or {} for m in json.loads(path.read_text())["methods"]}
    cells = [f"{name}: R@1 {m.get('recall_at', {}).get('1', float('nan')):.3f} max F1 {m.get('max_f1') or 0:.3f} "
             f"thr {m.get('max_f1_threshold')}" for name, m in methods.items()]
    return f"{path.parent.name} " + " | ".join(cells)


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="a folder of lcpr_eval outputs named eval_*")
    args = p.parse_args(argv)
    for path in sorted(args.out.glob("eval_*/report.json")):
        print(report_line(path))
    return 0


if __name__ == "__main__":
    sys.exit(main())
