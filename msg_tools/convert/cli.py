"""Shared command-line pieces of the converters: common options and the final summary."""
from __future__ import annotations

import argparse
from collections.abc import Iterable
from pathlib import Path

from ..bags import bag_summary
from ..bags.writer import STORAGES


def add_output_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="rosbag2 folder to create")
    parser.add_argument("--storage", choices=sorted(STORAGES), default="sqlite3", help="rosbag2 storage plugin")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag at --out")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def print_summary(out: Path, lines: Iterable[str]) -> None:
    for line in lines:
        print(line)
    print(bag_summary(out).format())
