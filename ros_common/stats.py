"""Thread-safe counters, rates, latency windows and once-per-cause warnings for diagnostics."""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np


class Counts:
    """A Counter shared between the callback thread and the worker."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._counts[key] += n

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    def __getitem__(self, key: str) -> int:
        with self._lock:
            return self._counts[key]


class RateMeter:
    """Messages per second over the last ``window`` seconds of wall time, per stream."""

    def __init__(self, window: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
        self._window = window
        self._clock = clock
        self._lock = threading.Lock()
        self._times: dict[str, deque[float]] = {}
        self.totals: Counter[str] = Counter()

    def tick(self, stream: str) -> None:
        now = self._clock()
        with self._lock:
            times = self._times.setdefault(stream, deque())
            times.append(now)
            self.totals[stream] += 1
            self._trim(times, now)

    def _trim(self, times: deque[float], now: float) -> None:
        while times and now - times[0] > self._window:
            times.popleft()

    def rates(self) -> dict[str, float]:
        now = self._clock()
        out = {}
        with self._lock:
            for stream, times in self._times.items():
                self._trim(times, now)
                out[stream] = len(times) / self._window
        return out


class Window:
    """The latest N samples (seconds) and their percentiles."""

    def __init__(self, size: int) -> None:
        self._lock = threading.Lock()
        self._values: deque[float] = deque(maxlen=size)
        self.count = 0

    def add(self, value: float) -> None:
        with self._lock:
            self._values.append(value)
            self.count += 1

    def percentiles(self, *qs: float) -> list[float] | None:
        with self._lock:
            if not self._values:
                return None
            values = np.fromiter(self._values, dtype=np.float64)
        return [float(v) for v in np.percentile(values, qs)]


class WarnOnce:
    """Logs a warning the first time each cause is seen; later ones are only counted."""

    def __init__(self, warn: Callable[[str], object]) -> None:
        self._warn = warn
        self._lock = threading.Lock()
        self._seen: set[str] = set()
        self.logged = 0  # warnings actually logged
        self.suppressed = 0  # repeats not logged

    def __call__(self, cause: str, detail: str) -> None:
        with self._lock:
            if cause in self._seen:
                self.suppressed += 1
                return
            self._seen.add(cause)
            self.logged += 1
        self._warn(f"{cause}: {detail} (warned once; counts in /diagnostics)")

    @property
    def causes(self) -> list[str]:
        with self._lock:
            return sorted(self._seen)


class NodeStats:
    """The counters every node reports in /diagnostics: warnings (once per cause), dropped inputs,
    repaired inputs (fixes), decisions, input rates, and latency / model-time windows."""

    def init_stats(self, warn: Callable[[str], object], *, window: int) -> None:
        self.warnings = WarnOnce(warn)
        self.drops, self.fixes, self.decisions = Counts(), Counts(), Counts()
        self.rates = RateMeter()
        self.latency = Window(window)  # s from a frame's arrival to its result
        self.model_time = Window(window)  # s of the worker's work per item
        self.loops = 0  # loop closures published
