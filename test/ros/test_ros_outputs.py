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


def test_candidate_rows_name_their_sessions_through_the_latched_session_table() -> None:
    from lcpr_ros.outputs import SessionTable, parse_sessions, row_sessions, sessions_msg

    table = SessionTable()
    own = Candidate(7, 3, 40.0, 1.0, 0.3, 0, None, False, query_session="robot1", match_session="robot1")
    peer = Candidate(7, 9, 40.0, 5.0, 0.4, 1, None, False, query_session="robot1", match_session="robot2")
    rows = parse_candidates(candidates_msg(Result(40.0, 7, "keyframe", [own, peer]), table))
    assert list(CANDIDATE_COLUMNS[-2:]) == ["query_session", "match_session"]  # appended at the end
    names = parse_sessions(sessions_msg(table.names))
    assert names == ["robot1", "robot2"]
    assert [row_sessions(r, names) for r in rows] == [("robot1", "robot1"), ("robot1", "robot2")]
    assert row_sessions(rows[1], names[:1]) == ("robot1", None)  # a code the reader's table lacks yet
    bare = parse_candidates(candidates_msg(Result(40.0, 7, "keyframe", [own])))  # no table: NaN codes
    assert row_sessions(bare[0], names) == (None, None)


def test_a_session_table_that_is_not_a_json_list_of_names_is_refused() -> None:
    from std_msgs.msg import String

    from lcpr_ros.outputs import parse_sessions

    for bad in ("{", '{"a": 1}', "[1, 2]"):
        with pytest.raises(ValueError, match="sessions"):
            parse_sessions(String(data=bad))
