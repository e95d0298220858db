"""Shared command-line pieces of the converters: common options and the final summary."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Protocol

from ..bags import bag_summary
from ..bags.writer import STORAGES
from ..errors import MsgToolsError


class Report(Protocol):
    def lines(self) -> list[str]: ...


def add_output_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="rosbag2 folder to create")
    parser.add_argument("--storage", choices=sorted(STORAGES), default="sqlite3", help="rosbag2 storage plugin")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag at --out")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def print_summary(out: Path, lines: Iterable[str]) -> None:
    for line in lines:
        print(line)
    print(bag_summary(out).format())


def run_conversion(prog: str, out: Path, convert: Callable[[], Report]) -> int:
    """A converter's exit status: 0 with the report and the bag's summary printed, or 2 with the refusal on
    stderr (a converter refuses bad input with a MsgToolsError naming it)."""
    try:
        report = convert()
    except MsgToolsError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return 2
    print_summary(out, report.lines())
    return 0
