"""LCPR weights for LiDAR-only robots: the bundled network fine-tuned with every camera slot empty.

    python benchmarks/recipes/lcpr_lidar_only.py [--corpus out/corpus] [--weights weights/lcpr_synth_narrow.pth]
                                                 [--out out/lidar_only] [--seeds [SEED ...]] [--stages 10 20]
                                                 [--real FOLDER ...]

Why: ``lcpr_node``'s ``lidar_only`` describes every cloud with the six camera slots empty, a condition the
bundled weights met only as an augmentation (one camera dropped at a time). The plan and the rules, fixed
before any validation city was scored with the new weights:

1. ``lcpr_train --init WEIGHTS --lidar-only`` on the corpus's 12 training cities (``--seeds 47 49 51 53`` adds
   the four KITTI-00-route cities the bundled file's fine-tuning added, rendered as ``lcpr_finetune.py``
   renders them), every camera slot empty in training, mining and validation, the bundled recipe's options
   and its learning-rate schedule where it stood after fine-tuning (3e-4 x 0.8^10, x0.8 every 6 epochs), and
   two augmentations for real sensors
   (``--augment-lidar-fov 0.3``: beams spanning less than the range image's geometry;
   ``--augment-lidar-sparse 0.3``: half the beams, or 10-50 % of the returns lost), to each of ``--stages``.
2. Each stage gets the bundled file's post-processing, fixed, not searched: whitening (power 0.5, 128
   directions) fitted on the training cities' LiDAR-only frames, and turn averaging on.
3. Every stage and the bundled file are scored on the two validation cities with ``lcpr_eval --lidar-only
   --no-verify`` (online protocol). Stage rule: the best mean validation max F1 (Recall@1 breaking ties).
4. Adoption rule (:func:`lcpr_core.lcpr.training.recipe_rules.adopt_lidar_only`): the chosen stage becomes the
   LiDAR-only default only if its mean validation max F1 is at least 1 point above the bundled file's in
   LiDAR-only mode and its mean validation Recall@1 at most 1 point below.
5. Only after the decision is written to ``lidar_only.json``: the three test cities, LiDAR-only, for both
   files, and every ``--real`` scan folder (default: the two Livox sequences in ``../shared/data``) converted
   with ``msg_tools_scans2bag`` and evaluated the same way beside Scan Context. Nothing is chosen on them.
6. If adopted: the result exported in float16 to ``OUT/lcpr_synth_lidar.pth`` (the file to copy to
   ``weights/``) with its max-F1 threshold on validation grid seed 3 as its operating threshold.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lcpr_common.progress import progress_bar
from lcpr_core.atomic import save_torch, write_atomic
from lcpr_core.evaluation.eval_report import online_methods
from lcpr_core.lcpr.checkpoint import read_released
from lcpr_core.lcpr.training.recipe_rules import (
    LIDAR_ONLY_MAX_RECALL_DROP,
    LIDAR_ONLY_MIN_F1_GAIN,
    adopt_lidar_only,
    made_after,
    reusable_report,
)
from lcpr_core.pretrained import with_operating_threshold
from lcpr_core.timing import cpu_model
from lcpr_offline.lcpr_recipe import (
    TEST,
    THRESHOLD_CITY,
    VALIDATION,
    Config,
    check_stages,
    export,
    extend_corpus,
    lcpr_figures,
    mean_point,
    require_corpus,
    run,
    train_command,
    trained_epochs,
)

#: The bundled file's schedule where its fine-tuning left it (Adam 3e-4 x 0.8^10, x0.8 every 6 epochs).
SCHEDULE = Config("cpu preset from the bundled network, LiDAR only", (64, 192), (16, 288), 0.25, 3e-4 * 0.8**10, 6,
                  0.8)
#: The augmentations for real sensors (lcpr_train options), on top of the recipe's own.
SENSOR_AUGMENT = ("--augment-lidar-fov", "0.3", "--augment-lidar-sparse", "0.3")
#: The real scan folders evaluated by default (read in place, never trained or tuned on).
REAL = ("../shared/data/livox_hku/walk_loop", "../shared/data/livox_hku/campus")


def evaluate(bag: Path, weights: Path, out: Path, *, scans: bool = False) -> dict[str, dict]:
    """Per method the online figures of ``lcpr_eval --lidar-only --no-verify`` (Scan Context beside it on
    real scans), reusing a report already made with ``weights``."""
    report = out / "report.json"
    if not reusable_report(report, weights):
        run([sys.executable, "-m", "lcpr_ros.evaluate", str(bag), "--weights", str(weights), "--threads", "2",
             "--quiet", "--no-verify", *(["--topics", "scans"] if scans else ["--lidar-only", "--no-scan-context"]),
             "--out", str(out)])
    return online_methods(report)


def postprocess(stage: Path, train_bags: list[str], cache: Path, out: Path) -> Path:
    """The bundled file's post-processing on a stage: whitening (its defaults) fitted on the training cities'
    LiDAR-only frames, then turn averaging on."""
    whitened, turned = out / "whitened.pth", out / "lcpr_lidar.pth"
    if not made_after(whitened, stage):
        run([sys.executable, "-m", "lcpr_offline.lcpr_train", *train_bags, "--cache", str(cache), "--quiet",
             "--whiten", str(stage), str(whitened)])
    if not made_after(turned, whitened):
        run([sys.executable, "-m", "lcpr_offline.lcpr_train", "--turn-average", "on", str(whitened), str(turned)])
    return turned


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--corpus", type=Path, default=Path("out/corpus"))
    p.add_argument("--weights", type=Path, default=Path("weights/lcpr_synth_narrow.pth"))
    p.add_argument("--out", type=Path, default=Path("out/lidar_only"))
    p.add_argument("--seeds", type=int, nargs="*", default=[],
                   help="KITTI-00-route training cities added to the corpus's 12 (the bundled file's fine-tuning "
                        "added 47 49 51 53; default none)")
    p.add_argument("--stages", type=int, nargs="+", default=[10, 20], help="epochs of fine-tuning, rising")
    p.add_argument("--queries-per-epoch", type=int, default=256)
    p.add_argument("--real", nargs="*", type=Path, default=[Path(f) for f in REAL],
                   help="real scan folders (msg_tools_scans2bag layout) evaluated after the decision")
    args = p.parse_args()
    check_stages(args.stages)
    require_corpus(args.corpus)
    train_bags = extend_corpus(args.corpus, args.out / "corpus", args.seeds)
    run_dir, cache = args.out / "run", args.out / "run" / "cache"
    py = sys.executable

    bundled = mean_point(lcpr_figures({n: evaluate(args.corpus / f"{n}.bag", args.weights, args.out / f"bundled_{n}")
                                       for n in VALIDATION}))
    points: list[dict] = []
    bar = progress_bar(len(args.stages), desc="LiDAR-only fine-tuning", unit="stage")
    for epochs in args.stages:
        trained = trained_epochs(run_dir)
        stage = args.out / f"stage_e{epochs}.pth"
        if trained < epochs:
            extra = ["--init", str(args.weights), "--lidar-only", *SENSOR_AUGMENT]
            run(train_command(py, SCHEDULE, train_bags, run_dir, cache, epochs, resume=trained > 0, extra=extra,
                              queries_per_epoch=args.queries_per_epoch))
            trained = epochs
        if not stage.is_file():
            if trained != epochs:
                raise SystemExit(f"{run_dir} is at epoch {trained}, past stage {epochs}, and {stage} is missing")
            export(py, run_dir / "last.pth", stage, fp32=True)
        weights = postprocess(stage, train_bags, cache, args.out / f"e{epochs}")
        cities = {n: evaluate(args.corpus / f"{n}.bag", weights, args.out / f"e{epochs}_{n}") for n in VALIDATION}
        points.append({"epochs": epochs, "weights": str(weights), **mean_point(lcpr_figures(cities))})
        bar.update(1)
        bar.write(f"stage {epochs}: validation R@1 / max F1 " + ", ".join(
            f"{k} {v['recall@1']:.3f} / {v['max_f1']:.3f}" for k, v in points[-1]["cities"].items()))
    bar.close()

    chosen = max(points, key=lambda pt: (pt["mean_max_f1"], pt["mean_recall@1"]))
    decision: dict = {"cpu": cpu_model(), "training_bags": len(train_bags), "bundled_validation": bundled,
                      "points": points, "chosen_epochs": chosen["epochs"], "adopted": adopt_lidar_only(chosen, bundled)}
    record = args.out / "lidar_only.json"
    write_atomic(record, lambda tmp: tmp.write_text(json.dumps(decision, indent=1)))
    _print_validation(decision)

    # Only now, with the decision on disk: the test cities and the real sequences, for both files.
    result = Path(chosen["weights"])
    held_out: dict[str, dict] = {}
    for name in TEST:
        held_out[name] = {label: evaluate(args.corpus / f"{name}.bag", w, args.out / f"{label}_{name}")
                          for label, w in (("bundled", args.weights), ("lidar", result))}
    for folder in args.real:
        bag = args.out / "real" / f"{folder.name}.bag"
        if not bag.is_dir():
            run([py, "-m", "msg_tools.convert.scans2bag", str(folder), "--out", str(bag)])
        held_out[folder.name] = {label: evaluate(bag, w, args.out / f"{label}_real_{folder.name}", scans=True)
                                 for label, w in (("bundled", args.weights), ("lidar", result))}
    decision["held_out"] = held_out
    write_atomic(record, lambda tmp: tmp.write_text(json.dumps(decision, indent=1)))
    _print_held_out(held_out)

    if decision["adopted"]:
        shipped = args.out / "lcpr_synth_lidar.pth"
        if not made_after(shipped, result):
            half = args.out / "lcpr_synth_lidar_fp16.pth"
            export(py, result, half, fp32=False)
            threshold = chosen["cities"][THRESHOLD_CITY]["max_f1_threshold"]
            entry = with_operating_threshold(read_released(half), max_distance=round(float(threshold), 2), chosen_on=(
                f"max-F1 distance ({threshold:.3f}) on the validation city grid seed 3, LiDAR only (online "
                "protocol, whitened and turn-averaged descriptors)"))
            save_torch(entry, shipped, shared=True)
        print(f"adopted; shipped in float16: {shipped} ({shipped.stat().st_size / 1e6:.2f} MB)")


def _print_validation(decision: dict) -> None:
    print(f"CPU: {decision['cpu']}; {decision['training_bags']} training cities")
    print("| LiDAR-only weights | " + " | ".join(f"{v} R@1 / max F1" for v in VALIDATION) + " | mean R@1 / max F1 |")
    print("|---|" + "---|" * len(VALIDATION) + "---|")
    for label, pt in [("bundled (cameras empty)", decision["bundled_validation"]),
                      *((f"{pt['epochs']} epochs LiDAR-only", pt) for pt in decision["points"])]:
        cells = " | ".join(f"{c['recall@1']:.3f} / {c['max_f1']:.3f}" for c in pt["cities"].values())
        print(f"| {label} | {cells} | {pt['mean_recall@1']:.3f} / {pt['mean_max_f1']:.3f} |")
    print(f"chosen on validation: {decision['chosen_epochs']} epochs; adopted by the rule (max F1 "
          f"+{LIDAR_ONLY_MIN_F1_GAIN}, Recall@1 -{LIDAR_ONLY_MAX_RECALL_DROP} at most): {decision['adopted']}")


def _print_held_out(held_out: dict[str, dict]) -> None:
    print("| held out (LiDAR only, online protocol) | bundled R@1 / max F1 | LiDAR-only weights R@1 / max F1 | "
          "Scan Context R@1 / max F1 |")
    print("|---|---|---|---|")
    for name, by in held_out.items():
        cells = [next(iter(by[label].values())) for label in ("bundled", "lidar")]
        sc = [m for k, m in by["bundled"].items() if "scan" in k.lower()]
        row = [f"{c['recall@1']:.3f} / {c['max_f1']:.3f}" for c in cells + sc[:1]]
        print(f"| {name} | " + " | ".join(row + ["-"] * (3 - len(row))) + " |")


if __name__ == "__main__":
    main()
