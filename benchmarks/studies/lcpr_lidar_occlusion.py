"""Does training with part of the LiDAR blacked out keep LCPR's recall when a quarter of its range image is gone?

    python benchmarks/studies/lcpr_lidar_occlusion.py [--corpus out/corpus] [--search out/config_search]
        [--bundle out/bundle] [--out out/lidar_occlusion] [--epochs 70] [--chance 0.5]

The bundled weights lose most of their Recall@1 when the upper quarter of the range image is gone
(README, robustness studies): nothing in their training ever hid the LiDAR. The plan, fixed before
it ran:

1. Continue the bundled weights' run (``benchmarks/recipes/lcpr_bundle.py``'s ``BUNDLE/run``, epoch 60) with the same
   recipe plus ``--augment-lidar-occlusion CHANCE`` (a 90-degree sector, the top or the bottom quarter
   of the rows, equally likely) to epoch ``--epochs``.
2. Score the bundled weights and the new epoch on the two *validation* cities: online Recall@1 and
   max F1 (retrieval only, as the bundle chooses), and the robustness study's occlusion conditions
   (``lcpr_robustness.py --studies occlusion`` on grid:3 and kitti00:45:900, the same cities).
3. Rule (:func:`lcpr_core.lcpr.training.recipe_rules.lidar_occlusion_replaces`): the new weights are to
   replace the bundled ones only if their mean validation Recall@1 is at most 1 point below the bundled
   weights' and their mean Recall@1 over the three LiDAR quarters (both validation cities) is higher.
   The test cities are not read here.

Writes ``OUT/occlusion.json`` and prints the table and the verdict.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from lcpr_core.atomic import write_atomic
from lcpr_core.lcpr.training.augment import LIDAR_QUARTERS
from lcpr_core.lcpr.training.recipe_rules import lidar_occlusion_replaces, reusable_report
from lcpr_core.timing import cpu_model
from lcpr_offline.lcpr_recipe import CPU, VALIDATION, evaluate, export, run, train_command

ROBUSTNESS_CITIES = ("grid:3", "kitti00:45:900")  # the validation cities of benchmarks/recipes/lcpr_corpus.sh
LIDAR_LABELS = tuple(f"LiDAR 1/4 {part} out" for part in LIDAR_QUARTERS)


def occlusion_scores(py: str, weights: Path, out: Path) -> dict[str, dict[str, float]]:
    """City -> occlusion condition -> Recall@1 (the robustness study on the validation cities)."""
    report = out / "robustness.json"
    if not reusable_report(report, weights, key=("weights",)):
        run([py, str(Path(__file__).with_name("lcpr_robustness.py")), "--cities", *ROBUSTNESS_CITIES,
             "--studies", "occlusion", "--weights", str(weights), "--out", str(out)])
    return {city: studies["occlusion"] for city, studies in json.loads(report.read_text())["recall_at_1"].items()}


def score(py: str, corpus: Path, weights: Path, out: Path) -> dict:
    online = {name: evaluate(py, corpus / f"{name}.bag", weights, out / f"eval_{name}", reuse=True)
              for name in VALIDATION}
    occluded = occlusion_scores(py, weights, out / "robustness")
    lidar = [cities[label] for cities in occluded.values() for label in LIDAR_LABELS]
    return {"weights": str(weights), "online": online, "occlusion": occluded,
            "mean_recall@1": sum(c["recall@1"] for c in online.values()) / len(online),
            "mean_lidar_quarter_recall@1": sum(lidar) / len(lidar)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--corpus", type=Path, default=Path("out/corpus"))
    p.add_argument("--search", type=Path, default=Path("out/config_search"))
    p.add_argument("--bundle", type=Path, default=Path("out/bundle"))
    p.add_argument("--out", type=Path, default=Path("out/lidar_occlusion"))
    p.add_argument("--epochs", type=int, default=70, help="continue the bundled run to this epoch (default 70)")
    p.add_argument("--chance", type=float, default=0.5, help="--augment-lidar-occlusion (default 0.5)")
    p.add_argument("--queries-per-epoch", type=int, default=256)
    args = p.parse_args()
    py = sys.executable
    bundled = args.bundle / "lcpr_synth_narrow.pth"
    if not (args.bundle / "run" / "last.pth").is_file() or not bundled.is_file():
        raise SystemExit(f"{args.bundle} has no run/last.pth or lcpr_synth_narrow.pth: "
                         "run benchmarks/recipes/lcpr_bundle.py")
    run_dir = args.out / "run"
    if not (run_dir / "last.pth").is_file():
        shutil.copytree(args.bundle / "run", run_dir, dirs_exist_ok=True)
    start = json.loads((args.bundle / "run" / "history.json").read_text())[-1]["epoch"]
    trained = json.loads((run_dir / "history.json").read_text())[-1]["epoch"]
    if args.epochs <= start:
        raise SystemExit(f"--epochs {args.epochs}: must be past the bundled run's {start}")
    train_bags = sorted(str(b) for b in args.corpus.glob("train_*.bag"))
    if trained < args.epochs:
        run(train_command(py, CPU, train_bags, run_dir, args.search / CPU.cache_name, args.epochs,
                          queries_per_epoch=args.queries_per_epoch, resume=True,
                          extra=("--augment-lidar-occlusion", str(args.chance))))
    new = args.out / f"occlusion_e{args.epochs}.pth"
    if not new.is_file():
        export(py, run_dir / "last.pth", new, fp32=False)
    results = {f"bundled (epoch {start})": score(py, args.corpus, bundled, args.out / "bundled"),
               f"+ LiDAR occlusion {args.chance:g} (epoch {args.epochs})": score(py, args.corpus, new,
                                                                                 args.out / "occluded")}
    b, a = results.values()
    replace = lidar_occlusion_replaces(b, a)
    text = json.dumps({"cpu": cpu_model(), "chance": args.chance, "epochs": args.epochs, "results": results,
                       "replace": replace}, indent=1)
    write_atomic(args.out / "occlusion.json", lambda tmp: tmp.write_text(text))
    print(f"CPU: {cpu_model()}; validation cities only")
    cities = list(b["occlusion"])
    print("| weights | " + " | ".join(f"{v} R@1 / max F1" for v in VALIDATION) + " | mean R@1 | "
          + " | ".join(f"{c}: {label.removeprefix('LiDAR 1/4 ').removesuffix(' out')}" for c in cities
                       for label in LIDAR_LABELS) + " | mean LiDAR quarter R@1 |")
    print("|---|" + "---|" * (len(VALIDATION) + 2 + len(cities) * len(LIDAR_LABELS)))
    for name, r in results.items():
        online = " | ".join(f"{r['online'][v]['recall@1']:.2f} / {r['online'][v]['max_f1']:.3f}" for v in VALIDATION)
        occl = " | ".join(f"{r['occlusion'][c][label]:.2f}" for c in cities for label in LIDAR_LABELS)
        print(f"| {name} | {online} | {r['mean_recall@1']:.3f} | {occl} | {r['mean_lidar_quarter_recall@1']:.3f} |")
    print(f"rule (fixed before the run): replace the bundled weights: {'yes' if replace else 'no'}")


if __name__ == "__main__":
    main()
