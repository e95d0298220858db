"""The bundled LCPR weights (issue #14): continue the search's winner, choose on validation, then test once.

    python benchmarks/recipes/lcpr_bundle.py [--corpus out/corpus] [--search out/config_search] [--out out/bundle]
                                             [--stages 40 50 60] [--target out/bundle/lcpr_synth_narrow.pth]

1. Copies the configuration search's run of the ``cpu`` preset (``lcpr_config_search.py``,
   its 30 epochs) to ``OUT/run`` unless that exists, and continues it with the same options
   (``lcpr_train --resume``) to each epoch of ``--stages``, keeping a float32 copy of each stage.
2. Scores each stage on the two *validation* cities exactly as the search scores its points (online
   protocol, retrieval only) and takes the search's 30-epoch point from its ``search.json``.
3. Chooses the epoch with the best mean validation Recall@1 (mean max F1 breaks ties) and exports it
   in float16 to ``--target`` (copy it to ``weights/lcpr_synth_narrow.pth`` to bundle it).
4. Evaluates the float16 weights beside Scan Context (``lcpr_eval --no-verify``) on the validation
   cities: the max-F1 threshold of grid seed 3 is the operating threshold
   (``lcpr_core.pretrained.BUNDLED_MAX_DISTANCE``); then, after everything is chosen, on the three
   test cities. Writes ``bundle.json`` and ``bundle.png`` (validation Recall@1 against epochs) and
   prints the README's table. Stages already trained and scored are reused (the test cities are
   evaluated again on every run).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from lcpr_common.progress import progress_bar
from lcpr_core.atomic import write_atomic
from lcpr_core.timing import cpu_model
from lcpr_offline.lcpr_recipe import (
    CPU,
    TEST,
    THRESHOLD_CITY,
    VALIDATION,
    evaluate,
    export,
    final_evaluation,
    finish_figure,
    in_training_recall,
    one_panel,
    print_final,
    run,
    slug,
    train_command,
    training_seconds,
    validation_cells,
)


def _search_points(search: Path) -> list[dict]:
    path = search / "search.json"
    if not path.is_file():
        raise SystemExit(f"{path} does not exist: run benchmarks/recipes/lcpr_config_search.py first")
    return [p for p in json.loads(path.read_text())["points"] if p["config"] == CPU.name]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--corpus", type=Path, default=Path("out/corpus"))
    p.add_argument("--search", type=Path, default=Path("out/config_search"))
    p.add_argument("--out", type=Path, default=Path("out/bundle"))
    p.add_argument("--stages", type=int, nargs="+", default=[40, 50, 60], help="epochs to continue to, in order")
    p.add_argument("--queries-per-epoch", type=int, default=256)
    p.add_argument("--target", type=Path, default=None, help="float16 export (default OUT/lcpr_synth_narrow.pth)")
    args = p.parse_args()
    py = sys.executable
    searched = _search_points(args.search)
    if not searched:
        raise SystemExit(f"{args.search}/search.json has no point of {CPU.name!r}")
    start_epoch = max(pt["epochs"] for pt in searched)
    if sorted(args.stages) != args.stages or args.stages[0] <= start_epoch:
        raise SystemExit(f"--stages {args.stages}: must rise and start after the search's last epoch {start_epoch}")
    train_bags = sorted(str(b) for b in args.corpus.glob("train_*.bag"))
    missing = [n for n in (*VALIDATION, *TEST) if not (args.corpus / f"{n}.bag").is_dir()]
    if len(train_bags) < 12 or missing:
        raise SystemExit(f"{args.corpus}: needs 12 train_*.bag (found {len(train_bags)}) and the validation and "
                         f"test cities (missing {missing}); run benchmarks/recipes/lcpr_corpus.sh first")
    run_dir = args.out / "run"
    if not (run_dir / "last.pth").is_file():
        shutil.copytree(args.search / slug(CPU), run_dir, dirs_exist_ok=True)
    trained = json.loads((run_dir / "history.json").read_text())[-1]["epoch"]

    points = [{"epochs": pt["epochs"], "train_s": pt["train_s"], "cities": pt["cities"],
               "mean_recall@1": pt["mean_recall@1"], "mean_max_f1": pt["mean_max_f1"], "source": "search"}
              for pt in searched]
    bar = progress_bar(len(args.stages), desc="bundle", unit="stage")
    for epochs in args.stages:
        bar.update(1)
        weights = args.out / f"stage_e{epochs}.pth"
        if trained < epochs:
            run(train_command(py, CPU, train_bags, run_dir, args.search / CPU.cache_name, epochs,
                              queries_per_epoch=args.queries_per_epoch, resume=True))
            trained = epochs
        if not weights.is_file():
            if trained != epochs:
                raise SystemExit(f"{run_dir} is at epoch {trained}, past stage {epochs}, and {weights} is missing")
            export(py, run_dir / "last.pth", weights, fp32=True)
        cities = {name: evaluate(py, args.corpus / f"{name}.bag", weights, args.out / f"eval_e{epochs}_{name}",
                                 reuse=True) for name in VALIDATION}
        points.append({"epochs": epochs, "train_s": round(training_seconds(run_dir, epochs), 1), "cities": cities,
                       "mean_recall@1": sum(c["recall@1"] for c in cities.values()) / len(cities),
                       "mean_max_f1": sum(c["max_f1"] for c in cities.values()) / len(cities),
                       "in_training_val_recall@1": in_training_recall(run_dir, epochs), "source": "bundle"})
        bar.write(f"epoch {epochs}: validation R@1 " + ", ".join(f"{k} {v['recall@1']:.2f}" for k, v in cities.items()))
    bar.close()

    chosen = max((pt for pt in points if pt["epochs"] >= start_epoch),
                 key=lambda pt: (pt["mean_recall@1"], pt["mean_max_f1"]))
    source = (args.search / f"{slug(CPU)}_e{chosen['epochs']}.pth" if chosen["source"] == "search"
              else args.out / f"stage_e{chosen['epochs']}.pth")
    target = args.target or args.out / "lcpr_synth_narrow.pth"
    export(py, source, target, fp32=False)
    final, lcpr, threshold = final_evaluation(py, args.corpus, target, args.out)
    cpu = cpu_model()
    text = json.dumps({"cpu": cpu, "points": points, "chosen_epoch": chosen["epochs"], "weights": str(target),
                       "max_distance": threshold, "final": final}, indent=1)
    write_atomic(args.out / "bundle.json", lambda tmp: tmp.write_text(text))
    _plot(points, chosen["epochs"], start_epoch, args.out / "bundle.png", cpu)
    _print(points, chosen, final, lcpr, threshold, cpu)


def _plot(points: list[dict], chosen: int, start_epoch: int, path: Path, cpu: str) -> None:
    fig, ax = one_panel()
    pts = sorted(points, key=lambda pt: pt["epochs"])
    epochs = [pt["epochs"] for pt in pts]
    for i, name in enumerate(VALIDATION):
        ax.plot(epochs, [pt["cities"][name]["recall@1"] for pt in pts], "o-", color=f"C{i}", label=f"{name} Recall@1")
        ax.plot(epochs, [pt["cities"][name]["max_f1"] for pt in pts], "s--", color=f"C{i}", alpha=0.6,
                label=f"{name} max F1")
    ax.plot(epochs, [pt["mean_recall@1"] for pt in pts], "k^-", label="mean Recall@1")
    ax.axvline(start_epoch + 0.5, color="grey", lw=0.8, ls=":")
    ax.axvline(chosen, color="green", lw=1.0, label=f"chosen: epoch {chosen}")
    finish_figure(fig, ax, path, xlabel=f"epochs (cpu preset; left of the dotted line: the search; {cpu}, 2 threads)",
                  ylabel="validation cities, online protocol",
                  title="LCPR bundled weights: validation Recall@1 and max F1 against epochs")


def _print(points: list[dict], chosen: dict, final: dict[str, dict], lcpr: str, threshold: float | None,
           cpu: str) -> None:
    print(f"CPU: {cpu}, 2 threads")
    print("| epochs | training min | " + " | ".join(f"{v} R@1 / max F1" for v in VALIDATION) + " | mean R@1 |")
    print("|---|---|" + "---|" * len(VALIDATION) + "---|")
    for pt in sorted(points, key=lambda pt: pt["epochs"]):
        print(f"| {pt['epochs']} | {pt['train_s'] / 60:.1f} | {validation_cells(pt)} | {pt['mean_recall@1']:.3f} |")
    print(f"chosen on validation: epoch {chosen['epochs']}; max-F1 threshold on {THRESHOLD_CITY}: {threshold}")
    print_final(final, lcpr)


if __name__ == "__main__":
    main()
