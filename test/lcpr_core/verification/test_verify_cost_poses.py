"""verify_cost.py counts accepted candidates by whether their pose is right, and names the wrong ones."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import numpy as np

from lcpr_core.verification import Verification

TOOL = Path(__file__).resolve().parents[3] / "benchmarks" / "tools" / "verify_cost.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("verify_cost_tool", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_an_accepted_candidate_counts_as_right_only_with_its_pose_and_a_refused_one_not_at_all() -> None:
    poses = np.stack([_at(0.0), _at(8.0), _at(11.0)])  # LiDAR poses along x
    verdicts = {
        (2, 0): Verification(True, "accepted", _at(11.2), 0.6),  # truth: 11 m; 0.2 m off: right
        (2, 1): Verification(True, "accepted", np.eye(4), 0.5),  # slid onto the query: 3 m off
        (1, 0): Verification(False, "low overlap", np.eye(4), 0.1),  # refused: not counted
    }
    right, wrong = _tool()._pose_check(verdicts, poses)
    assert right == 1
    assert len(wrong) == 1 and wrong[0].startswith("2-1: 3.0 m apart, pose off by 3.00 m")
