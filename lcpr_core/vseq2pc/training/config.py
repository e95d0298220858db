"""The settings of a VSeq2PC training run (``vseq2pc_train``) and the files it writes."""
from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from typing import Any

from ...errors import InvalidValueError
from ..pairs import (
    TrainPairConfig,
)

log = logging.getLogger("lcpr_core.vseq2pc.training")

SEQUENCE_FILE = "sequence_model.pth"
DESCRIPTOR_FILE = "descriptor_model.pth"
STATE_FILE = "train_state.pt"
DRIVE_SPACING_M = 1.0e6  # drives trained together lie this far apart: no pair across drives is a positive
#: what picks the best epoch: the validation pairs' max F1, or Recall@1 of the validation drive's loop
#: queries (vseq2pc_eval's protocol; needs a separate validation cache)
SELECT_METRICS = ("max_f1", "recall_at_1")



@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (the CLI's options)."""

    caches: tuple[str, ...]
    out: str
    val_cache: str | None = None
    val_fraction: float = 0.15
    pretrain_epochs: int = 2
    epochs: int = 4
    batch: int = 16
    queries_per_epoch: int | None = None  # None = every training query once per epoch
    seq_base_lr: float = 1.5e-4  # x batch / 256
    seq_warmup_epochs: float = 1.0
    seq_weight_decay: float = 0.05
    seq_betas: tuple[float, float] = (0.9, 0.95)
    desc_lr: float = 0.002
    margin: float = 0.2
    mixed_batch_norm: bool = False  # scans and sequences share the tower's batch statistics (loss.describe)
    reconstruction_weight: float = 0.0  # stage 1's MSE kept in stage 2 with this weight; 0 = the release
    ranking_weight: float = 0.0  # weight of the ranking term (training.loss.ranking_loss); 0 = the release's loss
    select: str = "max_f1"  # SELECT_METRICS
    in_batch: bool = True  # score every query of a batch against every sampled scan of the batch
    straight_through_clamp: bool = True  # gradients pass the sequence model's output clamp (SequenceModel)
    pairs: TrainPairConfig = field(default_factory=TrainPairConfig)
    val_negatives: int = 10
    seed: int = 0
    threads: int | None = None
    progress: bool = True
    resume: bool = False
    init_sequence: str | None = None  # weights to start from (released or ours)
    init_descriptor: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.caches, (str, os.PathLike)) or not self.caches:
            raise InvalidValueError(f"caches={self.caches!r}; expected one or more feature cache paths")
        object.__setattr__(self, "caches", tuple(os.fspath(c) for c in self.caches))
        for name in ("pretrain_epochs", "epochs", "val_negatives"):
            if getattr(self, name) < 0:
                raise InvalidValueError(f"{name}={getattr(self, name)}; expected >= 0")
        if self.batch < 1:
            raise InvalidValueError(f"batch={self.batch}; expected >= 1")
        if not 0.0 <= self.val_fraction < 1.0:
            raise InvalidValueError(f"val_fraction={self.val_fraction}; expected a share in [0, 1)")
        if self.queries_per_epoch is not None and self.queries_per_epoch < 1:
            raise InvalidValueError(f"queries_per_epoch={self.queries_per_epoch}; expected None or >= 1")
        for name in ("ranking_weight", "reconstruction_weight"):
            if getattr(self, name) < 0:
                raise InvalidValueError(f"{name}={getattr(self, name)}; expected >= 0")
        if self.select not in SELECT_METRICS:
            raise InvalidValueError(f"select={self.select!r}; accepted: {', '.join(SELECT_METRICS)}")
        if self.select == "recall_at_1" and self.val_cache is None:
            raise InvalidValueError("select='recall_at_1' needs val_cache (a drive of its own with revisits)")
        if self.seq_base_lr <= 0 or self.desc_lr <= 0 or self.seq_warmup_epochs < 0:
            raise InvalidValueError("learning rates must be positive and seq_warmup_epochs >= 0")

    @property
    def seq_lr(self) -> float:
        return self.seq_base_lr * self.batch / 256.0

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
