"""The training loop: cache descriptors, mine, step on triplets, validate, checkpoint, plot.

Files written into the output folder:

* ``init.pth``  the initial weights (epoch 0), to compare against the trained model;
* ``last.pth``  the latest epoch, with optimizer state and history (``--resume`` reads it);
* ``best.pth``  the epoch with the best validation Recall@1;
* ``history.json`` and ``curve.png``.

All checkpoints are the released layout ``{'epoch', 'net', 'scheduler'}`` plus a
``'config'`` entry (width, sizes, LiDAR preset) that :func:`lcpr_core.lcpr.describer.build_model`
reads, so ``build_model(ModelConfig(weights='best.pth'))`` rebuilds the trained network.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lcpr_common.progress import progress_bar

from ...atomic import atomic_path, save_torch
from ...errors import CheckpointError, InvalidValueError
from ...torch_files import check_state_dict
from ..checkpoint import LIDAR_ONLY, init_from_imagenet, load_weights, read_released, save_checkpoint
from ..models import LCPR
from ..turn_average import ENTRY as TURN_AVERAGE
from ..whitening import ENTRY as WHITENING
from .config import TrainConfig
from .dataset import TrainingData
from .loss import batch_triplet_loss
from .mining import Triplet, mine
from .plot import plot_training_curve
from .validation import split_recall

log = logging.getLogger(__name__)

CHECKPOINTS = ("init.pth", "last.pth", "best.pth")


def make_model(config: TrainConfig) -> LCPR:
    """The network to train: seeded, then its ResNet blocks from ImageNet or the whole network from a trained
    checkpoint (``init``, e.g. a float16 export) when a file is given."""
    inputs = config.inputs
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = LCPR(num_cameras=inputs.num_cameras, image_size=inputs.image_size, range_size=inputs.range_size,
                     width=inputs.width)
    if config.imagenet:
        init_from_imagenet(model, config.imagenet)
    if config.init:
        load_weights(model, config.init)  # copied into the float32 parameters
    return model


@dataclass
class Trainer:
    """Trains an LCPR on :class:`TrainingData`; :meth:`fit` runs (or resumes) to ``optim.epochs``."""

    data: TrainingData
    config: TrainConfig
    out: Path
    progress: bool = True
    echo: Callable[[str], None] = print
    model: LCPR = field(init=False)
    history: list[dict[str, Any]] = field(init=False, default_factory=list)
    epoch: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if self.data.lidar_only != self.config.lidar_only:  # the config decides what the network sees
            self.data = dataclasses.replace(self.data, lidar_only=self.config.lidar_only)
        torch.set_num_threads(self.config.threads)
        self.device = torch.device(self.config.device)
        self.model = make_model(self.config).to(self.device)
        opt = self.config.optim
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=opt.lr, weight_decay=opt.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.StepLR(self.optimizer, step_size=opt.step_epochs, gamma=opt.gamma)
        self._descriptors: np.ndarray | None = None
        self._augment_rng = np.random.default_rng([self.config.seed, 2])  # training inputs only
        self._deadline: float | None = None  # perf_counter() past which no step begins (the time budget)
        if len(self.data.split.train) == 0 or len(self.data.split.val) == 0:
            raise InvalidValueError(f"the split has {self.data.split.summary()}; training needs train and val queries "
                                    f"(record drives that revisit places, or change the split fractions)")

    # ------------------------------------------------------------------ checkpoints
    def _payload_extra(self, *, full: bool) -> dict[str, Any]:
        extra: dict[str, Any] = {"config": self.config.inputs.model_entry(), "history": self.history}
        if self.config.lidar_only:
            extra[LIDAR_ONLY] = True
        if full:
            extra |= {"optimizer": self.optimizer.state_dict(), "train": self.config.to_dict()}
        return extra

    def save(self, name: str, *, full: bool = False) -> Path:
        path = self.out / name
        save_checkpoint(self.model, path, epoch=self.epoch, scheduler=self.scheduler.state_dict(),
                        extra=self._payload_extra(full=full))
        return path

    def resume(self, path: str | os.PathLike[str] | None = None) -> None:
        """Continue from ``last.pth`` (or ``path``): weights, optimizer, scheduler, epoch count and history."""
        file = Path(path) if path else self.out / "last.pth"
        if not file.is_file():
            raise CheckpointError(f"cannot resume: {str(file)!r} does not exist")
        ckpt = torch.load(file, map_location=self.device, weights_only=True)
        if not isinstance(ckpt, dict) or "optimizer" not in ckpt or "net" not in ckpt:
            found = sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__
            raise CheckpointError(f"cannot resume from {str(file)!r}: it holds {found}; "
                                  f"expected a last.pth written by lcpr_train ('net', 'optimizer', 'scheduler')")
        want = self.config.inputs.model_entry()
        if ckpt.get("config") != want:
            raise CheckpointError(f"cannot resume from {str(file)!r}: it was trained with {ckpt.get('config')}, "
                                  f"this run asks for {want}")
        check_state_dict(self.model, ckpt["net"], source=str(file))
        self.model.load_state_dict(ckpt["net"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.scheduler.load_state_dict(ckpt["scheduler"])
        self.epoch = int(ckpt["epoch"])
        self.history = list(ckpt.get("history", []))
        self.echo(f"resumed from {file} at epoch {self.epoch} (lr {self.optimizer.param_groups[0]['lr']:.3g})")

    # ------------------------------------------------------------------ descriptors
    def describe(self, samples: np.ndarray, desc: str = "describe") -> np.ndarray:
        """N x 256 descriptors (NaN rows for samples not listed), model in eval mode."""
        return describe_samples(self.model, self.data, samples, batch=self.config.eval_batch, device=self.device,
                                amp=self.config.amp, progress=self.progress, desc=desc)

    def epoch_queries(self, epoch: int) -> np.ndarray:
        """The training queries of ``epoch`` (all, or a seeded random subset of ``queries_per_epoch``)."""
        queries = self.data.split.train
        n = self.config.optim.queries_per_epoch
        if n and n < len(queries):
            queries = np.sort(np.random.default_rng([self.config.seed, epoch, 1]).choice(queries, n, replace=False))
        return queries

    def _refresh(self) -> dict[str, float]:
        """Describe the database, the next epoch's queries and the val queries; validation recall."""
        split = self.data.split
        start = time.perf_counter()
        needed = np.concatenate([split.database, self.epoch_queries(self.epoch + 1), split.val])
        self._descriptors = self.describe(needed, desc=f"describe e{self.epoch}")
        recall = split_recall(split, self._descriptors, split.val)
        return recall.as_dict() | {"describe_s": round(time.perf_counter() - start, 1)}

    # ------------------------------------------------------------------ training
    def train_epoch(self) -> dict[str, Any]:
        """Mine on the cached descriptors, then one pass over the mined triplets."""
        assert self._descriptors is not None
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, self.epoch])
        start = time.perf_counter()
        mined = mine(self.epoch_queries(self.epoch), self.data.split, self._descriptors, cfg.mining, rng)
        triplets = [mined.triplets[i] for i in rng.permutation(len(mined.triplets))]
        self.model.train()
        losses: list[float] = []
        bar = progress_bar(len(triplets), desc=f"epoch {self.epoch}", unit="q", enabled=self.progress, leave=False)
        step = cfg.optim.queries_per_batch
        # Past the deadline (less the time the next refresh will take) no step begins: the epoch is cut short.
        stop = None if self._deadline is None else self._deadline - float(self.history[-1].get("describe_s", 0))
        trained = 0
        for lo in range(0, len(triplets), step):
            if stop is not None and time.perf_counter() > stop:
                break
            group = triplets[lo:lo + step]
            loss = self.step(group)
            losses.append(loss)
            trained += len(group)
            bar.update(len(group))
            bar.set_postfix(loss=f"{loss:.4f}", refresh=False)
        bar.close()
        self.scheduler.step()
        stats = mined.stats
        return {"loss": float(np.mean(losses)) if losses else None, "train_s": round(time.perf_counter() - start, 1),
                "tuples": stats.tuples, "trained": trained, "cut_short": trained < len(triplets),
                "no_negative": stats.no_negative, "no_positive": stats.no_positive,
                "mean_negatives": round(stats.mean_negatives, 3)}

    def step(self, triplets: Sequence[Triplet]) -> float:
        """One optimiser step on a group of triplets; returns the loss."""
        ids: list[int] = []
        for t in triplets:
            ids += [t.query, t.positive, *t.negatives]
        images, ranges = self.data.inputs(ids, augmentation=self.config.augment, rng=self._augment_rng,
                                          device=self.device)
        with autocast(self.device, self.config.amp):
            desc = self.model(images, ranges)
        loss = batch_triplet_loss(desc.float(), [len(t.negatives) for t in triplets],
                                  margin=self.config.mining.margin)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())

    def fit(self, *, resume: bool = False) -> list[dict[str, Any]]:
        """Train to ``optim.epochs`` epochs in all, validating and checkpointing after each."""
        self.out.mkdir(parents=True, exist_ok=True)
        if resume:
            self.resume()
        t0 = time.perf_counter()
        budget = self.config.optim.time_budget_s
        self._deadline = t0 + budget if budget else None
        recall = self._refresh()
        if not self.history:  # epoch 0: the initialisation
            self.history.append({"epoch": 0, "loss": None, "lr": self.optimizer.param_groups[0]["lr"],
                                 "seconds": round(time.perf_counter() - t0, 1), **recall})
            self.save("init.pth")
            self._report(self.history[-1])
        first = self.epoch  # epochs before it come from a resumed run
        for _ in range(self.epoch, self.config.optim.epochs):
            if self.epoch > first and self.history[-1].get("cut_short"):
                self.echo(f"time budget: {budget:g} s reached during epoch {self.epoch} "
                          f"({self.history[-1].get('trained')} queries trained); stopping")
                break
            spent = time.perf_counter() - t0
            if budget and len(self.history) > 1 and spent + self.history[-1]["seconds"] > budget:
                self.echo(f"time budget: {spent:.0f} s spent of {budget:g} s, and an epoch takes about "
                          f"{self.history[-1]['seconds']:.0f} s; stopping after epoch {self.epoch}")
                break
            self.epoch += 1
            start = time.perf_counter()
            lr = self.optimizer.param_groups[0]["lr"]
            record = {"epoch": self.epoch, "lr": lr, **self.train_epoch()}
            record |= self._refresh()
            record["seconds"] = round(time.perf_counter() - start, 1)
            best = max((h.get("recall@1", -1.0) for h in self.history if h["epoch"] > 0), default=-1.0)
            self.history.append(record)
            self.save("last.pth", full=True)
            if record["recall@1"] >= best:
                self.save("best.pth")
            self._write_history()
            self._report(record)
        self._write_history()
        return self.history

    def test_recall(self) -> dict[str, float]:
        """Recall@1/5/10 of the test queries with the current weights."""
        split = self.data.split
        if len(split.test) == 0:
            return {}
        desc = self.describe(np.concatenate([split.database, split.test]), desc="describe test")
        return split_recall(split, desc, split.test).as_dict()

    # ------------------------------------------------------------------ reporting
    def _write_history(self) -> None:
        with atomic_path(self.out / "history.json") as tmp:
            tmp.write_text(json.dumps(self.history, indent=1))
        plot_training_curve(self.history, self.out / "curve.png",
                            title=f"LCPR training (width {self.config.inputs.width:g}, "
                                  f"{self.config.inputs.image_size[0]}x{self.config.inputs.image_size[1]} images)")

    def _report(self, r: dict[str, Any]) -> None:
        loss = "   -   " if r.get("loss") is None else f"{r['loss']:.4f}"
        extra = "" if r["epoch"] == 0 else (f"  tuples {r['tuples']} (avg {r['mean_negatives']:.1f} neg, "
                                            f"{r['no_negative']} without negatives)")
        self.echo(f"epoch {r['epoch']:3d}  loss {loss}  val R@1 {_pct(r['recall@1'])} R@5 {_pct(r['recall@5'])} "
                  f"R@10 {_pct(r['recall@10'])}  lr {r['lr']:.3g}  {r['seconds']:.0f} s "
                  f"(describe {r.get('describe_s', 0):.0f} s){extra}")


@torch.no_grad()
def describe_samples(model: LCPR, data: TrainingData, samples: np.ndarray, *, batch: int = 16,
                     device: torch.device | str = "cpu", amp: str = "off", progress: bool = True,
                     desc: str = "describe") -> np.ndarray:
    """len(data) x 256 descriptors of ``samples`` (NaN rows for the others), ``model`` in eval mode
    (under bfloat16 autocast with ``amp='bf16'``)."""
    model.eval()
    out = np.full((len(data), model.descriptor_dim), np.nan, np.float32)
    samples = np.unique(np.asarray(samples, np.int64))
    bar = progress_bar(len(samples), desc=desc, unit="sample", enabled=progress, leave=False)
    for lo in range(0, len(samples), batch):
        idx = samples[lo:lo + batch]
        images, ranges = data.inputs(idx, device=device)
        with autocast(torch.device(device), amp):
            out[idx] = model(images, ranges).float().cpu().numpy()
        bar.update(len(idx))
    bar.close()
    return out


def autocast(device: torch.device, amp: str) -> torch.autocast:
    """bfloat16 autocast on ``device`` when ``amp`` is 'bf16'; a disabled one (float32) for 'off'."""
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp == "bf16")


def export_weights(source: str | os.PathLike[str], target: str | os.PathLike[str], *, half: bool = True) -> int:
    """Copy a checkpoint without optimizer state, floating tensors as float16 when ``half``; returns bytes.

    The result is the released layout plus 'config', 'history' and the descriptor post-processing entries
    ('whitening', 'turn_average'); it loads with ``weights_only=True`` (float16 tensors are cast when
    loaded into the float32 model).
    """
    ckpt = read_released(source)
    net = {k: (v.half() if half and v.is_floating_point() else v) for k, v in ckpt["net"].items()}
    payload = {"epoch": ckpt.get("epoch", 0), "net": net, "scheduler": ckpt.get("scheduler", {}),
               "config": ckpt.get("config"), "history": ckpt.get("history", [])}
    if ckpt.get(WHITENING) is not None:  # float32 always: it is small and scales tiny directions up
        payload[WHITENING] = ckpt[WHITENING]
    for entry in (TURN_AVERAGE, LIDAR_ONLY):
        if entry in ckpt:
            payload[entry] = ckpt[entry]
    return save_torch(payload, target, shared=True)  # a file to ship: readable by all


def _pct(v: float) -> str:
    return "  -  " if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:5.1f}"


