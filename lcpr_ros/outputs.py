"""Loop candidates -> std_msgs/Float64MultiArray, in the layouts other programs rely on.

``~/loop_closure``: data = [query_stamp_s, match_stamp_s] of the result's loop (the
verified candidate with the best fitness; with ``verify.enabled`` false, the nearest
descriptor), the input LIO-SAM's ``lio_loop/loop_closure_detection`` expects.
``~/candidates``: one row per candidate, verified or not; ``layout.dim[0]`` =
("candidates", rows, rows * cols), ``layout.dim[1]`` = (comma-separated column names,
cols, cols) (:mod:`ros_common.tables`). ``tx..qw`` is match_T_query (the query keyframe's LiDAR frame in the match
keyframe's LiDAR frame), ``cov_0..cov_35`` its 6 x 6 covariance row-major over
(x, y, z, roll, pitch, yaw) as in geometry_msgs/PoseWithCovariance; NaN where the
candidate was not registered.
``~/up`` (geometry_msgs/Vector3Stamped): a keyframe's up direction measured from its walls
(:mod:`lcpr_core.up`), a unit vector in the cloud's frame at the keyframe's stamp, for ``lcpr_backend``.
"""
from __future__ import annotations

from geometry_msgs.msg import Vector3Stamped
from std_msgs.msg import Float64MultiArray

from lcpr_core.detector import Candidate, Result
from msg_tools.build import build_message
from msg_tools.types import sec_to_stamp
from ros_common.tables import (
    COVARIANCE_COLUMNS,
    POSE_COLUMNS,
    parse_candidates,
    pose_covariance_cells,
    row_covariance,
    row_pose,
    table_msg,
)

__all__ = ["CANDIDATE_COLUMNS", "candidates_msg", "loop_closure_msg", "parse_candidates", "row_covariance", "row_pose",
           "up_msg"]

CANDIDATE_COLUMNS: tuple[str, ...] = (
    "query_stamp", "match_stamp", "query_id", "match_id", "distance", "rank", "degraded",
    "verified", "fitness", *POSE_COLUMNS, *COVARIANCE_COLUMNS,
)


def _row(c: Candidate) -> list[float]:
    return [c.query_stamp, c.match_stamp, float(c.query_id), float(c.match_id), c.distance, float(c.rank),
            float(c.degraded), float(c.verified), float(c.fitness),
            *pose_covariance_cells(c.match_T_query, c.covariance)]


def loop_closure_msg(result: Result) -> Float64MultiArray | None:
    best = result.loop
    if best is None:
        return None
    return Float64MultiArray(data=[float(best.query_stamp), float(best.match_stamp)])


def up_msg(result: Result, frame_id: str) -> Vector3Stamped | None:
    """``~/up``: the keyframe's up direction from its walls (unit vector in the cloud's frame, at its stamp)."""
    if result.up is None:
        return None
    stamp = sec_to_stamp(float(result.stamp))
    x, y, z = (float(v) for v in result.up)
    return build_message("geometry_msgs/msg/Vector3Stamped", {
        "header": {"stamp": {"sec": stamp.sec, "nanosec": stamp.nanosec}, "frame_id": frame_id},
        "vector": {"x": x, "y": y, "z": z}}, msg_type=Vector3Stamped)


def candidates_msg(result: Result) -> Float64MultiArray | None:
    if not result.candidates:
        return None
    return table_msg([_row(c) for c in result.candidates], CANDIDATE_COLUMNS)
