"""~/candidates rows written by the node read back to the same pose and covariance."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("std_msgs")

from lcpr_core.detector import Candidate, Result  # noqa: E402
from lcpr_ros.outputs import CANDIDATE_COLUMNS, candidates_msg, parse_candidates, row_covariance, row_pose  # noqa: E402


def test_a_candidate_row_reads_back_to_its_relative_pose_and_covariance() -> None:
    yaw = math.radians(130.0)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = (1.5, -2.0, 0.25)
    cov = np.diag([0.01, 0.02, 0.03, 0.004, 0.005, 0.006])
    cov[0, 5] = cov[5, 0] = 0.001
    verified = Candidate(7, 3, 40.0, 1.0, 0.3, 0, None, False, verified=True, fitness=0.6, match_T_query=T,
                         covariance=cov, verification="accepted")
    unregistered = Candidate(7, 4, 40.0, 2.0, 0.4, 1, None, False, verification="no cloud")
    rows = parse_candidates(candidates_msg(Result(40.0, 7, "keyframe", [verified, unregistered])))
    assert list(rows[0]) == list(CANDIDATE_COLUMNS)
    pose, covariance = row_pose(rows[0]), row_covariance(rows[0])
    assert pose is not None and covariance is not None
    assert np.allclose(pose, T) and np.allclose(covariance, cov)
    assert rows[0]["verified"] == 1.0 and rows[0]["fitness"] == pytest.approx(0.6)
    assert row_pose(rows[1]) is None and row_covariance(rows[1]) is None and rows[1]["verified"] == 0.0
