"""Matches -> std_msgs/Float64MultiArray in lcpr_node's layouts (``lcpr_ros.outputs.parse_candidates`` reads them).

``~/loop_closure``: data = [query_stamp_s, match_stamp_s] of the best candidate.
``~/candidates``: one row per candidate; ``layout.dim[0]`` = ("candidates", rows, rows * cols),
``layout.dim[1]`` = (comma-separated column names, cols, cols). Columns: see CANDIDATE_COLUMNS;
``distance`` is 1 - probability (the network's match probability; lower is better, in [0, 1]),
``query_id`` the camera frame number of the query frame, ``match_id`` the scan's map id,
``yaw_deg`` the direction (LiDAR frame) of the scan slice the camera matched.
"""
from __future__ import annotations

from collections.abc import Sequence

from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout

from lcpr_core.vseq2pc.retrieval import ScanMatch

CANDIDATE_COLUMNS: tuple[str, ...] = (
    "query_stamp", "match_stamp", "query_id", "match_id", "distance", "rank", "probability", "logit", "yaw_deg",
)


def candidate_rows(query_stamp: float, query_id: int, matches: Sequence[ScanMatch]) -> list[list[float]]:
    return [[float(query_stamp), m.stamp, float(query_id), float(m.id), 1.0 - m.probability, float(m.rank),
             m.probability, m.logit, m.relative_yaw_deg] for m in matches]


def table_msg(rows: Sequence[Sequence[float]], columns: Sequence[str] = CANDIDATE_COLUMNS,
              label: str = "candidates") -> Float64MultiArray:
    """Rows x columns -> Float64MultiArray with the column names in ``layout.dim[1].label``."""
    n, cols = len(rows), len(columns)
    layout = MultiArrayLayout(dim=[
        MultiArrayDimension(label=label, size=n, stride=n * cols),
        MultiArrayDimension(label=",".join(columns), size=cols, stride=cols),
    ], data_offset=0)
    return Float64MultiArray(layout=layout, data=[float(v) for row in rows for v in row])


def loop_closure_msg(query_stamp: float, best: ScanMatch) -> Float64MultiArray:
    return Float64MultiArray(data=[float(query_stamp), float(best.stamp)])
