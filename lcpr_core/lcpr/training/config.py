"""Dataclass configurations of LCPR training: inputs, split, mining, optimisation, augmentation."""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from typing import Any

from ...errors import CheckpointError, InvalidValueError
from ..describer import checkpoint_config
from ..preprocess import lidar_preset
from .augment import AugmentConfig

NEGATIVE_RULES = ("violating", "absolute")
AMP_MODES = ("off", "bf16")


@dataclass(frozen=True)
class InputConfig:
    """The model inputs the cache holds and the network is built for."""

    num_cameras: int = 6
    image_size: tuple[int, int] = (64, 192)  # (height, width) of each camera image; multiples of 32
    range_size: tuple[int, int] = (16, 288)  # (height, width) of the range image; multiples of 8
    lidar: str = "nuscenes_lidar_top"  # range-image preset (geometry); its size is replaced by range_size
    width: float = 0.25  # channel multiplier of the network (1.0 = released)

    def __post_init__(self) -> None:
        lidar_preset(self.lidar)  # raises with the accepted names
        if self.num_cameras < 1:
            raise InvalidValueError(f"num_cameras={self.num_cameras}; it must be at least 1")
        if len(self.image_size) != 2 or any(v < 32 or v % 32 for v in self.image_size):
            raise InvalidValueError(f"image_size={self.image_size}; accepted: (height, width), multiples of 32, "
                                    f"e.g. (64, 192) or (256, 704)")
        if len(self.range_size) != 2 or any(v < 8 or v % 8 for v in self.range_size):
            raise InvalidValueError(f"range_size={self.range_size}; accepted: (height, width), multiples of 8, "
                                    f"e.g. (16, 288) or (32, 1056)")
        if not 0 < self.width <= 4:
            raise InvalidValueError(f"width={self.width}; accepted: a channel multiplier in (0, 4], e.g. 0.25 or 1.0")

    def model_entry(self) -> dict[str, Any]:
        """The 'config' entry written next to 'net' in checkpoints (read back by build_model)."""
        return {"width": float(self.width), "num_cameras": int(self.num_cameras),
                "image_size": list(self.image_size), "range_size": list(self.range_size), "lidar": self.lidar}


#: Named input configurations: the released one (GPU) and smaller ones for CPU training.
PRESETS: dict[str, InputConfig] = {
    "released": InputConfig(image_size=(256, 704), range_size=(32, 1056), width=1.0),
    "cpu": InputConfig(image_size=(64, 192), range_size=(16, 288), width=0.25),
    "cpu_large": InputConfig(image_size=(128, 352), range_size=(32, 528), width=0.5),
}


def input_preset(name: str) -> InputConfig:
    try:
        return PRESETS[name]
    except KeyError as err:
        raise InvalidValueError(f"unknown input preset {name!r}; accepted: {', '.join(PRESETS)}") from err


def checkpoint_inputs(checkpoint: str | os.PathLike[str], *, default: InputConfig | None = None) -> InputConfig:
    """The inputs a checkpoint written by lcpr_train was trained on (its 'config' entry).

    A file without the entry (a released checkpoint, a plain state dict) gives ``default``, or is refused
    when there is none.
    """
    entry = checkpoint_config(checkpoint)
    if not entry:
        if default is not None:
            return default
        raise CheckpointError(f"{str(checkpoint)!r} has no 'config' entry (sizes and width); expected a checkpoint "
                              "written by lcpr_train")
    return InputConfig(num_cameras=int(entry.get("num_cameras", 6)), image_size=tuple(entry["image_size"]),
                       range_size=tuple(entry["range_size"]), lidar=str(entry.get("lidar", "nuscenes_lidar_top")),
                       width=float(entry["width"]))


@dataclass(frozen=True)
class SplitConfig:
    """How samples become database / train / val / test queries (the paper's organisation)."""

    positive_radius: float = 9.0  # m: a database sample this close to a query is a positive
    negative_radius: float = 18.0  # m: a database sample at least this far is a negative
    exclude_recent_s: float = 30.0  # s: a match must be older than this to make a sample a revisit
    fractions: tuple[float, float, float] = (0.7, 0.1, 0.2)  # train / val / test shares of the queries
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.positive_radius < self.negative_radius:
            raise InvalidValueError(f"positive_radius={self.positive_radius}, negative_radius={self.negative_radius}; "
                                    f"accepted: 0 < positive_radius < negative_radius (paper: 9 and 18 m)")
        if not self.exclude_recent_s >= 0:
            raise InvalidValueError(f"exclude_recent_s={self.exclude_recent_s}; it must be >= 0 seconds")
        if len(self.fractions) != 3 or any(f < 0 for f in self.fractions) or abs(sum(self.fractions) - 1) > 1e-6:
            raise InvalidValueError(
                f"fractions={self.fractions}; accepted: three shares (train, val, test) >= 0 summing to 1")


@dataclass(frozen=True)
class MiningConfig:
    """Hard-example mining for the triplet loss."""

    negatives: int = 6  # negatives per query (paper: 6)
    margin: float = 0.5  # triplet margin m (paper: 0.5)
    pool: int = 64  # random potential negatives examined per query and epoch
    rule: str = "violating"  # violating: d(q,n) < d(q,p) + m; absolute: d(q,n) < m (the paper's Eq. 7)

    def __post_init__(self) -> None:
        if self.negatives < 1:
            raise InvalidValueError(f"negatives={self.negatives}; it must be at least 1 (paper: 6)")
        if not self.margin > 0:
            raise InvalidValueError(f"margin={self.margin}; it must be positive (paper: 0.5)")
        if self.pool < self.negatives:
            raise InvalidValueError(f"pool={self.pool}; it must be at least negatives={self.negatives}")
        if self.rule not in NEGATIVE_RULES:
            raise InvalidValueError(f"rule={self.rule!r}; accepted: {', '.join(NEGATIVE_RULES)}")


@dataclass(frozen=True)
class OptimConfig:
    """Adam with step decay (paper: lr 1e-5, x0.8 every 10 epochs)."""

    epochs: int = 30
    lr: float = 1e-5
    gamma: float = 0.8
    step_epochs: int = 10
    queries_per_batch: int = 4  # each brings 1 + 1 + up to `negatives` samples
    queries_per_epoch: int = 0  # 0 = all training queries; else a random subset each epoch
    weight_decay: float = 0.0
    # 0 = none; else no epoch is begun that would end past it (judged by the last one's time), and an epoch
    # still running when it is reached is cut short
    time_budget_s: float = 0.0

    def __post_init__(self) -> None:
        if self.epochs < 1:
            raise InvalidValueError(f"epochs={self.epochs}; it must be at least 1")
        if not self.lr > 0:
            raise InvalidValueError(f"lr={self.lr}; it must be positive (paper: 1e-5)")
        if not 0 < self.gamma <= 1:
            raise InvalidValueError(f"gamma={self.gamma}; accepted: (0, 1] (paper: 0.8)")
        if self.step_epochs < 1:
            raise InvalidValueError(f"step_epochs={self.step_epochs}; it must be at least 1 (paper: 10)")
        if self.queries_per_batch < 1:
            raise InvalidValueError(f"queries_per_batch={self.queries_per_batch}; it must be at least 1")
        if self.queries_per_epoch < 0:
            raise InvalidValueError(f"queries_per_epoch={self.queries_per_epoch}; it must be >= 0 (0 = all)")
        if self.weight_decay < 0:
            raise InvalidValueError(f"weight_decay={self.weight_decay}; it must be >= 0")
        if not self.time_budget_s >= 0:
            raise InvalidValueError(f"time_budget_s={self.time_budget_s}; it must be >= 0 seconds (0 = none)")


@dataclass(frozen=True)
class TrainConfig:
    """Everything one training run depends on besides the bags."""

    inputs: InputConfig = field(default_factory=lambda: PRESETS["cpu"])
    split: SplitConfig = field(default_factory=SplitConfig)
    mining: MiningConfig = field(default_factory=MiningConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    seed: int = 0  # network initialisation and sampling seed
    imagenet: str = ""  # torchvision resnet18 state dict for the ResNet blocks (width 1.0 only)
    init: str = ""  # a trained checkpoint whose network is the starting point (fine-tuning); fresh optimizer
    threads: int = 2  # torch intra-op threads
    eval_batch: int = 16  # samples per forward when caching descriptors
    device: str = "cpu"  # torch device, e.g. cuda:0 for the released preset
    amp: str = "off"  # off: float32 throughout; bf16: forward passes under bfloat16 autocast (GPUs)
    augment: AugmentConfig = field(default_factory=AugmentConfig)  # off by default
    lidar_only: bool = False  # every camera slot empty in training, mining and validation (LiDAR-only weights)

    def __post_init__(self) -> None:
        if self.threads < 1:
            raise InvalidValueError(f"threads={self.threads}; it must be at least 1")
        if self.eval_batch < 1:
            raise InvalidValueError(f"eval_batch={self.eval_batch}; it must be at least 1")
        if self.amp not in AMP_MODES:
            raise InvalidValueError(f"amp={self.amp!r}; accepted: {', '.join(AMP_MODES)}")
        if self.imagenet and self.inputs.width != 1.0:
            raise InvalidValueError(f"imagenet={self.imagenet!r} needs width 1.0 (torchvision resnet18 shapes); "
                                    f"got width={self.inputs.width}")
        if self.imagenet and self.init:
            raise InvalidValueError(f"imagenet={self.imagenet!r} and init={self.init!r}: give one starting point, "
                                    "not both")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
