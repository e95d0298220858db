"""Which LCPR configuration generalises best for a CPU training budget (issue #14): a fixed plan.

    python benchmarks/recipes/lcpr_config_search.py [--corpus out/corpus] [--out out/config_search]
                                                    [--budget-min 120]

Trains each configuration of :data:`PLAN` on the 12 training cities of ``benchmarks/recipes/lcpr_corpus.sh``
(the bundled recipe's augmentations), and at each of its checkpoint epochs evaluates the weights of
that epoch on the two *validation* cities (``lcpr_eval --no-verify --no-scan-context``, online
protocol). The test cities are not read. Writes ``search.json`` (every point: configuration, epoch,
cumulative training seconds, validation Recall@1 and max F1 per city) and ``config_search.png``
(mean validation Recall@1 against training time, one line per configuration), and prints the table
(one training run per point, seed 0).

Training time is what ``lcpr_train`` records per epoch (the steps and its per-epoch validation
pass); building a configuration's preprocessed cache is reported beside it, once per input size.
A stage whose start would pass ``--budget-min`` (wall time of the whole search, evaluations
included) is skipped and listed as such. Stages resume: a configuration's later checkpoints
continue from its earlier ones (``lcpr_train --resume``), so the plan's order sets the curve.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lcpr_common.progress import progress_bar
from lcpr_core.atomic import write_atomic
from lcpr_core.timing import cpu_model
from lcpr_offline.lcpr_recipe import (
    CPU,
    VALIDATION,
    Config,
    evaluate,
    export,
    finish_figure,
    in_training_recall,
    one_panel,
    run,
    slug,
    train_command,
    training_seconds,
    validation_cells,
)

FAST_LR = Config("cpu preset, lr 1e-3 (x0.7 / 4 epochs)", (64, 192), (16, 288), 0.25, 1e-3, 4, 0.7)
WIDE = Config("width 0.5 (64x192, 16x288)", (64, 192), (16, 288), 0.5, 3e-4, 6, 0.8)
LARGE = Config("larger inputs (96x288, 32x384, w 0.25)", (96, 288), (32, 384), 0.25, 3e-4, 6, 0.8)

# (configuration, train until this epoch, then evaluate); fixed before any result was seen.
PLAN: tuple[tuple[Config, int], ...] = (
    (CPU, 5), (CPU, 10), (CPU, 20),
    (FAST_LR, 5), (FAST_LR, 10),
    (WIDE, 5), (WIDE, 10),
    (LARGE, 5), (LARGE, 10),
    (CPU, 30),
)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--corpus", type=Path, default=Path("out/corpus"))
    p.add_argument("--out", type=Path, default=Path("out/config_search"))
    p.add_argument("--budget-min", type=float, default=120.0, help="wall-clock budget of the search (<= 120)")
    p.add_argument("--queries-per-epoch", type=int, default=256)
    args = p.parse_args()
    if not 0 < args.budget_min <= 120:
        raise SystemExit(f"--budget-min {args.budget_min}: the search is a CPU budget of at most 120 minutes")
    py = sys.executable
    train_bags = sorted(str(b) for b in args.corpus.glob("train_*.bag"))
    val_bags = [args.corpus / f"{name}.bag" for name in VALIDATION]
    missing = [str(b) for b in val_bags if not b.is_dir()]
    if len(train_bags) < 12 or missing:
        raise SystemExit(f"{args.corpus}: needs 12 train_*.bag (found {len(train_bags)}) and {VALIDATION} "
                         f"(missing {missing}); run benchmarks/recipes/lcpr_corpus.sh first")
    args.out.mkdir(parents=True, exist_ok=True)
    result_path = args.out / "search.json"
    cpu = cpu_model()
    points: list[dict] = []
    skipped: list[str] = []
    start = time.perf_counter()
    bar = progress_bar(len(PLAN), desc="search", unit="stage")
    for config, epochs in PLAN:
        bar.update(1)
        elapsed_min = (time.perf_counter() - start) / 60
        if elapsed_min >= args.budget_min:
            skipped.append(f"{config.name} to epoch {epochs}")
            continue
        run_dir = args.out / slug(config)
        resume = (run_dir / "last.pth").is_file()
        run(train_command(py, config, train_bags, run_dir, args.out / config.cache_name, epochs,
                          queries_per_epoch=args.queries_per_epoch, resume=resume))
        train_s = training_seconds(run_dir, epochs)
        cache_meta = json.loads((args.out / config.cache_name / "meta.json").read_text()) \
            if (args.out / config.cache_name / "meta.json").is_file() else {}
        weights = args.out / f"{slug(config)}_e{epochs}.pth"
        export(py, run_dir / "last.pth", weights, fp32=True)
        cities = {bag.stem: evaluate(py, bag, weights, args.out / f"eval_{slug(config)}_e{epochs}_{bag.stem}")
                  for bag in val_bags}
        point = {"config": config.name, "epochs": epochs, "train_s": round(train_s, 1),
                 "cache_s": cache_meta.get("build_seconds"),
                 "in_training_val_recall@1": in_training_recall(run_dir, epochs),
                 "cities": cities,
                 "mean_recall@1": sum(c["recall@1"] for c in cities.values()) / len(cities),
                 "mean_max_f1": sum(c["max_f1"] for c in cities.values()) / len(cities)}
        points.append(point)
        bar.write(f"{config.name} epoch {epochs}: {train_s / 60:.1f} min training, validation R@1 "
                   + ", ".join(f"{k} {v['recall@1']:.2f}" for k, v in cities.items()))
        _write(result_path, cpu, points, skipped, time.perf_counter() - start)
    bar.close()
    _write(result_path, cpu, points, skipped, time.perf_counter() - start)
    _plot(points, args.out / "config_search.png", cpu)
    _print_table(points, skipped, cpu, time.perf_counter() - start)


def _write(path: Path, cpu: str, points: list[dict], skipped: list[str], wall_s: float) -> None:
    text = json.dumps({"cpu": cpu, "threads": 2, "wall_s": round(wall_s, 1), "points": points, "skipped": skipped},
                      indent=1)
    write_atomic(path, lambda tmp: tmp.write_text(text))


def _plot(points: list[dict], path: Path, cpu: str) -> None:
    fig, ax = one_panel()
    for name in dict.fromkeys(p["config"] for p in points):
        pts = sorted((p["train_s"] / 60, p["mean_recall@1"], p["epochs"]) for p in points if p["config"] == name)
        ax.plot([x for x, _, _ in pts], [y for _, y, _ in pts], "o-", label=name)
        for x, y, e in pts:
            ax.annotate(f"{e}", (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
    finish_figure(fig, ax, path, xlabel=f"training time, minutes ({cpu}, 2 threads)",
                  ylabel="Recall@1, mean of the 2 validation cities",
                  title="LCPR configurations (labels: epochs; online protocol, no verification)")


def _print_table(points: list[dict], skipped: list[str], cpu: str, wall_s: float) -> None:
    print(f"CPU: {cpu}, 2 threads; search wall time {wall_s / 60:.1f} min")
    print("| configuration | epochs | training min | " + " | ".join(f"{v} R@1 / max F1" for v in VALIDATION)
          + " | mean R@1 |")
    print("|---|---|---|" + "---|" * len(VALIDATION) + "---|")
    for p in points:
        print(f"| {p['config']} | {p['epochs']} | {p['train_s'] / 60:.1f} | {validation_cells(p)} "
              f"| {p['mean_recall@1']:.3f} |")
    if points:
        best = max(points, key=lambda p: (p["mean_recall@1"], p["mean_max_f1"]))
        print(f"best on validation: {best['config']}, epoch {best['epochs']} "
              f"(mean R@1 {best['mean_recall@1']:.3f}, mean max F1 {best['mean_max_f1']:.3f})")
    for s in skipped:
        print(f"skipped (budget): {s}")


if __name__ == "__main__":
    main()
