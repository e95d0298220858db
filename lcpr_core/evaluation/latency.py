"""Per-stage latency of a method's keyframes: percentiles in milliseconds."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidValueError


@dataclass(frozen=True)
class LatencyStats:
    count: int
    mean_ms: float
    p50_ms: float
    p90_ms: float
    p99_ms: float
    max_ms: float


def latency_stats(timings: Sequence[Mapping[str, float]], *, warmup: int = 0) -> dict[str, LatencyStats]:
    """Per stage (and "total", the sum of a sample's stages) percentiles in milliseconds.

    The first ``warmup`` samples are left out while more than that many exist.
    """
    samples = list(timings)
    if warmup < 0:
        raise InvalidValueError(f"warmup={warmup}; expected >= 0 samples")
    if len(samples) > warmup:
        samples = samples[warmup:]
    stages: dict[str, list[float]] = {}
    for sample in samples:
        for stage, seconds in sample.items():
            stages.setdefault(stage, []).append(seconds)
        if sample:
            stages.setdefault("total", []).append(sum(sample.values()))
    out = {}
    for stage, values in stages.items():
        ms = np.asarray(values, np.float64) * 1e3
        p50, p90, p99 = np.percentile(ms, [50, 90, 99])
        out[stage] = LatencyStats(len(ms), float(ms.mean()), float(p50), float(p90), float(p99), float(ms.max()))
    return out
