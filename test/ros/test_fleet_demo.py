"""The fleet demo runs end to end over DDS: two detectors in /robot1 and /robot2, robot1's back end merging both."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("gtsam")
pytest.importorskip("rclpy")


@pytest.mark.slow
def test_the_fleet_demo_anchors_robot2_in_robot1s_map_by_inter_robot_loops_over_dds(tmp_path: Path) -> None:
    out = tmp_path / "fleet"
    run = subprocess.run([sys.executable, "-m", "lcpr_ros.demo", "--fleet", "--frames", "30", "--out", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    report = json.loads((out / "fleet_report.json").read_text())
    loops = report["inter_robot_loops"]
    # inter-robot rows reached robot1's candidates naming both sessions, and the back end took them
    assert loops["rows"] > 0 and loops["in_graph"] > 0, loops
    assert report["backend"]["peer sessions anchored"] == "robot2", report["backend"]
    assert report["ate_m"]["robot2"] is not None and report["merged_ate_m"] < 2.0, report
    assert report["keyframes"] > 0 and report["keyframe_bytes_mean"] > 0
    assert (out / "fleet.png").read_bytes()[:4] == b"\x89PNG"
