"""What a rosbag2 holds: topics, types, message counts, time span."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..types import NS_PER_S
from .open import open_bag, storage_of


@dataclass(frozen=True)
class TopicSummary:
    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagSummary:
    path: Path
    storage: str
    topics: tuple[TopicSummary, ...]
    message_count: int
    start_ns: int | None  # first log time, None for an empty bag
    end_ns: int | None  # last log time

    @property
    def start(self) -> float | None:
        return None if self.start_ns is None else self.start_ns / NS_PER_S

    @property
    def end(self) -> float | None:
        return None if self.end_ns is None else self.end_ns / NS_PER_S

    @property
    def duration(self) -> float:
        """Seconds from the first to the last message."""
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / NS_PER_S

    def format(self) -> str:
        lines = [
            f"bag:       {self.path}",
            f"storage:   {self.storage}",
            f"messages:  {self.message_count}",
            f"duration:  {self.duration:.3f} s"
            + (f" ({_exact(self.start_ns)} .. {_exact(self.end_ns)})" if self.start_ns is not None else ""),
            "topics:",
        ]
        width = max((len(t.name) for t in self.topics), default=0)
        lines += [f"  {t.name:<{width}}  {t.count:>8}  {t.msgtype}" for t in self.topics]
        return "\n".join(lines)


def bag_summary(path: str | os.PathLike[str]) -> BagSummary:
    """Topics (sorted by name), types, counts and time span of a rosbag2 (sqlite3 or mcap)."""
    with open_bag(path) as reader:
        counts: dict[tuple[str, str], int] = {}
        for c in reader.connections:
            counts[(c.topic, c.msgtype)] = counts.get((c.topic, c.msgtype), 0) + c.msgcount
        total = reader.message_count
        start = int(reader.start_time) if total else None
        end = int(reader.end_time) - 1 if total else None  # rosbags reports the end as last + 1 ns
    topics = tuple(TopicSummary(name, msgtype, n) for (name, msgtype), n in sorted(counts.items()))
    return BagSummary(Path(path), storage_of(path), topics, total, start, end)


def _exact(ns: int | None) -> str:
    return "-" if ns is None else f"{ns // NS_PER_S}.{ns % NS_PER_S:09d}"
