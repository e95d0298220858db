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

Batch norm: the descriptor model's tower is shared by scan slices and by the camera stream
of the sequence descriptor. Called apart (the release), training normalises each kind with
its own batch statistics, while eval mode normalises both with one set of running
statistics; the network learned under a normalisation it never meets at inference
(docs/studies/vseq2pc_loss.md measures the difference).
``mixed_batch_norm`` passes both kinds through the tower together, so training sees what
eval sees. ``ranking_weight`` adds a ranking term (each query's positives above its
negatives, a softmax over the batch's max-slice logits), which is what Recall@1 asks for;
benchmarks/studies/vseq2pc_loss_study.sh measures both on the validation drive.

Several drives train together (``--cache A.npz B.npz ...``): their frames are laid side by
side ``DRIVE_SPACING_M`` apart, so a pair across drives is always a negative.

Validation: the last ``val_fraction`` of each drive's frames (or a separate cache) give
the validation queries; per epoch its loss and the max F1 of its pairs. With a separate
validation cache, stage 2 also runs vseq2pc_eval's protocol on it (Recall@1 of its loop
queries, max F1 at 1:100); ``select`` says which of the pairs' max F1 and that Recall@1
picks the ``best_*`` weights. ``ranking_weight`` adds the ranking term of
:func:`~lcpr_core.vseq2pc.training.loss.ranking_loss` to the stage-2 loss.

The output folder holds ``sequence_model.pth`` (a state dict), ``descriptor_model.pth``
(``{'state_dict': ...}``, the released layout), ``best_*.pth`` (highest validation max
F1), ``train_state.pt`` (optimisers and history, for ``--resume``), ``history.json``
and ``curves.png``.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...errors import InvalidValueError
from ..checkpoint import (
    load_descriptor_state_dict,
    load_sequence_state_dict,
)
from ..dataset import FeatureCache
from ..evaluate import evaluate
from ..initialisation import seeded_models
from ..net import Vseq2pcNet
from ..pairs import (
    PairSet,
    TrainPairConfig,
    training_pairs,
)
from .config import STATE_FILE, TrainConfig
from .data import TrainData, split
from .files import _resume, _save
from .loop import Run, joint_epoch, pretrain_epoch, validate
from .schedule import _seq_optimizer

log = logging.getLogger("lcpr_core.vseq2pc.training")

# ---------------------------------------------------------------------- the run
def train(config: TrainConfig) -> Run:
    """Run (or resume) both stages; returns the finished run (models in eval mode)."""
    if config.threads:
        torch.set_num_threads(config.threads)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    caches = [FeatureCache.load(path) for path in config.caches]
    data, val = split(caches, 0.0 if config.val_cache else config.val_fraction)
    val_drive = FeatureCache.load(config.val_cache) if config.val_cache else None
    if val_drive is not None:
        val = TrainData.from_cache(val_drive)
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
            if stage == 2 and val_drive is not None:
                metrics.update(_protocol(run, val_drive))
            run.stage, run.epoch = stage, epoch
            score = metrics.get("val_max_f1" if config.select == "max_f1" else "val_recall_at_1")
            best = stage == 2 and score is not None and score > run.best_f1
            if best and score is not None:
                run.best_f1 = float(score)
            run.history.append({"stage": stage, "epoch": epoch, "train_loss": train_loss, **metrics,
                                "seq_lr": run.seq_opt.param_groups[0]["lr"] if run.seq_opt else None,
                                "seconds": time.perf_counter() - start})
            _save(run, out, best=best)
            _report(run.history[-1])
    seq.eval()
    desc.eval()
    return run


def _protocol(run: Run, drive: FeatureCache) -> dict[str, float | None]:
    """vseq2pc_eval's protocol on the validation drive: Recall@1 of its loop queries, max F1 at 1:100."""
    result = evaluate(Vseq2pcNet.from_models(run.seq, run.desc), drive, name="validation")
    return {"val_recall_at_1": result.recall_at.get(1), "val_protocol_max_f1": result.max_f1}


def _report(h: dict[str, Any]) -> None:
    val = "-" if h["val_loss"] is None else f"{h['val_loss']:.4f}"
    f1 = "" if h["val_max_f1"] is None else f", val max F1 {h['val_max_f1']:.3f}"
    r1 = "" if h.get("val_recall_at_1") is None else f", val R@1 {h['val_recall_at_1']:.3f}"
    print(f"stage {h['stage']} epoch {h['epoch']}: train loss {h['train_loss']:.4f}, val loss {val}{f1}{r1} "
          f"({h['seconds']:.0f} s)", flush=True)
