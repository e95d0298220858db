"""One epoch of stage 1 (reconstruction) or stage 2 (joint), and validation."""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from lcpr_common.progress import progress_bar

from ...evaluation import pr_sweep
from ..models import DescriptorModel, SequenceModel
from ..net import scan_slice_descriptors
from ..pairs import (
    NEGATIVE_RADIUS,
    POSITIVE_RADIUS,
    PairSet,
    place_label,
    planar_distances,
    training_pairs,
)
from ..retrieval import head_logits
from .config import TrainConfig
from .data import TrainData
from .loss import cross_logits, pair_logits, place_loss, ranking_loss
from .schedule import _set_lr, lr_at

log = logging.getLogger("lcpr_core.vseq2pc.training")

# ---------------------------------------------------------------------- one epoch
@dataclass
class Run:
    """Models, optimisers and progress of a training run."""

    config: TrainConfig
    seq: SequenceModel
    desc: DescriptorModel
    seq_opt: torch.optim.Optimizer | None = None
    desc_opt: torch.optim.Optimizer | None = None
    stage: int = 1  # the stage of the last completed epoch (1 before anything ran)
    epoch: int = 0  # completed epochs of that stage
    history: list[dict[str, Any]] = field(default_factory=list)
    best_f1: float = -1.0  # the best epoch's value of config.select (max F1 or Recall@1; name kept for resumes)


def _epoch_queries(data: TrainData, config: TrainConfig, rng: np.random.Generator) -> np.ndarray:
    order = rng.permutation(data.queries)
    return order if config.queries_per_epoch is None else order[: config.queries_per_epoch]


def _batches(items: np.ndarray, size: int) -> list[np.ndarray]:
    return [items[i : i + size] for i in range(0, len(items), size)]


def pretrain_epoch(run: Run, data: TrainData, epoch: int, rng: np.random.Generator) -> float:
    """One stage-1 epoch: MSE between F_seq and the query frame's forward LiDAR feature."""
    run.seq.train()
    assert run.seq_opt is not None

    def loss(q: np.ndarray) -> torch.Tensor:
        return F.mse_loss(run.seq(data.frames(q)), data.target(q))

    return _epoch(run, data, epoch, rng, stage=1, loss=loss, optimisers=(run.seq_opt,))


def joint_epoch(run: Run, data: TrainData, epoch: int, rng: np.random.Generator) -> float:
    """One stage-2 epoch: the place loss of each batch's pairs (both models)."""
    run.seq.train()
    run.desc.train()
    assert run.seq_opt is not None and run.desc_opt is not None

    def loss(q: np.ndarray) -> torch.Tensor:
        value = _pair_loss(run, data, q, training_pairs(data.positions, q, data.scans, config=run.config.pairs,
                                                         rng=rng))
        if run.config.reconstruction_weight > 0:  # stage 1's task kept: F_seq stays the LiDAR's forward view
            value = value + run.config.reconstruction_weight * F.mse_loss(run.seq(data.frames(q)), data.target(q))
        return value

    return _epoch(run, data, epoch, rng, stage=2, loss=loss, optimisers=(run.seq_opt, run.desc_opt))


def _epoch(run: Run, data: TrainData, epoch: int, rng: np.random.Generator, *, stage: int,
           loss: Callable[[np.ndarray], torch.Tensor], optimisers: tuple[torch.optim.Optimizer, ...]) -> float:
    """Batches of the epoch's queries: the sequence model's learning rate on its schedule, one step of
    every optimiser per batch; returns the mean loss."""
    cfg = run.config
    assert run.seq_opt is not None
    epochs = cfg.pretrain_epochs if stage == 1 else cfg.epochs
    batches = _batches(_epoch_queries(data, cfg, rng), cfg.batch)
    per_epoch = max(1, len(batches))
    total, warm = per_epoch * epochs, int(round(per_epoch * cfg.seq_warmup_epochs))
    losses: list[float] = []
    with progress_bar(len(batches), desc=f"stage {stage} epoch {epoch}/{epochs}", unit="batch",
                      enabled=cfg.progress, leave=False) as bar:
        for i, q in enumerate(batches):
            _set_lr(run.seq_opt, lr_at((epoch - 1) * per_epoch + i, base=cfg.seq_lr, warmup_steps=warm,
                                       total_steps=total))
            value = loss(q)
            for opt in optimisers:
                opt.zero_grad(set_to_none=True)
            value.backward()
            for opt in optimisers:
                opt.step()
            losses.append(value.item())
            bar.update()
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
    return float(np.mean(losses)) if losses else float("nan")


def _pair_loss(run: Run, data: TrainData, queries: np.ndarray, pairs: PairSet) -> torch.Tensor:
    s = len(pairs) // len(queries)
    if run.config.in_batch:
        return _in_batch_loss(run, data, queries, pairs.scan)
    scans = data.lidar[torch.from_numpy(pairs.scan)].view(len(queries), s, 12, -1)
    logits, sq = pair_logits(run.seq, run.desc, data.frames(queries), scans,
                             mixed_batch_norm=run.config.mixed_batch_norm)
    return _stage2_loss(run, logits, sq, pairs.distance.reshape(len(queries), s))


def _in_batch_loss(run: Run, data: TrainData, queries: np.ndarray, scans: np.ndarray) -> torch.Tensor:
    """Every query of the batch against every sampled scan of the batch; pairs closer than 3 m or farther
    than 20 m count (the others have no clear label), positives and negatives weighted half each."""
    scans = np.unique(scans)
    logits, sq = cross_logits(run.seq, run.desc, data.frames(queries), data.lidar[torch.from_numpy(scans)],
                              mixed_batch_norm=run.config.mixed_batch_norm)
    dist = planar_distances(data.positions[queries], data.positions[scans])
    weights = np.zeros(dist.shape)
    for mask in (dist < POSITIVE_RADIUS, dist > NEGATIVE_RADIUS):
        if mask.any():
            weights[mask] = 1.0 / mask.sum()
    weights /= weights.sum()
    return _stage2_loss(run, logits, sq, dist, weights=torch.from_numpy(weights.astype(np.float32)))


def _stage2_loss(run: Run, logits: torch.Tensor, sq: torch.Tensor, dist: np.ndarray, *,
                 weights: torch.Tensor | None = None) -> torch.Tensor:
    """The place loss of pairs ``dist`` metres apart (labels by :func:`place_label`), plus the ranking term
    over their positives (< 3 m) and negatives (> 20 m) when ``ranking_weight`` is set."""
    labels = torch.from_numpy(place_label(dist).astype(np.float32))
    loss = place_loss(logits, sq, labels, margin=run.config.margin, weights=weights)
    if run.config.ranking_weight > 0:
        loss = loss + run.config.ranking_weight * ranking_loss(
            logits, torch.from_numpy(dist < POSITIVE_RADIUS), torch.from_numpy(dist > NEGATIVE_RADIUS))
    return loss


@torch.inference_mode()
def validate(run: Run, data: TrainData, pairs: PairSet, *, stage: int) -> dict[str, float | None]:
    """Stage 1: MSE of the validation queries. Stage 2: pair loss and max F1 (scores: max-slice logits).

    Every query sequence and every scan is described once (eval mode), then the pairs are scored."""
    run.seq.eval()
    run.desc.eval()
    queries = np.unique(pairs.query) if len(pairs) else data.queries
    if len(queries) == 0:
        return {"val_loss": None, "val_max_f1": None}
    f_seq = torch.cat([run.seq(data.frames(q)) for q in _batches(queries, 64)])
    if stage == 1:
        return {"val_loss": float(F.mse_loss(f_seq, data.target(queries))), "val_max_f1": None}
    if len(pairs) == 0:
        return {"val_loss": None, "val_max_f1": None}
    frames0 = data.camera[torch.from_numpy(data.sequences[queries, 0])]
    d_seq = run.desc.sequence_descriptor(f_seq, frames0)
    scans = np.unique(pairs.scan)
    d_scan = torch.cat([scan_slice_descriptors(run.desc, data.lidar[torch.from_numpy(s)])
                        for s in _batches(scans, 128)])
    qi = torch.from_numpy(np.searchsorted(queries, pairs.query))
    si = torch.from_numpy(np.searchsorted(scans, pairs.scan))
    values, indices = head_logits(run.desc, d_seq[qi][:, None, :], d_scan[si])  # P
    chosen = d_scan[si, indices]
    sq = ((d_seq[qi] - chosen) ** 2).sum(dim=1)
    labels = torch.from_numpy(pairs.label.astype(np.float32))
    loss = place_loss(values, sq, labels, margin=run.config.margin)
    positive = pairs.positive
    pr = pr_sweep(-values.numpy(), positive, num_positives=int(positive.sum()), num_queries=len(pairs))
    return {"val_loss": float(loss), "val_max_f1": None if pr is None else pr.max_f1}
