"""Which LCPR configuration generalises best for a CPU training budget (issue #14): a fixed plan.

    python benchmarks/lcpr_config_search.py [--corpus out/corpus] [--out out/config_search]
                                            [--budget-min 120]

Trains each configuration of :data:`PLAN` on the 12 training cities of ``benchmarks/lcpr_corpus.sh``
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
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from precision_cost import online  # noqa: E402

from lcpr_core.atomic import save_figure, write_atomic  # noqa: E402
from lcpr_core.timing import cpu_model  # noqa: E402
from msg_tools.progress import progress_bar  # noqa: E402

AUGMENT = ("--augment-yaw", "0.5", "--augment-lighting", "0.5", "--brightness", "0.3", "1.6",
           "--augment-camera-drop", "0.2")
VALIDATION = ("val_grid_s3", "val_k00_s45")


@dataclass(frozen=True)
class Config:
    name: str
    image: tuple[int, int]
    ranges: tuple[int, int]
    width: float
    lr: float
    step_epochs: int
    gamma: float

    def train_args(self) -> list[str]:
        return ["--image-size", *map(str, self.image), "--range-size", *map(str, self.ranges),
                "--width", str(self.width), "--lr", str(self.lr), "--step-epochs", str(self.step_epochs),
                "--gamma", str(self.gamma)]

    @property
    def cache_name(self) -> str:
        return f"cache_{self.image[0]}x{self.image[1]}_{self.ranges[0]}x{self.ranges[1]}"


CPU = Config("cpu preset (64x192, 16x288, w 0.25, lr 3e-4)", (64, 192), (16, 288), 0.25, 3e-4, 6, 0.8)
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


def run(cmd: list[str]) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")


def train_command(py: str, config: Config, train_bags: list[str], run_dir: Path, cache: Path, epochs: int, *,
                  queries_per_epoch: int, resume: bool, extra: Sequence[str] = ()) -> list[str]:
    """The ``lcpr_train`` command of one stage: ``config`` to ``epochs`` in all, the recipe's augmentations
    (and ``extra`` options)."""
    return [py, "-m", "lcpr_core.lcpr.training.cli", *train_bags, "--out", str(run_dir), "--cache", str(cache),
            "--epochs", str(epochs), "--queries-per-epoch", str(queries_per_epoch), "--batch", "4",
            "--fractions", "0.8", "0.1", "0.1", "--threads", "2", "--seed", "0", "--quiet", *config.train_args(),
            *AUGMENT, *extra, *(["--resume"] if resume else [])]


def training_seconds(run_dir: Path, epochs: int) -> float:
    """Training time ``lcpr_train`` recorded for epochs 1..``epochs`` of ``run_dir`` (steps and validation)."""
    history = json.loads((run_dir / "history.json").read_text())
    return float(sum(h.get("seconds", 0.0) for h in history if 0 < h["epoch"] <= epochs))


def in_training_recall(run_dir: Path, epoch: int) -> float | None:
    """Recall@1 on the validation queries of the training cities that ``lcpr_train`` recorded at ``epoch``."""
    history = json.loads((run_dir / "history.json").read_text())
    return next((h.get("recall@1") for h in history if h["epoch"] == epoch), None)


def export(py: str, source: Path, target: Path, *, fp32: bool) -> None:
    """``lcpr_train --export``: a copy of a checkpoint without optimizer state (float16 unless ``fp32``)."""
    run([py, "-m", "lcpr_core.lcpr.training.cli", "--export", str(source), str(target),
         *(["--export-fp32"] if fp32 else [])])


def slug(config: Config) -> str:
    return "".join(c if c.isalnum() else "_" for c in config.name)[:48].strip("_")


def made_after(path: Path, source: Path) -> bool:
    """Whether ``path`` exists and was written after ``source``: the benchmarks' rule for reusing a result
    (a report, an exported or post-processed weights file) instead of making it again."""
    return path.is_file() and path.stat().st_mtime > source.stat().st_mtime


def reusable_report(report: Path, weights: Path, *, key: tuple[str, ...] = ("settings", "model", "weights")) -> bool:
    """Whether a JSON report can stand for running ``weights`` again: written after them and made with that
    same file, whose path the report holds under ``key`` (an ``lcpr_eval`` report's by default); a report
    another weights file left in the same folder is not."""
    if not made_after(report, weights):
        return False
    made_with = json.loads(report.read_text())
    for part in key:
        made_with = made_with[part]
    return Path(made_with).resolve() == weights.resolve()


def evaluate(py: str, bag: Path, weights: Path, out: Path, *, reuse: bool = False) -> dict[str, float]:
    """Online Recall@1 and max F1 of ``weights`` on ``bag`` (retrieval only); with ``reuse``, a report in
    ``out`` made with them (:func:`reusable_report`) is read back instead of evaluating again."""
    report = out / "report.json"
    if not (reuse and reusable_report(report, weights)):
        run([py, "-m", "lcpr_ros.evaluate", str(bag), "--weights", str(weights), "--threads", "2", "--quiet",
             "--no-verify", "--no-scan-context", "--out", str(out)])
    recall_at_1, max_f1 = online(report)
    return {"recall@1": recall_at_1, "max_f1": max_f1}


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
                         f"(missing {missing}); run benchmarks/lcpr_corpus.sh first")
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
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for name in dict.fromkeys(p["config"] for p in points):
        pts = sorted((p["train_s"] / 60, p["mean_recall@1"], p["epochs"]) for p in points if p["config"] == name)
        ax.plot([x for x, _, _ in pts], [y for _, y, _ in pts], "o-", label=name)
        for x, y, e in pts:
            ax.annotate(f"{e}", (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
    finish_figure(fig, ax, path, xlabel=f"training time, minutes ({cpu}, 2 threads)",
                  ylabel="Recall@1, mean of the 2 validation cities",
                  title="LCPR configurations (labels: epochs; online protocol, no verification)")


def finish_figure(fig: Figure, ax: Axes, path: Path, *, xlabel: str, ylabel: str, title: str) -> None:
    """Label, grid and legend one panel, write the PNG atomically and close the figure."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def validation_cells(point: dict) -> str:
    """A point's ``R@1 / max F1`` per validation city, as table cells."""
    return " | ".join(f"{point['cities'][v]['recall@1']:.2f} / {point['cities'][v]['max_f1']:.3f}"
                      for v in VALIDATION)


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
