"""The maintained measuring tools (benchmarks/tools/) run as a user runs them: each prints its help.

Every script there is started in a subprocess with this interpreter (the venv, the installed package)
and ``--help``, from another working directory: it must exit 0 with a usage line, so a script that no
longer starts or parses its options shows up in CI although no tool runs for real here. The tools read
their arguments before importing torch or the package (a fraction of a second each); the imports that
follow are mypy's to check (setup.cfg lists benchmarks).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[2] / "benchmarks" / "tools"


def test_the_tools_folder_holds_the_maintained_tools() -> None:
    assert {p.stem for p in TOOLS.glob("*.py")} >= {"lcpr_forward", "map_search", "node_soak", "verify_cost"}


@pytest.mark.parametrize("tool", sorted(TOOLS.glob("*.py")), ids=lambda p: p.stem)
def test_every_maintained_tool_prints_its_help(tool: Path, tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(tool), "--help"], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith(f"usage: {tool.name}"), done.stdout[:500]
