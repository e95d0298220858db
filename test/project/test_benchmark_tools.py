"""The maintained measuring tools (benchmarks/tools/) run as a user runs them: each prints its help.

Every script there is started in a subprocess with this interpreter (the venv, the installed package)
and ``--help``, from another working directory: it must exit 0 with a usage line, so a script that no
longer starts or parses its options shows up in CI although most tools do not run for real here (verify_cost's
profile does, on its smallest drive). The tools read their arguments before importing torch or the package (a
fraction of a second each); the imports that follow are mypy's to check (setup.cfg lists benchmarks).
"""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
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


def _tool_module(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"{name}_tool", TOOLS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_a_folder_with_one_scan_more_than_poses_ends_the_tool_with_one_error_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "walk"
    folder.mkdir()
    for k in range(3):
        np.zeros((10, 4), np.float32).tofile(folder / f"{k:06d}.bin")  # KITTI layout: x, y, z, reflectance
    np.savetxt(folder / "poses.txt", np.tile(np.eye(4)[:3].reshape(1, 12), (2, 1)))
    tool = _tool_module("lidar_loops_compare")
    status = tool.main(["--only-folders", "--folder", str(folder), "--mc-map-length", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert err == [f"lidar_loops_compare.py: error: 3 scans but 2 lines in {folder / 'poses.txt'}, and the scan "
                   "names (000000.bin .. 000002.bin) are not line numbers of it"]
    assert not (tmp_path / "out").exists()


def test_every_maintained_tool_ends_on_bad_input_through_the_shared_helper() -> None:
    """One way for all: each tool's main is wrapped by lcpr_common.cli.tool_main."""
    unwrapped = [tool.name for tool in sorted(TOOLS.glob("*.py")) if "@tool_main\ndef main(" not in tool.read_text()]
    assert unwrapped == []


def test_verify_cost_profile_names_every_stage_and_its_shares_add_up(capsys: pytest.CaptureFixture[str]) -> None:
    """--profile on the smallest drive with a revisit: a row per stage, wall and CPU shares summing to 100 %,
    the registrations charged, and the worker processes' line; the verdicts still match (exit status 0)."""
    tool = _tool_module("verify_cost")
    status = tool.main(["--frames", "110", "--queries", "1", "--candidates", "2", "--repeats", "2",
                        "--processes", "1", "--profile"])
    out = capsys.readouterr().out
    assert status == 0, out
    rows = {cells[0]: cells[1:] for line in out.splitlines() if line.startswith("| ") and "---" not in line
            for cells in [[c.strip() for c in line.strip("|").split("|")]]}
    assert list(rows) == ["stage", *tool.STAGES, "total"], out
    stages = [rows[s] for s in tool.STAGES]
    for column in (1, 3):  # share of wall, share of CPU
        assert sum(float(r[column].rstrip(" %")) for r in stages) == pytest.approx(100.0, abs=0.5), out
    assert all(float(r[0]) >= 0.0 and float(r[2]) >= 0.0 for r in stages), out
    assert float(rows["coarse GICP"][0]) > 0.0 and float(rows["prepare (query)"][0]) > 0.0, out
    assert "over 1 worker processes (seen from the parent" in out and "submap stitching: not exercised" in out, out
