"""Training VSeq2PC from a feature cache (``vseq2pc_train``).

Stage 1 pretrains the sequence model: MSE between F_seq and the forward 90 degrees of
the query frame's LiDAR structure feature. Stage 2 trains both models on (sequence,
scan) pairs: BCE-with-logits(max-slice logit, y) + y d^2 + (1 - y) relu(margin - d)^2,
d = ||D_seq - D_slice|| of the best slice. Optimisers as the release: Adam (0.002) for
the descriptor model; AdamW (base 1.5e-4 x batch / 256, betas 0.9/0.95, weight decay
0.05) with linear warm-up then cosine decay for the sequence model. The defaults are
scaled down to train in minutes on two CPU cores (the release: 50 epochs, 10 warm-up);
with so few steps the release's sequence-model rate barely moves it (stage-1 validation
MSE 0.067 -> 0.064 in two short epochs), ``--seq-base-lr 2.4e-3`` (1.5e-4 at batch 16)
reached 0.026. Stage 2 scores every query of a batch against every scan sampled for the
batch (in-batch pairs; pairs under 3 m or over 20 m count, positives and negatives
weighted half each): the same loss on ~B times more pairs per step for little extra
compute, which is what made short CPU runs learn at all. ``--no-in-batch`` scores only
each query's own sampled scans, as the release does.

The sequence model's output is clamped to [0, 1], and a clamped cell passes no gradient. In
stage 2 the joint loss pushed every cell of F_seq below 0 (a 12-epoch run on four drives
ended with F_seq == 0 everywhere, so the network ignored the sequence), and no gradient
could bring it back. Training therefore lets gradients through the clamp (straight-through;
values unchanged); ``--no-straight-through-clamp`` trains with the plain clamp.

Several drives train together (``--cache A.npz B.npz ...``): their frames are laid side by
side ``DRIVE_SPACING_M`` apart, so a pair across drives is always a negative.

Validation: the last ``val_fraction`` of each drive's frames (or a separate cache) give
the validation queries; per epoch its loss and the max F1 of its pairs.

The output folder holds ``sequence_model.pth`` (a state dict), ``descriptor_model.pth``
(``{'state_dict': ...}``, the released layout), ``best_*.pth`` (highest validation max
F1), ``train_state.pt`` (optimisers and history, for ``--resume``), ``history.json``
and ``curves.png``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from msg_tools.progress import progress_bar

from ..atomic import atomic_path, save_figure
from ..errors import InvalidValueError
from ..evaluation import pr_sweep
from ..models import DescriptorModel, SequenceModel
from ..preprocess.structure import CAMERA_SECTORS
from .checkpoint import (
    load_descriptor_state_dict,
    load_sequence_state_dict,
    save_descriptor_weights,
    save_sequence_weights,
)
from .dataset import FeatureCache
from .initialisation import seeded_models
from .net import scan_slice_descriptors
from .pairs import (
    NEGATIVE_RADIUS,
    POSITIVE_RADIUS,
    PairSet,
    TrainPairConfig,
    place_label,
    planar_distances,
    training_pairs,
)
from .retrieval import head_logits

__all__ = ["TrainConfig", "TrainData", "lr_at", "main", "pair_logits", "place_loss", "train"]

log = logging.getLogger(__name__)

SEQUENCE_FILE = "sequence_model.pth"
DESCRIPTOR_FILE = "descriptor_model.pth"
STATE_FILE = "train_state.pt"
DRIVE_SPACING_M = 1.0e6  # drives trained together lie this far apart: no pair across drives is a positive


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
        if self.seq_base_lr <= 0 or self.desc_lr <= 0 or self.seq_warmup_epochs < 0:
            raise InvalidValueError("learning rates must be positive and seq_warmup_epochs >= 0")

    @property
    def seq_lr(self) -> float:
        return self.seq_base_lr * self.batch / 256.0

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ---------------------------------------------------------------------- data
@dataclass
class TrainData:
    """Tensors of a cache and which frames are training / validation queries and scans."""

    camera: torch.Tensor  # (N, 12, 90)
    lidar: torch.Tensor  # (N, 12, 360)
    positions: np.ndarray  # (N, 3)
    sequences: np.ndarray  # (N, 4), -1 = incomplete
    queries: np.ndarray  # frame indices with a complete sequence
    scans: np.ndarray  # frame indices usable as scans

    @classmethod
    def from_cache(cls, cache: FeatureCache, rows: np.ndarray | None = None) -> TrainData:
        seq = cache.sequences()
        complete = np.flatnonzero(seq[:, 0] >= 0)
        scans = np.arange(len(cache))
        if rows is not None:
            keep = np.zeros(len(cache), bool)
            keep[rows] = True
            complete, scans = complete[keep[complete]], scans[keep]
        return cls(torch.from_numpy(cache.camera), torch.from_numpy(cache.lidar), cache.positions, seq, complete, scans)

    @classmethod
    def concat(cls, drives: Sequence[TrainData]) -> TrainData:
        """One dataset of several drives: frame indices renumbered, drive k moved k x ``DRIVE_SPACING_M`` in x."""
        if len(drives) == 1:
            return drives[0]
        starts = np.cumsum([0] + [len(d.positions) for d in drives[:-1]])
        positions = [d.positions + np.array([k * DRIVE_SPACING_M, 0.0, 0.0]) for k, d in enumerate(drives)]
        sequences = [np.where(d.sequences >= 0, d.sequences + s, -1) for d, s in zip(drives, starts, strict=True)]
        return cls(torch.cat([d.camera for d in drives]), torch.cat([d.lidar for d in drives]),
                   np.concatenate(positions), np.concatenate(sequences),
                   np.concatenate([d.queries + s for d, s in zip(drives, starts, strict=True)]),
                   np.concatenate([d.scans + s for d, s in zip(drives, starts, strict=True)]))

    def frames(self, queries: np.ndarray) -> torch.Tensor:
        """B x 4 x 12 x 90 camera-feature sequences of the query frames."""
        return self.camera[torch.from_numpy(self.sequences[queries])]

    def target(self, queries: np.ndarray) -> torch.Tensor:
        """B x 12 x 90: the forward 90 degrees of each query frame's LiDAR feature."""
        return self.lidar[torch.from_numpy(np.asarray(queries))][:, :, CAMERA_SECTORS]


def split(caches: Sequence[FeatureCache], val_fraction: float) -> tuple[TrainData, TrainData | None]:
    """Of each drive, the first frames train and the last ``val_fraction`` give validation queries (against
    every scan of every drive)."""
    if val_fraction == 0:
        return TrainData.concat([TrainData.from_cache(c) for c in caches]), None
    train, val = [], []
    for cache in caches:
        cut = int(round(len(cache) * (1.0 - val_fraction)))
        train.append(TrainData.from_cache(cache, np.arange(cut)))
        whole = TrainData.from_cache(cache)
        whole.queries = whole.queries[whole.queries >= cut]
        val.append(whole)
    return TrainData.concat(train), TrainData.concat(val)


# ---------------------------------------------------------------------- model pieces
def pair_logits(seq: SequenceModel, desc: DescriptorModel, frames: torch.Tensor, lidar: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """B x 4 x 12 x 90 sequences and B x S x 12 x 360 scans (S per sequence) -> max-slice logits (B, S) and
    the squared descriptor distance to the best slice (B, S)."""
    b, s = lidar.shape[:2]
    d_seq = desc.sequence_descriptor(seq(frames), frames[:, 0])  # B x 288
    d_scan = scan_slice_descriptors(desc, lidar.reshape(b * s, *lidar.shape[2:])).view(b, s, 8, -1)
    return _best_slice(desc, d_seq, d_scan)


def cross_logits(seq: SequenceModel, desc: DescriptorModel, frames: torch.Tensor, lidar: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """B sequences against every one of M scans (M x 12 x 360) -> logits and squared distances (B, M)."""
    d_seq = desc.sequence_descriptor(seq(frames), frames[:, 0])  # B x 288
    d_scan = scan_slice_descriptors(desc, lidar)  # M x 8 x 288
    return _best_slice(desc, d_seq, d_scan.expand(len(d_seq), -1, -1, -1))


def _best_slice(desc: DescriptorModel, d_seq: torch.Tensor, d_scan: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    values, indices = head_logits(desc, d_seq[:, None, None, :], d_scan)  # B x S
    chosen = torch.gather(d_scan, 2, indices[..., None, None].expand(-1, -1, 1, d_scan.shape[-1]))[:, :, 0]
    sq = ((d_seq[:, None, :] - chosen) ** 2).sum(dim=-1)
    return values, sq


def place_loss(logits: torch.Tensor, sq_dist: torch.Tensor, labels: torch.Tensor, *, margin: float,
               weights: torch.Tensor | None = None) -> torch.Tensor:
    """BCE-with-logits + y d^2 + (1 - y) relu(margin - d)^2, averaged (weighted when ``weights`` sum to 1)."""
    d = torch.sqrt(sq_dist + 1e-12)
    bce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    per_pair = bce + labels * sq_dist + (1 - labels) * F.relu(margin - d) ** 2
    return per_pair.mean() if weights is None else (per_pair * weights).sum()


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
    best_f1: float = -1.0


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
        return _pair_loss(run, data, q, training_pairs(data.positions, q, data.scans, config=run.config.pairs, rng=rng))

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
    logits, sq = pair_logits(run.seq, run.desc, data.frames(queries), scans)
    labels = torch.from_numpy(pairs.label.astype(np.float32)).view(len(queries), s)
    return place_loss(logits, sq, labels, margin=run.config.margin)


def _in_batch_loss(run: Run, data: TrainData, queries: np.ndarray, scans: np.ndarray) -> torch.Tensor:
    """Every query of the batch against every sampled scan of the batch; pairs closer than 3 m or farther
    than 20 m count (the others have no clear label), positives and negatives weighted half each."""
    scans = np.unique(scans)
    logits, sq = cross_logits(run.seq, run.desc, data.frames(queries), data.lidar[torch.from_numpy(scans)])
    dist = planar_distances(data.positions[queries], data.positions[scans])
    positive, negative = dist < POSITIVE_RADIUS, dist > NEGATIVE_RADIUS
    weights = np.zeros(dist.shape)
    for mask in (positive, negative):
        if mask.any():
            weights[mask] = 1.0 / mask.sum()
    weights /= weights.sum()
    labels = torch.from_numpy(place_label(dist).astype(np.float32))
    return place_loss(logits, sq, labels, margin=run.config.margin,
                      weights=torch.from_numpy(weights.astype(np.float32)))


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


# ---------------------------------------------------------------------- files
def _save(run: Run, out: Path, *, best: bool) -> None:
    save_sequence_weights(run.seq, out / SEQUENCE_FILE)
    save_descriptor_weights(run.desc, out / DESCRIPTOR_FILE)
    if best:
        save_sequence_weights(run.seq, out / f"best_{SEQUENCE_FILE}")
        save_descriptor_weights(run.desc, out / f"best_{DESCRIPTOR_FILE}")
    state = {
        "stage": run.stage, "epoch": run.epoch, "best_f1": run.best_f1,
        "seq_opt": None if run.seq_opt is None else run.seq_opt.state_dict(),
        "desc_opt": None if run.desc_opt is None else run.desc_opt.state_dict(),
        "history": json.dumps(run.history), "config": json.dumps(run.config.to_dict()),
    }
    with atomic_path(out / STATE_FILE) as tmp:
        torch.save(state, tmp)
    text = json.dumps({"config": run.config.to_dict(), "history": run.history}, indent=1)
    with atomic_path(out / "history.json") as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")
    plot_curves(run.history, out / "curves.png")


def _resume(run: Run, out: Path) -> None:
    state = torch.load(out / STATE_FILE, map_location="cpu", weights_only=True)
    run.seq.load_state_dict(load_sequence_state_dict(out / SEQUENCE_FILE))
    run.desc.load_state_dict(load_descriptor_state_dict(out / DESCRIPTOR_FILE))
    run.stage, run.epoch, run.best_f1 = int(state["stage"]), int(state["epoch"]), float(state["best_f1"])
    run.history = json.loads(state["history"])
    run.seq_opt = _seq_optimizer(run.seq, run.config)
    run.desc_opt = torch.optim.Adam(run.desc.parameters(), lr=run.config.desc_lr) if run.stage == 2 else None
    if state["seq_opt"] is not None:
        run.seq_opt.load_state_dict(state["seq_opt"])
    if run.desc_opt is not None and state["desc_opt"] is not None:
        run.desc_opt.load_state_dict(state["desc_opt"])
    log.info("resumed %s after stage %d epoch %d", out, run.stage, run.epoch)


def plot_curves(history: list[dict[str, Any]], path: Path) -> None:
    """Training and validation loss per epoch (both stages), and the validation max F1 (stage 2)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=100)
    FigureCanvasAgg(fig)
    for col, stage, title in ((1, 1, "stage 1: reconstruction MSE"), (2, 2, "stage 2: place loss")):
        ax = fig.add_subplot(1, 3, col)
        rows = [h for h in history if h["stage"] == stage]
        x = [h["epoch"] for h in rows]
        ax.plot(x, [h["train_loss"] for h in rows], "o-", label="train")
        ax.plot(x, [np.nan if h["val_loss"] is None else h["val_loss"] for h in rows], "s--", label="validation")
        ax.set(xlabel="epoch", ylabel="loss", title=title)
        ax.grid(alpha=0.3)
        ax.legend()
    ax = fig.add_subplot(1, 3, 3)
    rows = [h for h in history if h["stage"] == 2]
    ax.plot([h["epoch"] for h in rows], [np.nan if h["val_max_f1"] is None else h["val_max_f1"] for h in rows], "o-")
    ax.set(xlabel="epoch", ylabel="max F1", title="stage 2: validation pairs", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    save_figure(fig, path)


# ---------------------------------------------------------------------- the run
def train(config: TrainConfig) -> Run:
    """Run (or resume) both stages; returns the finished run (models in eval mode)."""
    if config.threads:
        torch.set_num_threads(config.threads)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    caches = [FeatureCache.load(path) for path in config.caches]
    data, val = split(caches, 0.0 if config.val_cache else config.val_fraction)
    if config.val_cache:
        val = TrainData.from_cache(FeatureCache.load(config.val_cache))
    if len(data.queries) == 0:
        raise InvalidValueError(f"{', '.join(config.caches)}: no complete query sequence in the training part; drive "
                                "longer (a sequence needs 15 m after its query frame)")
    seq, desc = seeded_models(config.seed)
    seq.straight_through_clamp = config.straight_through_clamp
    if config.init_sequence:
        seq.load_state_dict(load_sequence_state_dict(config.init_sequence))
    if config.init_descriptor:
        desc.load_state_dict(load_descriptor_state_dict(config.init_descriptor))
    run = Run(config, seq, desc)
    if config.resume and (out / STATE_FILE).is_file():
        _resume(run, out)
    val_pairs = PairSet(*(np.zeros(0, np.int64),) * 2, np.zeros(0), np.zeros(0))
    if val is not None and len(val.queries):
        val_cfg = TrainPairConfig(positives=1, negatives=config.val_negatives, revisit_fraction=1.0)
        val_pairs = training_pairs(val.positions, val.queries, val.scans, config=val_cfg,
                                   rng=np.random.default_rng(config.seed + 99))
    log.info("%d training queries, %d scans; %d validation queries, %d validation pairs", len(data.queries),
             len(data.scans), 0 if val is None else len(val.queries), len(val_pairs))

    for stage, epochs in ((1, config.pretrain_epochs), (2, config.epochs)):
        if stage < run.stage:
            continue
        first = run.epoch + 1 if stage == run.stage else 1
        if stage == 2 and (run.stage == 1 or run.desc_opt is None):
            run.seq_opt = _seq_optimizer(seq, config)  # a fresh schedule for the joint stage
            run.desc_opt = torch.optim.Adam(desc.parameters(), lr=config.desc_lr)
        elif stage == 1 and run.seq_opt is None:
            run.seq_opt = _seq_optimizer(seq, config)
        for epoch in range(first, epochs + 1):
            rng = np.random.default_rng([config.seed, stage, epoch])
            torch.manual_seed(config.seed * 1000 + stage * 100 + epoch)
            start = time.perf_counter()
            step = pretrain_epoch if stage == 1 else joint_epoch
            train_loss = step(run, data, epoch, rng)
            metrics = validate(run, val if val is not None else data, val_pairs, stage=stage)
            run.stage, run.epoch = stage, epoch
            f1 = metrics["val_max_f1"]
            best = stage == 2 and f1 is not None and f1 > run.best_f1
            if best:
                run.best_f1 = float(f1)  # type: ignore[arg-type]
            run.history.append({"stage": stage, "epoch": epoch, "train_loss": train_loss, **metrics,
                                "seq_lr": run.seq_opt.param_groups[0]["lr"] if run.seq_opt else None,
                                "seconds": time.perf_counter() - start})
            _save(run, out, best=best)
            _report(run.history[-1])
    seq.eval()
    desc.eval()
    return run


def _report(h: dict[str, Any]) -> None:
    val = "-" if h["val_loss"] is None else f"{h['val_loss']:.4f}"
    f1 = "" if h["val_max_f1"] is None else f", val max F1 {h['val_max_f1']:.3f}"
    print(f"stage {h['stage']} epoch {h['epoch']}: train loss {h['train_loss']:.4f}, val loss {val}{f1} "
          f"({h['seconds']:.0f} s)", flush=True)


def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig(caches=("-",), out="")
    p = argparse.ArgumentParser(prog="vseq2pc_train", description="Train VSeq2PC on a feature cache "
                                "(vseq2pc_cache): stage 1 pretrains the sequence model, stage 2 trains both.")
    p.add_argument("--cache", required=True, nargs="+", help="training feature cache(s) (.npz), one per drive")
    p.add_argument("--out", required=True, help="output folder (weights, train_state.pt, history.json, curves.png)")
    p.add_argument("--val-cache", default=None, help="validation cache (default: the last --val-fraction of --cache)")
    p.add_argument("--val-fraction", type=float, default=d.val_fraction)
    p.add_argument("--pretrain-epochs", type=int, default=d.pretrain_epochs, help="stage 1 epochs")
    p.add_argument("--epochs", type=int, default=d.epochs, help="stage 2 epochs")
    p.add_argument("--batch", type=int, default=d.batch, help="query sequences per step")
    p.add_argument("--queries-per-epoch", type=int, default=None, help="subsample the queries of each epoch")
    p.add_argument("--seq-base-lr", type=float, default=d.seq_base_lr, help="AdamW base lr (x batch / 256)")
    p.add_argument("--seq-warmup-epochs", type=float, default=d.seq_warmup_epochs)
    p.add_argument("--desc-lr", type=float, default=d.desc_lr, help="Adam lr of the descriptor model")
    p.add_argument("--negatives", type=int, default=d.pairs.negatives, help="negatives (> 20 m) per positive")
    p.add_argument("--revisit-fraction", type=float, default=d.pairs.revisit_fraction,
                   help="share of positives taken from another pass when there is one")
    p.add_argument("--in-batch", action=argparse.BooleanOptionalAction, default=d.in_batch,
                   help="score each query against every scan sampled for the batch (default), or only its own")
    p.add_argument("--straight-through-clamp", action=argparse.BooleanOptionalAction,
                   default=d.straight_through_clamp,
                   help="let gradients pass the sequence model's [0, 1] output clamp (default), or not (the release)")
    p.add_argument("--init-sequence", default=None, help="start from these sequence weights (released or ours)")
    p.add_argument("--init-descriptor", default=None, help="start from these descriptor weights")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        config = TrainConfig(
            caches=tuple(args.cache), out=args.out, val_cache=args.val_cache, val_fraction=args.val_fraction,
            pretrain_epochs=args.pretrain_epochs, epochs=args.epochs, batch=args.batch,
            queries_per_epoch=args.queries_per_epoch, seq_base_lr=args.seq_base_lr,
            seq_warmup_epochs=args.seq_warmup_epochs, desc_lr=args.desc_lr,
            in_batch=args.in_batch, straight_through_clamp=args.straight_through_clamp,
            pairs=TrainPairConfig(negatives=args.negatives, revisit_fraction=args.revisit_fraction),
            seed=args.seed, threads=args.threads, progress=not args.no_progress, resume=args.resume,
            init_sequence=args.init_sequence, init_descriptor=args.init_descriptor,
        )
        start = time.perf_counter()
        run = train(config)
    except (ValueError, OSError) as err:
        print(f"vseq2pc_train: error: {err}", file=sys.stderr)
        return 2
    print(f"done in {time.perf_counter() - start:.0f} s; weights in {os.fspath(config.out)} "
          f"(best validation max F1 {run.best_f1:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
