"""The rules the LCPR weights recipes decide by (benchmarks/recipes/, benchmarks/studies/).

Each rule was fixed before the run it decides, and reads validation cities only: a point is
``{"mean_recall@1": float, "mean_max_f1": float, ...}``, the mean over the validation cities of the
online protocol's figures. Kept here, apart from the scripts that run the pipelines, so the tests
check the very rules the scripts apply. Also the rule by which a recipe reuses a result it made
before instead of making it again.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

#: Mean validation max F1 the fine-tuned weights must add to the bundled weights' to replace them.
FINETUNE_MIN_F1_GAIN = 0.01
#: Mean validation Recall@1 the fine-tuned weights may lose against the bundled weights'.
FINETUNE_MAX_RECALL_DROP = 0.01
#: How the fine-tuning recipe chooses a stage on the validation cities: the sort key of a point.
#: ``recall`` is the bundle's rule; ``max_f1`` the issue's target metric (Recall@1 breaking ties).
STAGE_RULES: dict[str, Callable[[dict], tuple[float, float]]] = {
    "recall": lambda pt: (pt["mean_recall@1"], pt["mean_max_f1"]),
    "max_f1": lambda pt: (pt["mean_max_f1"], pt["mean_recall@1"]),
}
#: Mean validation max F1 turn averaging must add to single-pass descriptors to be adopted.
TURN_AVERAGE_MIN_F1_GAIN = 0.01
#: Mean validation Recall@1 turn averaging may lose.
TURN_AVERAGE_MAX_RECALL_DROP = 0.01
#: Mean validation Recall@1 a whitening variant may lose against the unwhitened descriptors.
WHITENING_MAX_RECALL_DROP = 0.01
#: Mean clean validation Recall@1 weights trained with LiDAR occlusion may lose against the bundled ones.
OCCLUSION_MAX_CLEAN_LOSS = 0.01
#: Mean LiDAR-only validation max F1 LiDAR-only weights must add to the bundled weights' (cameras empty).
LIDAR_ONLY_MIN_F1_GAIN = 0.01
#: Mean LiDAR-only validation Recall@1 they may lose against the bundled weights'.
LIDAR_ONLY_MAX_RECALL_DROP = 0.01


def gains_without_loss(new: dict, old: dict, *, min_f1_gain: float, max_recall_drop: float) -> bool:
    """Whether ``new`` adds at least ``min_f1_gain`` of mean validation max F1 to ``old`` while losing at most
    ``max_recall_drop`` of its mean validation Recall@1: the form of the adoption rules below."""
    return (new["mean_max_f1"] >= old["mean_max_f1"] + min_f1_gain
            and new["mean_recall@1"] >= old["mean_recall@1"] - max_recall_drop)


def adopt_finetuned(result: dict, bundled: dict) -> bool:
    """Whether fine-tuned weights replace the bundled ones: mean validation max F1 at least
    FINETUNE_MIN_F1_GAIN above theirs, mean validation Recall@1 at most FINETUNE_MAX_RECALL_DROP below."""
    return gains_without_loss(result, bundled, min_f1_gain=FINETUNE_MIN_F1_GAIN,
                              max_recall_drop=FINETUNE_MAX_RECALL_DROP)


def adopt_lidar_only(result: dict, bundled: dict) -> bool:
    """Whether weights trained LiDAR-only become the LiDAR-only default: both points scored with every camera
    slot empty; mean validation max F1 at least LIDAR_ONLY_MIN_F1_GAIN above the bundled weights', mean
    validation Recall@1 at most LIDAR_ONLY_MAX_RECALL_DROP below."""
    return gains_without_loss(result, bundled, min_f1_gain=LIDAR_ONLY_MIN_F1_GAIN,
                              max_recall_drop=LIDAR_ONLY_MAX_RECALL_DROP)


def adopt_turn_average(scores: dict[str, dict]) -> bool:
    """Whether turn averaging is adopted: ``scores["turn average"]``'s mean validation max F1 at least
    TURN_AVERAGE_MIN_F1_GAIN above ``scores["single"]``'s, its mean Recall@1 at most
    TURN_AVERAGE_MAX_RECALL_DROP below."""
    return gains_without_loss(scores["turn average"], scores["single"], min_f1_gain=TURN_AVERAGE_MIN_F1_GAIN,
                              max_recall_drop=TURN_AVERAGE_MAX_RECALL_DROP)


def choose_whitening(variants: dict[str, dict]) -> str:
    """The whitening variant to adopt: among those whose mean validation Recall@1 is at most
    WHITENING_MAX_RECALL_DROP below the unwhitened descriptors' (``variants["none"]``), the best mean
    validation max F1; ``"none"`` unless it beats the unwhitened one."""
    base = variants["none"]
    allowed = {name: v for name, v in variants.items()
               if name == "none" or v["mean_recall@1"] >= base["mean_recall@1"] - WHITENING_MAX_RECALL_DROP}
    best = max(allowed, key=lambda name: allowed[name]["mean_max_f1"])
    return best if allowed[best]["mean_max_f1"] > base["mean_max_f1"] else "none"


def lidar_occlusion_replaces(bundled: dict, new: dict) -> bool:
    """Whether weights trained with LiDAR occlusion replace the bundled ones: at most
    OCCLUSION_MAX_CLEAN_LOSS of mean clean validation Recall@1 lost, and a higher mean Recall@1 with a
    quarter of the range image gone (``mean_lidar_quarter_recall@1``)."""
    return (new["mean_recall@1"] >= bundled["mean_recall@1"] - OCCLUSION_MAX_CLEAN_LOSS
            and new["mean_lidar_quarter_recall@1"] > bundled["mean_lidar_quarter_recall@1"])


def made_after(path: Path, source: Path) -> bool:
    """Whether ``path`` exists and was written after ``source``: the recipes' rule for reusing a result
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
