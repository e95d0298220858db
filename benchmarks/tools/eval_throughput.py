"""Keyframes per second of ``lcpr_eval`` (retrieval only) for several batch sizes and weights, and the bag's
reading alone, in one process, naming the CPU and GPU.

    python benchmarks/tools/eval_throughput.py BAG [--device cuda] [--weights seeded bundled FILE] [--batches 1 16]

Each run is :func:`lcpr_offline.lcpr_evaluate.evaluate_bag` without verification or Scan Context (what
bounds a run with verification is the CPU registration: ``verify_cost.py``). Keyframes per second count
the frames read and through the detector (``detect_time_s``), not the setup before (model, ``auto``'s
measurement, graph capture) nor the evaluation after. ``seeded`` is the released size with random weights
(speed does not depend on their values; their descriptors are all alike, so their Recall@1 is noise);
``bundled`` the trained narrow weights, whose Recall@1 shows that the batch size changes no result.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from lcpr_common.cli import tool_main


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path, help="a nuScenes-rig rosbag2 (e.g. citysim --image-size 1600x900)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--weights", nargs="+", default=["seeded"], help="LCPR weights, each run in turn (default: "
                   "seeded, the released size)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 16], help="frames per network call (default 1 16)")
    p.add_argument("--limit", type=int, default=0, help="frames per run (default all)")
    args = p.parse_args(argv)

    import torch

    from lcpr_core import ModelConfig
    from lcpr_core.evaluation import throughput_line
    from lcpr_core.lcpr.runtime.cuda import gpu_name
    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import VerifierConfig
    from lcpr_offline.lcpr_evaluate import EvalOptions, evaluate_bag
    from msg_tools.bags import read_frames
    from msg_tools.frames import NUSCENES_TOPICS

    gpu = f", GPU {gpu_name(args.device)}" if torch.device(args.device).type == "cuda" else ""
    print(f"CPU {cpu_model()}{gpu}; bag {args.bag}")
    tic = time.perf_counter()
    stream = read_frames(args.bag, topics=NUSCENES_TOPICS)
    indexed = time.perf_counter() - tic
    count = sum(1 for _ in stream)
    stream.close()
    read = time.perf_counter() - tic - indexed
    print(f"reading alone (one thread): index {indexed:.2f} s, {count} frames in {read:.2f} s = "
          f"{read / max(count, 1) * 1e3:.2f} ms a frame")
    rows = []
    for weights in args.weights:
        for batch in args.batches:
            opts = EvalOptions(model=ModelConfig(weights=weights, device=args.device), batch=batch,
                               verify=VerifierConfig(enabled=False), scan_context=None, pose_graph=False,
                               limit=args.limit)
            report = evaluate_bag(args.bag, opts, progress=False)
            keyframes = int(report.counts["keyframes"])
            recall = report.methods[0].online.recall_at.get(1)
            rows.append((weights, batch, keyframes / report.detect_time_s, report.setup_time_s, recall))
            print(f"{weights}, batch {batch}: {throughput_line(report)}; Recall@1 {recall}", flush=True)
    print("\n| weights | batch | keyframes/s | setup s | Recall@1 |\n|---|---|---|---|---|")
    for weights, batch, rate, setup, recall in rows:
        print(f"| {weights} | {batch} | {rate:.1f} | {setup:.1f} | {'-' if recall is None else f'{recall:.3f}'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
