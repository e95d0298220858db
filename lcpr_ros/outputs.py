"""Loop candidates -> std_msgs/Float64MultiArray, in the layouts other programs rely on.

``~/loop_closure``: data = [query_stamp_s, match_stamp_s] of the result's loop (the
verified candidate with the best fitness; with ``verify.enabled`` false, the nearest
descriptor), the input LIO-SAM's ``lio_loop/loop_closure_detection`` expects.
``~/candidates``: one row per candidate, verified or not; ``layout.dim[0]`` =
("candidates", rows, rows * cols), ``layout.dim[1]`` = (comma-separated column names,
cols, cols) (:mod:`ros_common.tables`). ``tx..qw`` is match_T_query (the query keyframe's LiDAR frame in the match
keyframe's LiDAR frame), ``cov_0..cov_35`` its 6 x 6 covariance row-major over
(x, y, z, roll, pitch, yaw) as in geometry_msgs/PoseWithCovariance; NaN where the
candidate was not registered. ``query_session``, ``match_session`` (the last columns): codes
into the session names of ``~/sessions`` (std_msgs/String, a JSON list, code = index, latched;
:class:`ros_common.tables.SessionTable`); NaN when the writer kept no table.
``~/keyframes`` (std_msgs/UInt8MultiArray): each keyframe as the peer robots take it (:func:`keyframe_msg`).
``~/up`` (geometry_msgs/Vector3Stamped): a keyframe's up direction measured from its walls
(:mod:`lcpr_core.up`), a unit vector in the cloud's frame at the keyframe's stamp, for ``lcpr_backend``.
"""
from __future__ import annotations

import array
import dataclasses
import math
from collections.abc import Collection

from geometry_msgs.msg import Vector3Stamped
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout, UInt8MultiArray

from lcpr_core.detector import Candidate, Result
from msg_tools.build import build_message
from msg_tools.types import sec_to_stamp
from ros_common.inputs import KEYFRAME_FORMAT
from ros_common.tables import (
    COVARIANCE_COLUMNS,
    POSE_COLUMNS,
    SESSION_COLUMNS,
    SessionTable,
    parse_candidates,
    parse_sessions,
    pose_covariance_cells,
    row_covariance,
    row_pose,
    row_sessions,
    sessions_msg,
    table_msg,
)

__all__ = ["CANDIDATE_COLUMNS", "SessionTable", "candidates_msg", "keyframe_msg", "loop_closure_msg",
           "parse_candidates", "parse_sessions", "row_covariance", "row_pose", "row_sessions", "sessions_msg", "up_msg"]

CANDIDATE_COLUMNS: tuple[str, ...] = (
    "query_stamp", "match_stamp", "query_id", "match_id", "distance", "rank", "degraded",
    "verified", "fitness", *POSE_COLUMNS, *COVARIANCE_COLUMNS, *SESSION_COLUMNS,
)


def _row(c: Candidate, sessions: SessionTable | None = None) -> list[float]:
    codes = ([math.nan, math.nan] if sessions is None
             else [float(sessions.code(c.query_session)), float(sessions.code(c.match_session))])
    return [c.query_stamp, c.match_stamp, float(c.query_id), float(c.match_id), c.distance, float(c.rank),
            float(c.degraded), float(c.verified), float(c.fitness),
            *pose_covariance_cells(c.match_T_query, c.covariance), *codes]


def loop_closure_msg(result: Result, *, skip_sessions: Collection[str] = ()) -> Float64MultiArray | None:
    """``~/loop_closure`` of a result: its loop among the candidates whose match is of none of ``skip_sessions``
    (a peer robot's keyframes: their stamps are of its clock, which a LIO-SAM reading this topic does not know)."""
    kept = [c for c in result.candidates if c.match_session not in skip_sessions]
    best = dataclasses.replace(result, candidates=kept).loop if len(kept) < len(result.candidates) else result.loop
    if best is None:
        return None
    return Float64MultiArray(data=[float(best.query_stamp), float(best.match_stamp)])


def keyframe_msg(record: bytes) -> UInt8MultiArray:
    """``~/keyframes``: one keyframe record (:func:`lcpr_core.detector.encode_peer_keyframe`) in a
    std_msgs/UInt8MultiArray whose ``layout.dim[0]`` = (``lcpr_keyframe/1``, bytes, bytes)."""
    layout = MultiArrayLayout(dim=[MultiArrayDimension(label=KEYFRAME_FORMAT, size=len(record), stride=len(record))],
                              data_offset=0)
    return UInt8MultiArray(layout=layout, data=array.array("B", record))


def up_msg(result: Result, frame_id: str) -> Vector3Stamped | None:
    """``~/up``: the keyframe's up direction from its walls (unit vector in the cloud's frame, at its stamp)."""
    if result.up is None:
        return None
    stamp = sec_to_stamp(float(result.stamp))
    x, y, z = (float(v) for v in result.up)
    return build_message("geometry_msgs/msg/Vector3Stamped", {
        "header": {"stamp": {"sec": stamp.sec, "nanosec": stamp.nanosec}, "frame_id": frame_id},
        "vector": {"x": x, "y": y, "z": z}}, msg_type=Vector3Stamped)


def candidates_msg(result: Result, sessions: SessionTable | None = None) -> Float64MultiArray | None:
    """``~/candidates`` of a result (None without candidates); ``sessions`` gives the session codes (a name new
    to it gets the next code: publish :func:`sessions_msg` of its names when it grew)."""
    if not result.candidates:
        return None
    return table_msg([_row(c, sessions) for c in result.candidates], CANDIDATE_COLUMNS)
