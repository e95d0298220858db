"""Weights, best weights and the resumable training state in the output folder."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import torch

from ...atomic import atomic_path, save_torch
from ..checkpoint import (
    load_descriptor_state_dict,
    load_sequence_state_dict,
    save_descriptor_weights,
    save_sequence_weights,
)
from .config import DESCRIPTOR_FILE, SEQUENCE_FILE, STATE_FILE
from .loop import Run
from .plot import plot_curves
from .schedule import _seq_optimizer

log = logging.getLogger("lcpr_core.vseq2pc.training")

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
    save_torch(state, out / STATE_FILE)
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
