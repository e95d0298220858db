"""Header stamps: exact integer nanoseconds, and the per-stream order check."""
from __future__ import annotations

from typing import Any

NS_PER_S = 1_000_000_000
DUPLICATE = "duplicate stamp"
OUT_OF_ORDER = "out of order"


def stamp_ns(header: Any) -> int:
    """Header (or Time) -> integer nanoseconds."""
    stamp = getattr(header, "stamp", header)
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def to_sec(ns: int) -> float:
    return ns / NS_PER_S


class StampOrder:
    """Accepts strictly increasing stamps on one stream; names why another is refused."""

    def __init__(self) -> None:
        self.last: int | None = None

    def check(self, ns: int) -> str | None:
        """None (accepted, becomes the last stamp) or the reason it is refused."""
        if self.last is not None:
            if ns == self.last:
                return DUPLICATE
            if ns < self.last:
                return OUT_OF_ORDER
        self.last = ns
        return None
