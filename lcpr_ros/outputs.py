"""Loop candidates -> std_msgs/Float64MultiArray, in the layouts other programs rely on.

``~/loop_closure``: data = [query_stamp_s, match_stamp_s] of the best candidate (the
input LIO-SAM's ``lio_loop/loop_closure_detection`` expects). ``~/candidates``: one
row per candidate; ``layout.dim[0]`` = ("candidates", rows, rows * cols),
``layout.dim[1]`` = (comma-separated column names, cols, cols).
"""
from __future__ import annotations

from typing import Any

from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout

from lcpr_core.detector import Candidate, Result

CANDIDATE_COLUMNS: tuple[str, ...] = (
    "query_stamp", "match_stamp", "query_id", "match_id", "distance", "rank", "degraded",
)


def _row(c: Candidate) -> list[float]:
    return [c.query_stamp, c.match_stamp, float(c.query_id), float(c.match_id), c.distance, float(c.rank),
            float(c.degraded)]


def loop_closure_msg(result: Result) -> Float64MultiArray | None:
    best = result.loop
    if best is None:
        return None
    return Float64MultiArray(data=[float(best.query_stamp), float(best.match_stamp)])


def candidates_msg(result: Result) -> Float64MultiArray | None:
    if not result.candidates:
        return None
    rows, cols = len(result.candidates), len(CANDIDATE_COLUMNS)
    layout = MultiArrayLayout(dim=[
        MultiArrayDimension(label="candidates", size=rows, stride=rows * cols),
        MultiArrayDimension(label=",".join(CANDIDATE_COLUMNS), size=cols, stride=cols),
    ], data_offset=0)
    data = [value for c in result.candidates for value in _row(c)]
    return Float64MultiArray(layout=layout, data=data)


def parse_candidates(msg: Any) -> list[dict[str, float]]:
    """A ``~/candidates`` message -> one dict per row, keyed by the column names it carries."""
    dims = msg.layout.dim
    if len(dims) != 2:
        raise ValueError(f"expected a 2-D layout (candidates x columns), got {len(dims)} dimensions")
    names = dims[1].label.split(",")
    rows, cols = int(dims[0].size), int(dims[1].size)
    if cols != len(names) or len(msg.data) < msg.layout.data_offset + rows * cols:
        raise ValueError(f"layout {rows} x {cols} with columns {names} does not fit {len(msg.data)} values")
    data = list(msg.data)[msg.layout.data_offset:]
    return [dict(zip(names, data[r * cols:(r + 1) * cols])) for r in range(rows)]
