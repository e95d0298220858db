"""The candidate table both nodes publish on ``~/candidates``: a std_msgs/Float64MultiArray whose
``layout.dim[0]`` = ("candidates", rows, rows * cols) and ``layout.dim[1]`` = (comma-separated column
names, cols, cols), so a reader finds every column by name whichever node wrote it.

Sessions travel as numbers: the ``query_session`` / ``match_session`` columns hold codes into the
node's session table, published latched on ``~/sessions`` as a std_msgs/String holding a JSON list of
names (code = index; the list only grows, so a code never changes its name)."""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout, String

from msg_tools.geometry import matrix_to_quaternion, quaternion_to_matrix

#: match_T_query as translation + quaternion, and its 6 x 6 covariance row-major: the same names in both nodes
POSE_COLUMNS: tuple[str, ...] = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
COVARIANCE_COLUMNS: tuple[str, ...] = tuple(f"cov_{i}" for i in range(36))


def table_msg(rows: Sequence[Sequence[float]], columns: Sequence[str], label: str = "candidates") -> Float64MultiArray:
    """Rows x columns -> Float64MultiArray with the column names in ``layout.dim[1].label``."""
    n, cols = len(rows), len(columns)
    for i, row in enumerate(rows):
        if len(row) != cols:
            raise ValueError(f"row {i} has {len(row)} values; the table has {cols} columns")
    layout = MultiArrayLayout(dim=[
        MultiArrayDimension(label=label, size=n, stride=n * cols),
        MultiArrayDimension(label=",".join(columns), size=cols, stride=cols),
    ], data_offset=0)
    return Float64MultiArray(layout=layout, data=[float(v) for row in rows for v in row])


def pose_covariance_cells(match_T_query: np.ndarray | None, covariance: np.ndarray | None) -> list[float]:
    """The POSE_COLUMNS and COVARIANCE_COLUMNS cells of a candidate (NaN where it has no pose or covariance)."""
    if match_T_query is None:
        pose = [math.nan] * len(POSE_COLUMNS)
    else:
        T = np.asarray(match_T_query, np.float64)
        pose = [*T[:3, 3].tolist(), *matrix_to_quaternion(T[:3, :3]).tolist()]
    cov = [math.nan] * 36 if covariance is None else np.asarray(covariance, np.float64).reshape(36).tolist()
    return [*pose, *cov]


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
    return [dict(zip(names, data[r * cols:(r + 1) * cols], strict=True)) for r in range(rows)]


def row_pose(row: Mapping[str, float]) -> np.ndarray | None:
    """match_T_query (4 x 4) of a parsed ``~/candidates`` row; None when the candidate was not registered."""
    values = [row.get(name, math.nan) for name in POSE_COLUMNS]
    if not np.isfinite(values).all():
        return None
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(np.array(values[3:]))
    T[:3, 3] = values[:3]
    return T


def row_covariance(row: Mapping[str, float]) -> np.ndarray | None:
    """The 6 x 6 covariance (x, y, z, roll, pitch, yaw) of a parsed ``~/candidates`` row; None when absent."""
    values = [row.get(name, math.nan) for name in COVARIANCE_COLUMNS]
    return np.array(values).reshape(6, 6) if np.isfinite(values).all() else None


#: the session columns of ``~/candidates``: codes into the ``~/sessions`` table
SESSION_COLUMNS: tuple[str, ...] = ("query_session", "match_session")


class SessionTable:
    """Session names and the codes ``~/candidates`` carries for them (code = index), append-only."""

    def __init__(self) -> None:
        self.names: list[str] = []
        self._codes: dict[str, int] = {}

    def __len__(self) -> int:
        return len(self.names)

    def code(self, name: str) -> int:
        """The code of ``name``, a new one (the next index) the first time it is asked for."""
        found = self._codes.get(name)
        if found is None:
            found = self._codes[name] = len(self.names)
            self.names.append(name)
        return found


def sessions_msg(names: Sequence[str]) -> String:
    """``~/sessions``: the session names as a JSON list (code = index)."""
    return String(data=json.dumps(list(names)))


def parse_sessions(msg: Any) -> list[str]:
    """A ``~/sessions`` message -> the session names, code = index (ValueError when it is not a list of str)."""
    try:
        names = json.loads(str(msg.data))
    except json.JSONDecodeError as err:
        raise ValueError(f"~/sessions holds {str(msg.data)[:80]!r}, not JSON: {err}") from err
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"~/sessions holds {str(msg.data)[:80]!r}; expected a JSON list of session names")
    return names


def row_sessions(row: Mapping[str, float], names: Sequence[str]) -> tuple[str | None, str | None]:
    """(query session, match session) of a parsed ``~/candidates`` row by the ``~/sessions`` table ``names``;
    None for a column the row lacks, NaN, or a code the table does not hold yet (a newer table is on its way)."""
    def name(column: str) -> str | None:
        value = row.get(column, math.nan)
        if not math.isfinite(value) or value != int(value) or not 0 <= int(value) < len(names):
            return None
        return names[int(value)]
    return name(SESSION_COLUMNS[0]), name(SESSION_COLUMNS[1])
