"""Learning rates: linear warm-up then cosine decay; the sequence model's AdamW."""
from __future__ import annotations

import logging
import math

import torch

from ..models import SequenceModel
from .config import TrainConfig

log = logging.getLogger("lcpr_core.vseq2pc.training")

def lr_at(step: int, *, base: float, warmup_steps: int, total_steps: int) -> float:
    """Linear warm-up to ``base`` then cosine decay to 0 at ``total_steps``."""
    if warmup_steps > 0 and step < warmup_steps:
        return base * (step + 1) / warmup_steps
    span = max(1, total_steps - warmup_steps)
    return base * 0.5 * (1.0 + math.cos(math.pi * min(1.0, (step - warmup_steps) / span)))


def _set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    for group in opt.param_groups:
        group["lr"] = lr


def _seq_optimizer(seq: SequenceModel, config: TrainConfig) -> torch.optim.AdamW:
    return torch.optim.AdamW(seq.parameters(), lr=config.seq_lr, betas=config.seq_betas,
                             weight_decay=config.seq_weight_decay)
