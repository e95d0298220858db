"""The training curves (curves.png)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ...atomic import save_figure

log = logging.getLogger("lcpr_core.vseq2pc.training")

def plot_curves(history: list[dict[str, Any]], path: Path) -> None:
    """Training and validation loss per epoch (both stages), and the validation max F1 and Recall@1 (stage 2)."""
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
    x = [h["epoch"] for h in rows]
    ax.plot(x, [np.nan if h["val_max_f1"] is None else h["val_max_f1"] for h in rows], "o-", label="pairs max F1")
    if any(h.get("val_recall_at_1") is not None for h in rows):
        ax.plot(x, [np.nan if h.get("val_recall_at_1") is None else h["val_recall_at_1"] for h in rows], "s-",
                label="drive Recall@1")
    ax.set(xlabel="epoch", ylabel="max F1 / Recall@1", title="stage 2: validation", ylim=(0, 1.02))
    ax.legend()
    ax.grid(alpha=0.3)
    save_figure(fig, path)
