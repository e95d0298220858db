"""Print what a rosbag2 holds (``msg_tools_baginfo``; ``python -m msg_tools.convert.baginfo``)."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ..bags import bag_summary
from ..errors import MsgToolsError


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="msg_tools_baginfo",
                                     description="Topics, types, counts and duration of rosbag2 folders.")
    parser.add_argument("bags", nargs="+", type=Path, help="rosbag2 folders (sqlite3 or mcap)")
    args = parser.parse_args(argv)
    status = 0
    for index, bag in enumerate(args.bags):
        if index:
            print()
        try:
            print(bag_summary(bag).format())
        except MsgToolsError as err:
            print(f"msg_tools_baginfo: error: {err}", file=sys.stderr)
            status = 2
    return status


if __name__ == "__main__":
    raise SystemExit(main())
