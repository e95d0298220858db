"""The back end's graph file: one .npz of plain arrays (no pickled objects), written atomically.

It holds the odometry, the graph nodes with their estimates and step covariances, the accepted loops, the
measured ups and the counters, enough for :meth:`~lcpr_core.backend.PoseGraphBackend.load` to continue the
graph. Reading checks the schema, the version, every array's shape and the arrays against each other before
anything is rebuilt, so a damaged file is refused with a :class:`~lcpr_core.errors.BackendError` (reason
``"bad graph file"``) naming what is wrong, never half-loaded.
"""
from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..atomic import atomic_path
from ..errors import BackendError
from .config import show

__all__ = ["GRAPH_SCHEMA", "GRAPH_VERSION", "SavedGraph", "read_graph_file", "write_graph_file"]

GRAPH_SCHEMA = "lcpr_backend_graph"
GRAPH_VERSION = 2  # 2 added the measured ups; version 1 files (none) still load
BAD_FILE = "bad graph file"

#: every array of a file and its shape (None: any length)
_SHAPES: dict[str, tuple[int | None, ...]] = {
    "base_T_lidar": (4, 4), "stamps": (None,), "odometry": (None, 4, 4), "node_index": (None,),
    "node_estimate": (None, 4, 4), "step_covariance": (None, 6, 6), "loop_nodes": (None, 2),
    "loop_measured": (None, 4, 4), "loop_covariance": (None, 6, 6), "loop_stamps": (None, 2),
    "loop_chi2": (None,), "up_stamps": (None,), "up_nodes": (None,), "up_body": (None, 3),
    "up_world": (3,)}


@dataclass
class SavedGraph:
    """What a graph file holds: N odometry messages, K nodes, L loops, U measured ups and the counters."""

    base_T_lidar: np.ndarray  # (4, 4) the extrinsic the loops were taken with
    stamps: np.ndarray  # (N,) odometry stamps, increasing
    odometry: np.ndarray  # (N, 4, 4) world_T_base of each odometry message
    node_index: np.ndarray  # (K,) odometry row of each graph node
    node_estimate: np.ndarray  # (K, 4, 4) the graph's estimate of each node
    step_covariance: np.ndarray  # (K - 1, 6, 6) ROS-order covariance of each node step
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

    def arrays(self) -> dict[str, np.ndarray]:
        """The file's arrays: the schema, the version, every array of :data:`_SHAPES` and the counters."""
        counters = {"rejected": self.rejected, "redundant": self.redundant, "refused": dict(self.refused)}
        return {"schema": np.array(GRAPH_SCHEMA), "version": np.array(GRAPH_VERSION, np.int64),
                **{name: getattr(self, name) for name in _SHAPES}, "counters": np.array(json.dumps(counters))}

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
        if version not in (1, GRAPH_VERSION):
            raise bad(f"version {version!r}; this back end reads versions 1 to {GRAPH_VERSION}")
        if version == 1:  # before measured ups
            data = {**data, "up_stamps": np.zeros(0), "up_nodes": np.zeros(0, np.int64), "up_body": np.zeros((0, 3)),
                    "up_world": np.full(3, np.nan)}
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
        idx = data["node_index"]
        if (len(data["odometry"]) != n or len(data["node_estimate"]) != k
                or len(data["step_covariance"]) != max(k - 1, 0)
                or (k and (idx[0] != 0 or np.any(np.diff(idx) <= 0) or idx[-1] >= n))
                or np.any(np.diff(data["stamps"]) <= 0) or (n and not k)
                or any(len(data[f"loop_{s}"]) != nl for s in ("measured", "covariance", "stamps", "chi2"))
                or (nl and (data["loop_nodes"].min() < 0 or data["loop_nodes"].max() >= k))
                or len(data["up_nodes"]) != len(data["up_stamps"]) or len(data["up_body"]) != len(data["up_stamps"])
                or (len(data["up_nodes"]) and (data["up_nodes"].min() < 0 or data["up_nodes"].max() >= k))
                or not (np.isfinite(data["up_world"]).all() or np.isnan(data["up_world"]).all())):
            raise bad(f"inconsistent arrays ({n} odometry stamps, {k} nodes, {nl} loops); the file is damaged")
        try:
            counters = json.loads(str(data["counters"]))
            rejected, refused = int(counters["rejected"]), {str(a): int(b) for a, b in counters["refused"].items()}
            redundant = int(counters.get("redundant", 0))
        except (KeyError, ValueError, TypeError, AttributeError) as err:
            raise bad(f"counters cannot be read ({err})") from err
        return cls(**{name: data[name] for name in _SHAPES}, rejected=rejected, redundant=redundant, refused=refused)


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
