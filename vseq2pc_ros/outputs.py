"""Matches -> std_msgs/Float64MultiArray in lcpr_node's layouts (``ros_common.tables.parse_candidates`` reads them).

``~/loop_closure``: data = [query_stamp_s, match_stamp_s] of the query's loop: the verified candidate with the
best fitness (``verify.enabled``, the default; none when no candidate passed), else the most probable one.
``~/candidates``: one row per candidate, in the table layout of :mod:`ros_common.tables`. Columns: see
CANDIDATE_COLUMNS;
``distance`` is 1 - probability (the network's match probability; lower is better, in [0, 1]),
``query_id`` the camera frame number of the query frame, ``match_id`` the scan's map id,
``yaw_deg`` the direction (LiDAR frame) of the scan slice the camera matched; ``verified``, ``fitness``,
``tx..qw`` (match_T_query: the query camera's pose in the scan's LiDAR frame) and ``cov_0..cov_35`` (its
6 x 6 covariance, row-major over x, y, z, roll, pitch, yaw) are lcpr_node's columns of the same names, NaN
where the candidate was not registered. Rows come verified first (best fitness first), then by ``rank``.
"""
from __future__ import annotations

from collections.abc import Sequence

from std_msgs.msg import Float64MultiArray

from lcpr_core.vseq2pc.retrieval import ScanMatch
from ros_common.tables import COVARIANCE_COLUMNS, POSE_COLUMNS, pose_covariance_cells, table_msg

CANDIDATE_COLUMNS: tuple[str, ...] = (
    "query_stamp", "match_stamp", "query_id", "match_id", "distance", "rank", "probability", "logit", "yaw_deg",
    "verified", "fitness", *POSE_COLUMNS, *COVARIANCE_COLUMNS,
)


def _row(query_stamp: float, query_id: int, m: ScanMatch) -> list[float]:
    return [float(query_stamp), m.stamp, float(query_id), float(m.id), 1.0 - m.probability, float(m.rank),
            m.probability, m.logit, m.relative_yaw_deg, float(m.verified), float(m.fitness),
            *pose_covariance_cells(m.match_T_query, m.covariance)]


def candidates_msg(query_stamp: float, query_id: int, matches: Sequence[ScanMatch]) -> Float64MultiArray:
    """One query's candidates as the ``~/candidates`` table (:mod:`ros_common.tables`)."""
    return table_msg([_row(query_stamp, query_id, m) for m in matches], CANDIDATE_COLUMNS)


def loop_closure_msg(query_stamp: float, best: ScanMatch) -> Float64MultiArray:
    return Float64MultiArray(data=[float(query_stamp), float(best.stamp)])
