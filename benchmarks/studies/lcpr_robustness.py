"""LCPR's robustness studies, reproduced on held-out synthetic cities (the paper's Table III, Fig. 5, Fig. 6).

Only the query keyframes are perturbed, one condition at a time (:mod:`lcpr_offline.lcpr_robustness`):
the vehicle turned by k camera slots (yaw), each camera or a quarter of the LiDAR range image
blacked out (occlusion), every image's brightness scaled (lighting).

Recall@1 per condition and city goes to ``OUT/robustness.json`` and ``OUT/robustness.png``. No
threshold is chosen here (Recall@1 has none); the default cities are the test cities of
``benchmarks/recipes/lcpr_corpus.sh`` (grid seeds 7 and 9, 300 keyframes; the KITTI-00 route with seed 21,
900 keyframes), which no training run or choice of the bundled weights read.

    python benchmarks/studies/lcpr_robustness.py [--cities grid:7 grid:9 kitti00:21:900] [--frames 300] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from lcpr_core.atomic import atomic_path
from lcpr_core.lcpr.describer import Describer, ModelConfig
from lcpr_core.pretrained import default_weights
from lcpr_core.timing import cpu_model
from lcpr_offline.lcpr_robustness import STUDIES, parse_city, plot, render, study_city

REPO = Path(__file__).resolve().parents[2]


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cities", nargs="+", type=parse_city,
                   default=[("grid", 7, None), ("grid", 9, None), ("kitti00", 21, 900)])
    p.add_argument("--frames", type=int, default=300, help="keyframes of a city that names none (default 300)")
    p.add_argument("--image-size", type=int, nargs=2, default=(400, 225), metavar=("W", "H"))
    p.add_argument("--weights", default="", help="LCPR weights (default: the bundled narrow weights)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--studies", nargs="+", choices=STUDIES, default=list(STUDIES), help="default: all three")
    p.add_argument("--out", type=Path, default=REPO / "out" / "robustness")
    args = p.parse_args(argv)
    weights = args.weights or default_weights()
    if not weights:
        p.error("no --weights and no bundled weights in this checkout")
    describer = Describer(ModelConfig(weights=str(weights), lidar="nuscenes_lidar_top", precision="fp32",
                                      threads=args.threads))
    start = time.perf_counter()
    results = {}
    frames = {}
    for route, seed, count in args.cities:
        name = f"{route}:{seed}"
        frames[name] = count or args.frames
        results[name] = study_city(describer, render(route, seed, frames[name], tuple(args.image_size)), name=name,
                                   studies=args.studies)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"weights": str(weights), "cpu": cpu_model(), "python": platform.python_version(),
              "frames": frames, "seconds": time.perf_counter() - start, "recall_at_1": results}
    with atomic_path(args.out / "robustness.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2) + "\n")
    plot(results, args.out / "robustness.png", weights=Path(weights).name)
    print(f"written: {args.out / 'robustness.json'}, {args.out / 'robustness.png'} ({report['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
