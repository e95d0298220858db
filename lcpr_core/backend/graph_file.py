"""The back end's graph file: one .npz of plain arrays (no pickled objects), written atomically.

It holds the sessions (name, whether it defines or is placed in the map frame, its rows), the odometry, the
graph nodes with their estimates and step covariances, the accepted loops, the measured ups and the counters,
enough for :meth:`~lcpr_core.backend.PoseGraphBackend.load` to continue the graph. Reading checks the
schema, the version, every array's shape and the arrays against each other before anything is rebuilt, so a
damaged file is refused with a :class:`~lcpr_core.errors.BackendError` (reason ``"bad graph file"``) naming
what is wrong, never half-loaded.
"""
from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..atomic import atomic_path
from ..errors import BackendError, InvalidValueError
from .config import show
from .session import DEFAULT_SESSION

__all__ = ["GRAPH_SCHEMA", "GRAPH_VERSION", "SavedGraph", "SavedSession", "read_graph_file", "write_graph_file"]

GRAPH_SCHEMA = "lcpr_backend_graph"
GRAPH_VERSION = 3  # 2 added the measured ups, 3 the sessions; version 1 and 2 files (one session) still load
BAD_FILE = "bad graph file"

#: every array of a file and its shape (None: any length)
_SHAPES: dict[str, tuple[int | None, ...]] = {
    "base_T_lidar": (4, 4), "stamps": (None,), "odometry": (None, 4, 4), "node_index": (None,),
    "node_estimate": (None, 4, 4), "step_covariance": (None, 6, 6), "loop_nodes": (None, 2),
    "loop_measured": (None, 4, 4), "loop_covariance": (None, 6, 6), "loop_stamps": (None, 2),
    "loop_chi2": (None,), "up_stamps": (None,), "up_nodes": (None,), "up_body": (None, 3),
    "up_world": (3,), "waiting_nodes": (None, 2), "waiting_measured": (None, 4, 4),
    "waiting_covariance": (None, 6, 6), "waiting_stamps": (None, 2)}


@dataclass(frozen=True)
class SavedSession:
    """One session of a file: its name, its place and how many odometry rows and nodes follow in the arrays."""

    name: str
    rows: int
    nodes: int
    root: bool  # defines the map frame
    anchored: bool  # placed in the map frame
    frame: np.ndarray  # (4, 4) map_T_odom fixed when it was placed (identity otherwise)
    anchors: int = 0
    held: bool = False  # a prior map held at its estimates

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "rows": self.rows, "nodes": self.nodes, "root": self.root,
                "anchored": self.anchored, "frame": np.asarray(self.frame, np.float64).ravel().tolist(),
                "anchors": self.anchors, "held": self.held}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SavedSession:
        frame = np.array(d["frame"], np.float64)
        if frame.shape != (16,) or not np.isfinite(frame).all():
            raise InvalidValueError(f"frame of session {d.get('name')!r} is not 16 finite numbers")
        return cls(name=str(d["name"]), rows=int(d["rows"]), nodes=int(d["nodes"]), root=bool(d["root"]),
                   anchored=bool(d["anchored"]), frame=frame.reshape(4, 4), anchors=int(d.get("anchors", 0)),
                   held=bool(d.get("held", False)))


@dataclass
class SavedGraph:
    """What a graph file holds: sessions, N odometry messages, K nodes, L loops, U measured ups and the counters.

    The arrays hold the sessions one after another, in the order of ``sessions``; node indices are rows within
    their session, loop and up nodes positions among all nodes.
    """

    base_T_lidar: np.ndarray  # (4, 4) the extrinsic the loops were taken with
    stamps: np.ndarray  # (N,) odometry stamps, increasing
    odometry: np.ndarray  # (N, 4, 4) world_T_base of each odometry message
    node_index: np.ndarray  # (K,) odometry row of each graph node within its session
    node_estimate: np.ndarray  # (K, 4, 4) the graph's estimate of each node
    step_covariance: np.ndarray  # (K, 6, 6) ROS-order covariance of the step to each node (zero for a first)
    loop_nodes: np.ndarray  # (L, 2) (parent, child) nodes of each accepted loop
    loop_measured: np.ndarray  # (L, 4, 4) parent_T_child
    loop_covariance: np.ndarray  # (L, 6, 6) ROS order, in the parent node's frame
    loop_stamps: np.ndarray  # (L, 2) (query, match) stamps as given
    loop_chi2: np.ndarray  # (L,) the consistency statistic of each loop
    up_stamps: np.ndarray  # (U,) stamps of the measured ups
    up_nodes: np.ndarray  # (U,) the node each up is held on
    up_body: np.ndarray  # (U, 3) the up in that node's base frame
    up_world: np.ndarray  # (3,) the world's up in the odometry frame; NaN before the warm-up ended
    rejected: int  # loops that failed the consistency check
    redundant: int  # loops skipped as redundant
    refused: dict[str, int]  # inputs refused, by reason
    sessions: list[SavedSession]
    inter_session: dict[str, int]  # inter-session loops by outcome, anchors
    # inter-session loops not in the graph (waiting to place a session, or contradicting its anchor), as loops
    waiting_nodes: np.ndarray  # (W, 2) (parent, child) nodes
    waiting_measured: np.ndarray  # (W, 4, 4) parent_T_child
    waiting_covariance: np.ndarray  # (W, 6, 6) ROS order, in the parent node's frame
    waiting_stamps: np.ndarray  # (W, 2) (query, match) stamps as given

    def arrays(self) -> dict[str, np.ndarray]:
        """The file's arrays: the schema, the version, every array of :data:`_SHAPES` and the counters."""
        counters = {"rejected": self.rejected, "redundant": self.redundant, "refused": dict(self.refused),
                    "inter_session": dict(self.inter_session)}
        return {"schema": np.array(GRAPH_SCHEMA), "version": np.array(GRAPH_VERSION, np.int64),
                **{name: getattr(self, name) for name in _SHAPES}, "counters": np.array(json.dumps(counters)),
                "sessions": np.array(json.dumps([info.to_dict() for info in self.sessions]))}

    @classmethod
    def from_arrays(cls, data: dict[str, np.ndarray], where: str, *, base_T_lidar: np.ndarray) -> SavedGraph:
        """The graph of a file's arrays, checked (``where`` names the file in errors; ``base_T_lidar``: the
        reading back end's extrinsic, which must be the file's)."""
        def bad(what: str) -> BackendError:
            return BackendError(f"graph file {where}: {what}", reason=BAD_FILE)

        schema = str(data["schema"]) if "schema" in data else None
        if schema != GRAPH_SCHEMA:
            raise bad(f"schema {schema!r}; expected {GRAPH_SCHEMA!r} (a file written by PoseGraphBackend.save)")
        version = int(data["version"]) if "version" in data else None
        if version not in (1, 2, GRAPH_VERSION):
            raise bad(f"version {version!r}; this back end reads versions 1 to {GRAPH_VERSION}")
        if version == 1:  # before measured ups
            data = {**data, "up_stamps": np.zeros(0), "up_nodes": np.zeros(0, np.int64), "up_body": np.zeros((0, 3)),
                    "up_world": np.full(3, np.nan)}
        if version is not None and version < 3:  # before sessions: no loop waited
            data = {**data, "waiting_nodes": np.zeros((0, 2), np.int64), "waiting_measured": np.zeros((0, 4, 4)),
                    "waiting_covariance": np.zeros((0, 6, 6)), "waiting_stamps": np.zeros((0, 2))}
        for name, shape in _SHAPES.items():
            arr = data.get(name)
            if arr is None or arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape,
                                                                                                    strict=True)):
                raise bad(f"{name} of shape {None if arr is None else arr.shape}; expected {shape} (None: any)")
            if arr.dtype.kind not in "fi" or not (np.isfinite(arr).all() or name == "up_world"):
                raise bad(f"{name} holds non-numbers or NaN/inf")
        if not np.allclose(data["base_T_lidar"], base_T_lidar, atol=1e-9):
            raise bad(f"saved with base_T_lidar {show(data['base_T_lidar'])}, but this back end has "
                      f"{show(base_T_lidar)}; loops from another extrinsic would not fit its graph")
        n, k, nl = len(data["stamps"]), len(data["node_index"]), len(data["loop_nodes"])
        if version < 3:  # one session; its first node's step held no covariance
            data = {**data, "step_covariance": np.concatenate([np.zeros((min(k, 1), 6, 6)), data["step_covariance"]])}
            sessions = [SavedSession(name=DEFAULT_SESSION, rows=n, nodes=k, root=True, anchored=True, frame=np.eye(4))]
        else:
            try:
                sessions = [SavedSession.from_dict(d) for d in json.loads(str(data["sessions"]))]
            except (KeyError, ValueError, TypeError, AttributeError) as err:
                raise bad(f"sessions cannot be read ({err})") from err
            names = [info.name for info in sessions]
            if len(set(names)) != len(names) or sum(info.root for info in sessions) > 1:
                raise bad(f"sessions {names} repeat a name or hold more than one map-frame session")
        if (sum(info.rows for info in sessions) != n or sum(info.nodes for info in sessions) != k
                or any(info.rows < 0 or info.nodes < 0 or (info.rows and not info.nodes) for info in sessions)):
            raise bad(f"inconsistent arrays: the sessions hold {sum(info.rows for info in sessions)} odometry rows and "
                      f"{sum(info.nodes for info in sessions)} nodes, the arrays {n} and {k}; the file is damaged")
        row0 = node0 = 0
        for info in sessions:
            idx = data["node_index"][node0:node0 + info.nodes]
            if (np.any(np.diff(data["stamps"][row0:row0 + info.rows]) <= 0)
                    or (info.nodes and (idx[0] != 0 or np.any(np.diff(idx) <= 0) or idx[-1] >= info.rows))):
                raise bad(f"inconsistent arrays: session {info.name!r} has stamps or node rows that do not "
                          "increase; the file is damaged")
            row0, node0 = row0 + info.rows, node0 + info.nodes
        if (len(data["odometry"]) != n or len(data["node_estimate"]) != k
                or len(data["step_covariance"]) != k
                or any(len(data[f"loop_{s}"]) != nl for s in ("measured", "covariance", "stamps", "chi2"))
                or (nl and (data["loop_nodes"].min() < 0 or data["loop_nodes"].max() >= k))
                or len(data["up_nodes"]) != len(data["up_stamps"]) or len(data["up_body"]) != len(data["up_stamps"])
                or (len(data["up_nodes"]) and (data["up_nodes"].min() < 0 or data["up_nodes"].max() >= k))
                or not (np.isfinite(data["up_world"]).all() or np.isnan(data["up_world"]).all())
                or any(len(data[f"waiting_{s}"]) != len(data["waiting_nodes"])
                       for s in ("measured", "covariance", "stamps"))
                or (len(data["waiting_nodes"]) and (data["waiting_nodes"].min() < 0
                                                    or data["waiting_nodes"].max() >= k))):
            raise bad(f"inconsistent arrays ({n} odometry stamps, {k} nodes, {nl} loops); the file is damaged")
        try:
            counters = json.loads(str(data["counters"]))
            rejected, refused = int(counters["rejected"]), {str(a): int(b) for a, b in counters["refused"].items()}
            redundant = int(counters.get("redundant", 0))
            inter = {str(a): int(b) for a, b in counters.get("inter_session", {}).items()}
        except (KeyError, ValueError, TypeError, AttributeError) as err:
            raise bad(f"counters cannot be read ({err})") from err
        return cls(**{name: data[name] for name in _SHAPES}, rejected=rejected, redundant=redundant, refused=refused,
                   sessions=sessions, inter_session=inter)


def write_graph_file(path: str | os.PathLike[str], graph: SavedGraph) -> None:
    """Write ``graph`` as .npz, atomically: readers see the old file or the whole new one."""
    arrays: dict[str, Any] = graph.arrays()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def read_graph_file(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Every array of the .npz at ``path`` (unchecked: :meth:`SavedGraph.from_arrays` checks them)."""
    where = os.fspath(path)
    try:
        with np.load(where, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise BackendError(f"graph file {where} cannot be read ({err}); expected an .npz written by "
                           "PoseGraphBackend.save", reason=BAD_FILE) from err
