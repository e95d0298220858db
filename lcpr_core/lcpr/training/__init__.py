"""Training LCPR with the paper's recipe: cached inputs, database/query split, hard mining, triplet loss.

Modules: config (dataclass configurations and input presets), cache (the memory-mapped inputs;
built from bags by :mod:`lcpr_offline.lcpr_cache`), split (database / train / val / test from poses),
dataset (cache -> tensors), mining (closest positive, negatives inside the margin), loss (triplet
margin loss), validation (Recall@N), plot (training curve), train (the loop, checkpoints, export).
The ``lcpr_train`` command, which reads the bags, is :mod:`lcpr_offline.lcpr_train`. The recipes of the
bundled weights (benchmarks/recipes/) decide by recipe_rules and score descriptor variants by recipe_scores.
"""
from .cache import SampleCache, open_cache
from .config import PRESETS, InputConfig, MiningConfig, OptimConfig, SplitConfig, TrainConfig, input_preset
from .dataset import TrainingData, to_model_inputs
from .loss import batch_triplet_loss, triplet_loss
from .mining import MiningResult, Triplet, closest_positive, mine, negatives_inside_margin
from .split import Split, split_samples
from .train import Trainer, export_weights, make_model
from .validation import Recall, split_recall

__all__ = [
    "PRESETS", "InputConfig", "MiningConfig", "MiningResult", "OptimConfig", "Recall", "SampleCache", "Split",
    "SplitConfig", "TrainConfig", "Trainer", "TrainingData", "Triplet", "batch_triplet_loss",
    "closest_positive", "export_weights", "input_preset", "make_model", "mine", "negatives_inside_margin",
    "open_cache", "split_recall", "split_samples", "to_model_inputs", "triplet_loss",
]
