"""Online figures read back from an ``lcpr_eval`` report (``OUT/report.json``, written by :mod:`.report`).

The recipes and tools that run ``lcpr_eval`` in a subprocess compare its results through these,
so they all read the same fields the same way. Plain JSON: it imports nothing of the evaluation.
"""
from __future__ import annotations

import json
from pathlib import Path


def online_methods(report: Path) -> dict[str, dict[str, float | None]]:
    """Online Recall@1, max F1 and its threshold of every method in an ``lcpr_eval`` report, by name."""
    methods = json.loads(report.read_text())["methods"]
    return {m["name"]: {"recall@1": float(m["online"]["recall_at"]["1"]), "max_f1": float(m["online"]["max_f1"]),
                        "max_f1_threshold": m["online"].get("max_f1_threshold")} for m in methods}


def online(report: Path) -> tuple[float, float]:
    """(online Recall@1, max F1) of the report's first method (LCPR)."""
    first = next(iter(online_methods(report).values()))
    return float(first["recall@1"] or 0.0), float(first["max_f1"] or 0.0)
