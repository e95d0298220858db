"""Run the whole test suite several times in a row on a loaded machine, each run in a new order.

Evidence for "the suite passes N runs in a row with the machine loaded": ``--load`` busy
processes (default: one per core, so the tests get about half the CPU they would alone) spin
for the whole time; run 1 is reversed (pytest-reverse), the others random (pytest-randomly,
a new seed each, printed so a failure can be replayed with ``pytest --randomly-seed=...``).

    .venv/bin/python benchmarks/tools/suite_under_load.py --runs 5
    .venv/bin/python benchmarks/tools/suite_under_load.py --alone test/ros/test_ros_node.py ...   # each test by itself
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import random
import re
import subprocess
import sys
import time
from pathlib import Path

from lcpr_common.cli import tool_main

REPO = Path(__file__).resolve().parents[2]


def _spin(stop_at: float) -> None:
    x = 0
    while time.time() < stop_at:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def each_alone(files: list[Path]) -> int:
    """``pytest FILE::TEST`` for every test of ``files``, one process each: no test leans on another."""
    listed = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:randomly",
                             *map(str, files)], cwd=REPO, capture_output=True, text=True).stdout
    ids = [line for line in listed.splitlines() if "::" in line]
    failed = []
    for test_id in ids:
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:randomly",
                               test_id], cwd=REPO, capture_output=True, text=True)
        tail = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else done.stderr[-200:]
        print(f"{'ok  ' if done.returncode == 0 else 'FAIL'} {test_id}: {tail}", flush=True)
        if done.returncode != 0:
            failed.append(test_id)
    print(f"{len(ids) - len(failed)} of {len(ids)} tests passed alone")
    return 1 if failed else 0


@tool_main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--load", type=int, default=os.cpu_count() or 1, help="busy processes beside the tests")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "suite_under_load", help="each run's full output")
    parser.add_argument("--alone", nargs="+", type=Path, default=None,
                        help="instead: run every test of these files in a pytest process of its own (no load)")
    parser.add_argument("pytest_args", nargs="*", help="extra pytest arguments (after --)")
    args = parser.parse_args(argv)
    if args.alone:
        return each_alone(args.alone)

    from lcpr_core.timing import cpu_model

    print(f"{cpu_model()}, {os.cpu_count()} cores; {args.load} busy processes; {args.runs} runs", flush=True)
    stop_at = time.time() + 24 * 3600
    load = [mp.Process(target=_spin, args=(stop_at,), daemon=True) for _ in range(args.load)]
    for p in load:
        p.start()
    results = []
    try:
        for run in range(1, args.runs + 1):
            if run == 1:
                order, extra = "reversed", ["-p", "no:randomly", "--reverse"]
            else:
                seed = random.randrange(2**32)
                order, extra = f"random seed {seed}", [f"--randomly-seed={seed}"]
            start = time.monotonic()
            done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *extra,
                                   *args.pytest_args], cwd=REPO, capture_output=True, text=True)
            minutes = (time.monotonic() - start) / 60
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / f"run{run}.txt").write_text(f"{order}\n{done.stdout}\n{done.stderr}")
            tail = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else done.stderr[-300:]
            failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", done.stdout, re.M)
            results.append((run, order, done.returncode, minutes, tail, failed))
            print(f"run {run} ({order}): exit {done.returncode}, {minutes:.1f} min: {tail}", flush=True)
            for name in failed:
                print(f"    {name}", flush=True)
    finally:
        for p in load:
            p.terminate()
    passed = sum(r[2] == 0 for r in results)
    print(f"{passed} of {len(results)} runs passed in a row" if passed == len(results)
          else f"{passed} of {len(results)} runs passed")
    return 0 if passed == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
