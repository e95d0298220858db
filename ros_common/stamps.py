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
    """Accepts strictly increasing stamps on one stream; names why another is refused.

    A stamp more than ``jump_back_ns`` older than the newest (> 0; a bag replayed again or
    with ``--loop``, a simulator reset) is accepted as the start of a new timeline:
    ``jumped_from`` then holds the newest stamp before it, until the next check.
    """

    def __init__(self, jump_back_ns: int = 0) -> None:
        self.last: int | None = None
        self.jump_back_ns = jump_back_ns
        self.jumped_from: int | None = None

    def check(self, ns: int) -> str | None:
        """None (accepted, becomes the last stamp) or the reason it is refused."""
        self.jumped_from = None
        if self.last is not None:
            if ns == self.last:
                return DUPLICATE
            if ns < self.last:
                if not 0 < self.jump_back_ns < self.last - ns:
                    return OUT_OF_ORDER
                self.jumped_from = self.last
        self.last = ns
        return None
