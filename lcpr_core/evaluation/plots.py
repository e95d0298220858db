"""The report's figures: precision-recall curves, latency histograms, the trajectory with accepted loops."""
from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..atomic import save_figure
from .protocols import GroundTruth, ProtocolResult
from .results import MethodResult


def _figure(size: tuple[float, float]) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)  # Agg without touching pyplot's global backend
    return fig


def plot_pr_curves(methods: Sequence[MethodResult], path: str | os.PathLike[str]) -> None:
    """Top-1 PR curves of every method, online protocol left, database/query right."""
    fig = _figure((10, 4.5))
    for col, (attr, title) in enumerate((("online", "online loop closure"), ("database_query", "database / query"))):
        ax = fig.add_subplot(1, 2, col + 1)
        for k, m in enumerate(methods):
            p: ProtocolResult | None = getattr(m, attr)
            color = f"C{k}"
            if p is None or p.pr is None:
                ax.plot([], [], color=color, label=f"{m.name}: n/a")
                continue
            ax.plot(p.pr.recall, p.pr.precision, color=color, lw=1.5, drawstyle="steps-post",
                    label=f"{m.name}: max F1 {p.pr.max_f1:.3f}")
            best = int(np.argmax(p.pr.f1))
            ax.plot(p.pr.recall[best], p.pr.precision[best], "o", color=color)
        ax.set(xlabel="recall", ylabel="precision", title=title, xlim=(0, 1.02), ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(loc="lower left", fontsize=8)
    save_figure(fig, path)


def plot_latency(methods: Sequence[MethodResult], path: str | os.PathLike[str], *, warmup: int = 0) -> None:
    """Histograms of per-keyframe stage times (ms, log axis), one panel per method."""
    fig = _figure((5 * max(1, len(methods)), 4))
    for k, m in enumerate(methods):
        ax = fig.add_subplot(1, max(1, len(methods)), k + 1)
        samples = m.timings[warmup:] if len(m.timings) > warmup else m.timings
        stages: dict[str, list[float]] = {}
        for sample in samples:
            for stage, seconds in sample.items():
                stages.setdefault(stage, []).append(seconds * 1e3)
            if sample:
                stages.setdefault("total", []).append(sum(sample.values()) * 1e3)
        values = [v for vs in stages.values() for v in vs if v > 0]
        if values:
            bins = np.geomspace(max(min(values), 1e-4), max(max(values), 1e-3) * 1.01, 40)
            for stage, vs in stages.items():
                style = dict(color="k", ls="--") if stage == "total" else {}
                ax.hist(np.maximum(vs, bins[0]), bins=bins, histtype="step", lw=1.5, label=stage, **style)
            ax.set_xscale("log")
            ax.legend(fontsize=8)
        total = m.latency.get("total")
        extra = "" if total is None else f" (total p50 {total.p50_ms:.1f} ms, p90 {total.p90_ms:.1f} ms)"
        ax.set(xlabel="ms per keyframe", ylabel="keyframes", title=f"{m.name}{extra}")
        ax.title.set_fontsize(9)
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def plot_trajectory(gt: GroundTruth, methods: Sequence[MethodResult], path: str | os.PathLike[str]) -> None:
    """The keyframe trajectory (x, y), keyframes with a true loop (orange), and each method's
    accepted online loops at its threshold: a dot on the query and a segment to the match, green
    when correct, red when not (an orange ring around a dot: that query had a true loop)."""
    from matplotlib.collections import LineCollection

    fig = _figure((5.5 * max(1, len(methods)), 5.5))
    xy = gt.positions[:, :2]
    for k, m in enumerate(methods):
        ax = fig.add_subplot(1, max(1, len(methods)), k + 1)
        ax.plot(xy[:, 0], xy[:, 1], "-", color="0.7", lw=1, zorder=1)
        if len(xy) and np.isfinite(xy).any():
            first = np.flatnonzero(np.isfinite(xy).all(axis=1))[0]
            ax.plot(*xy[first], "k^", ms=7, label="start", zorder=4)
        loops = np.flatnonzero(gt.has_loop)
        ax.scatter(xy[loops, 0], xy[loops, 1], s=60, color="tab:orange", label="true loop", zorder=2)
        p = m.online
        point = p.operating_point
        title = m.name
        if point is not None:
            accepted = np.flatnonzero(p.top1_distance <= point.threshold)
            for ok, color, label in ((True, "tab:green", "TP"), (False, "tab:red", "FP")):
                sel = accepted[p.top1_correct[accepted] == ok]
                if len(sel):
                    segs = np.stack([xy[p.query_rows[sel]], xy[p.top1_rows[sel]]], axis=1)
                    ax.add_collection(LineCollection(list(segs), colors=color, lw=1.2, zorder=3))
                ax.scatter(xy[p.query_rows[sel], 0], xy[p.query_rows[sel], 1], s=16, color=color,
                           label=f"{label} ({len(sel)})", zorder=3)
            where = " (its max-F1 threshold)" if point.source == "max F1" else ""
            title += f": loops accepted at distance <= {point.threshold:.3g}{where}"
        ax.set(xlabel="x (m)", ylabel="y (m)", title=title)
        ax.title.set_fontsize(9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    save_figure(fig, path)
