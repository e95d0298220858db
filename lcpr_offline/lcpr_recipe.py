"""The steps the recipes of the bundled LCPR weights share (benchmarks/recipes/, benchmarks/studies/).

The corpus's cities (``benchmarks/recipes/lcpr_corpus.sh``), the training configuration and its
augmentations, the ``lcpr_train`` / ``lcpr_eval`` commands each stage runs in a subprocess, the
final evaluation (validation cities, then test cities) and the tables and figures the recipes print.
The rules they decide by are in :mod:`lcpr_core.lcpr.training.recipe_rules`, the scores of descriptor
variants in :mod:`lcpr_core.lcpr.training.recipe_scores`.
"""
from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from lcpr_core.atomic import save_figure
from lcpr_core.evaluation.eval_report import online, online_methods
from lcpr_core.lcpr.training.recipe_rules import reusable_report
from lcpr_core.lcpr.training.recipe_scores import GATES

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: The recipe's augmentations (``lcpr_train`` options): yaw, lighting, brightness range, camera drop.
AUGMENT = ("--augment-yaw", "0.5", "--augment-lighting", "0.5", "--brightness", "0.3", "1.6",
           "--augment-camera-drop", "0.2")
#: The validation cities of the corpus: every choice is made on them.
VALIDATION = ("val_grid_s3", "val_k00_s45")
#: The test cities: read only after every choice is made.
TEST = ("test_grid_s7", "test_grid_s9", "test_k00_s21")
#: The validation city whose max-F1 threshold is the operating threshold (``BUNDLED_MAX_DISTANCE``).
THRESHOLD_CITY = "val_grid_s3"


@dataclass(frozen=True)
class Config:
    """One training configuration: input sizes, network width and learning-rate schedule."""

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


#: The configuration the search chose and the bundled weights were trained with.
CPU = Config("cpu preset (64x192, 16x288, w 0.25, lr 3e-4)", (64, 192), (16, 288), 0.25, 3e-4, 6, 0.8)


def require_corpus(corpus: Path) -> None:
    """Exit naming the validation and test cities ``corpus`` lacks, if any (``lcpr_corpus.sh`` makes them)."""
    missing = [n for n in (*VALIDATION, *TEST) if not (corpus / f"{n}.bag").is_dir()]
    if missing:
        raise SystemExit(f"{corpus}: missing {missing}; run benchmarks/recipes/lcpr_corpus.sh first")


def check_stages(stages: list[int]) -> None:
    """Exit unless fine-tuning ``stages`` (epochs) rise and start at 1 or more."""
    if sorted(set(stages)) != stages or stages[0] < 1:
        raise SystemExit(f"--stages {stages}: must rise and start at 1 or more")


def trained_epochs(run_dir: Path) -> int:
    """The last epoch ``lcpr_train`` recorded in ``run_dir`` (0 before its first run)."""
    history = run_dir / "history.json"
    return int(json.loads(history.read_text())[-1]["epoch"]) if history.is_file() else 0


def mean_point(cities: dict[str, dict]) -> dict:
    """A rule's point (:mod:`lcpr_core.lcpr.training.recipe_rules`): per-city figures and their means."""
    return {"cities": cities, "mean_recall@1": sum(c["recall@1"] for c in cities.values()) / len(cities),
            "mean_max_f1": sum(c["max_f1"] for c in cities.values()) / len(cities)}


def lcpr_figures(final: dict[str, dict]) -> dict[str, dict]:
    """Per city the LCPR method's (the first method's) online figures of an evaluation by method."""
    return {city: next(iter(methods.values())) for city, methods in final.items()}


def run(cmd: list[str]) -> None:
    """Run a command; on failure exit naming it, with the tail of its output."""
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")


def train_command(py: str, config: Config, train_bags: list[str], run_dir: Path, cache: Path, epochs: int, *,
                  queries_per_epoch: int, resume: bool, extra: Sequence[str] = ()) -> list[str]:
    """The ``lcpr_train`` command of one stage: ``config`` to ``epochs`` in all, the recipe's augmentations
    (and ``extra`` options)."""
    return [py, "-m", "lcpr_offline.lcpr_train", *train_bags, "--out", str(run_dir), "--cache", str(cache),
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
    run([py, "-m", "lcpr_offline.lcpr_train", "--export", str(source), str(target),
         *(["--export-fp32"] if fp32 else [])])


def slug(config: Config) -> str:
    """A folder name for a configuration's run."""
    return "".join(c if c.isalnum() else "_" for c in config.name)[:48].strip("_")


def evaluate(py: str, bag: Path, weights: Path, out: Path, *, reuse: bool = False) -> dict[str, float]:
    """Online Recall@1 and max F1 of ``weights`` on ``bag`` (retrieval only); with ``reuse``, a report in
    ``out`` made with them (:func:`~lcpr_core.lcpr.training.recipe_rules.reusable_report`) is read back
    instead of evaluating again."""
    report = out / "report.json"
    if not (reuse and reusable_report(report, weights)):
        run([py, "-m", "lcpr_ros.evaluate", str(bag), "--weights", str(weights), "--threads", "2", "--quiet",
             "--no-verify", "--no-scan-context", "--out", str(out)])
    recall_at_1, max_f1 = online(report)
    return {"recall@1": recall_at_1, "max_f1": max_f1}


def final_evaluation(py: str, corpus: Path, weights: Path, out: Path, *, test: bool = True,
                     reuse: bool = False) -> tuple[dict[str, dict], str, float | None]:
    """``lcpr_eval --no-verify`` of the chosen weights beside Scan Context on the validation cities and, only
    then (unless not ``test``), the test cities (into ``OUT/final_CITY``): per city and method the online
    figures, the LCPR method's name and its max-F1 threshold on :data:`THRESHOLD_CITY` (the operating
    threshold). With ``reuse``, a report made with the weights is read back instead of evaluating again."""
    final: dict[str, dict] = {}
    for name in (*VALIDATION, *(TEST if test else ())):  # the test cities only now, after every choice
        folder = out / f"final_{name}"
        report = folder / "report.json"
        if not (reuse and reusable_report(report, weights)):
            run([py, "-m", "lcpr_ros.evaluate", str(corpus / f"{name}.bag"), "--weights", str(weights),
                 "--threads", "2", "--quiet", "--no-verify", "--out", str(folder)])
        final[name] = online_methods(report)
    lcpr = next(iter(final[THRESHOLD_CITY]))
    return final, lcpr, final[THRESHOLD_CITY][lcpr]["max_f1_threshold"]


def extend_corpus(corpus: Path, out: Path, seeds: list[int], *, frames: int = 300) -> list[str]:
    """``out`` with links to every bag of ``corpus`` and a KITTI-00-route training city rendered per seed
    (``frames`` keyframes; every second one with twice the night share and camera drops, as
    ``lcpr_corpus.sh`` does for its pair); the training bags, sorted. A seed the corpus already has is refused."""
    out.mkdir(parents=True, exist_ok=True)
    for bag in sorted(corpus.glob("*.bag")):
        link = out / bag.name
        if not link.exists():
            link.symlink_to(bag.resolve(), target_is_directory=True)
    for i, seed in enumerate(seeds):
        bag = out / f"train_k00_s{seed}.bag"
        if (corpus / bag.name).exists():
            raise SystemExit(f"--seeds: {seed} is already a city of {corpus}")
        if bag.exists():
            continue
        extra = ["--night-fraction", "0.5", "--camera-drop", "0.05"] if i % 2 else []
        run([sys.executable, "-m", "citysim.cli", "--route", "kitti00", "--seed", str(seed), "--frames", str(frames),
             "--image-size", "400x225", "--workers", "2", "--no-progress", "--out", str(bag), *extra])
    return sorted(str(b) for b in out.glob("train_*.bag"))


def print_final(final: dict[str, dict], lcpr: str) -> None:
    """The table of :func:`final_evaluation`: online Recall@1 / max F1 per city and method."""
    others = [name for name in next(iter(final.values())) if name != lcpr]
    print(f"| city (online protocol) | {lcpr} Recall@1 / max F1 | " + " | ".join(others) + " |")
    print("|---|---|" + "---|" * len(others))
    for city, methods in final.items():
        cells = " | ".join(f"{methods[m]['recall@1']:.2f} / {methods[m]['max_f1']:.3f}" for m in [lcpr, *others])
        print(f"| {city} | {cells} |")


def print_gates(gates: dict[str, dict]) -> None:
    """The table of :func:`~.recipe_scores.gate_counts` per validation city and descriptor variant."""
    print("| validation city, descriptors | " + " | ".join(
        f"gate {g:g}: loops closable / no-revisit keyframes verified" for g in GATES) + " |")
    print("|---|" + "---|" * len(GATES))
    for city, by in gates.items():
        for label, counts in by.items():
            cells = " | ".join(f"{c['correct_under']} of {c['correct_in_top10']} / {c['no_revisit_under']} of "
                               f"{c['no_revisit']}" for c in counts.values())
            print(f"| {city}, {label} | {cells} |")


def validation_cells(point: dict) -> str:
    """A point's ``R@1 / max F1`` per validation city, as table cells."""
    return " | ".join(f"{point['cities'][v]['recall@1']:.2f} / {point['cities'][v]['max_f1']:.3f}"
                      for v in VALIDATION)


def one_panel(figsize: tuple[float, float] = (7.5, 4.5)) -> tuple[Figure, Axes]:
    """A figure of one panel, made without pyplot (no backend, nothing to close)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    return fig, fig.add_subplot()


def finish_figure(fig: Figure, ax: Axes, path: Path, *, xlabel: str, ylabel: str, title: str) -> None:
    """Label, grid and legend one panel and write the PNG atomically."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    save_figure(fig, path, dpi=120)
