"""Nearest neighbours within a reach: the searches behind the overlap, the evidence and the free-space excuse.

    near = Neighbours(xyz)                                   # M x 3 float64, built once per prepared cloud
    idx, within = near.nearest(points, reach=0.6, threads=1)  # N: nearest row, and whether it is within reach

Every verification test asks one question of a neighbour search: which point of the other cloud is
nearest, if one lies within ``verify.inlier_distance``. A k-d tree told that reach (pykdtree) prunes
everything farther and answers in NumPy arrays, two to four times faster than small_gicp's search, which
has no reach and answers in Python lists. Both are exact: the nearest point within reach is the same.
"""
from __future__ import annotations

import ctypes
import glob
import os
import threading

import numpy as np
from pykdtree.kdtree import KDTree

_LEAF = 16  # points per leaf: the fastest of 8 / 16 / 32 on compact clouds (benchmarks/tools/verify_cost.py)


class Neighbours:
    """An exact nearest-neighbour search over one cloud's points, answering only within a reach."""

    def __init__(self, xyz: np.ndarray) -> None:
        self._xyz = np.ascontiguousarray(xyz, np.float64).reshape(-1, 3)
        self._tree = KDTree(self._xyz, leafsize=_LEAF) if len(self._xyz) else None

    def __len__(self) -> int:
        return len(self._xyz)

    def nearest(self, points: np.ndarray, *, reach: float, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(nearest row of each point, whether it lies within ``reach`` m); a row is meaningful only within."""
        query = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        if self._tree is None or not len(query):
            return np.zeros(len(query), np.int64), np.zeros(len(query), bool)
        _limit_threads(threads)
        d2, idx = self._tree.query(query, k=1, distance_upper_bound=reach, sqr_dists=True)
        within = np.isfinite(d2) & (d2 <= reach * reach)
        return np.where(within, idx, 0).astype(np.int64), within


_local = threading.local()


def _limit_threads(threads: int) -> None:
    """Hold pykdtree's OpenMP to ``threads`` in the calling thread: its own copy of libgomp would otherwise use
    every core, beside the network and the other verification workers (the workers run one thread each)."""
    if getattr(_local, "threads", None) == threads:
        return
    _local.threads = threads
    if _OMP is not None:
        _OMP.omp_set_num_threads(ctypes.c_int(threads))


def _bundled_openmp() -> ctypes.CDLL | None:
    """The OpenMP runtime pykdtree's queries run on (its wheel's own libgomp, else the system's), or None."""
    import pykdtree

    here = os.path.dirname(os.path.dirname(os.path.abspath(pykdtree.__file__)))
    for path in [*sorted(glob.glob(os.path.join(here, "pykdtree.libs", "libgomp*.so*"))), "libgomp.so.1"]:
        try:
            lib = ctypes.CDLL(path)
            lib.omp_set_num_threads.argtypes = [ctypes.c_int]
            return lib
        except (OSError, AttributeError):
            continue
    return None


_OMP = _bundled_openmp()
