"""The training-curve PNG: loss per epoch and validation Recall@1/5/10."""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

from ...atomic import save_figure


def plot_training_curve(history: Sequence[Mapping[str, Any]], path: str | os.PathLike[str], *,
                        title: str = "LCPR training") -> None:
    """Write loss (left) and validation recall (right) against the epoch, atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.8), dpi=100)
    FigureCanvasAgg(fig)
    ax_loss, ax_rec = fig.subplots(1, 2)
    trained = [h for h in history if h.get("loss") is not None]
    ax_loss.plot([h["epoch"] for h in trained], [h["loss"] for h in trained], "o-", label="triplet loss")
    ax_loss.set(xlabel="epoch", ylabel="mean loss", title="training loss")
    ax_loss.grid(alpha=0.3)
    for key, style in (("recall@1", "o-"), ("recall@5", "s--"), ("recall@10", "^:")):
        pts = [(h["epoch"], h[key]) for h in history if key in h]
        if pts:
            ax_rec.plot(*zip(*pts, strict=True), style, label=key)
    ax_rec.set(xlabel="epoch (0 = initialisation)", ylabel="validation recall", title="validation", ylim=(0, 1.02))
    ax_rec.grid(alpha=0.3)
    ax_rec.legend(loc="lower right")
    fig.suptitle(title)
    save_figure(fig, path)
