"""Small timing helpers shared by the demo and the benchmarks."""
from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

#: Instruction-set flags that decide which inference path is fastest (see lcpr_core.lcpr.runtime.choose).
CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_bf16", "amx_int8")


def _cpuinfo(key: str) -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(key):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def cpu_model() -> str:
    """The CPU's marketing name (from /proc/cpuinfo on Linux): every speed figure names it."""
    return _cpuinfo("model name") or platform.processor() or platform.machine() or "unknown CPU"


def cpu_flags() -> str:
    """Which of :data:`CPU_FLAGS` this CPU has, space-separated."""
    flags = (_cpuinfo("flags") or "").split()
    return " ".join(f for f in CPU_FLAGS if f in flags) or "none of " + " ".join(CPU_FLAGS)


def median_seconds(fn: Callable[[], object], *, repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def memory_mb(pid: int | str = "self", *, field: str = "VmRSS") -> float:
    """A process's memory from /proc/PID/status in MiB: ``VmRSS`` (resident now) or ``VmHWM`` (peak resident).

    NaN where /proc has no such line (not Linux)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return float("nan")
    for line in lines:
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")
