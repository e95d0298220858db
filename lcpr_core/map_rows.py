"""The per-entry rows both growing maps keep: ids, stamps and poses, their checks and their order flags.

One home for the rules of a map entry, used by the LCPR descriptor map (poses (3,) x, y, z) and the
VSeq2PC scan database (poses (4, 4) world_T_lidar): ids non-negative, unique and unused (default: one more
than the largest so far), stamps finite seconds, poses finite or NaN (unknown). The searches read
``stamps_sorted`` (a prefix of rows is matchable) and ``ids_increasing`` (an id lookup needs no scan).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .errors import MapError
from .growable import GrowableArray

__all__ = ["MapRows", "RowAccess", "check_poses", "check_stamps"]


def _one_per_row(values: ArrayLike, n: int, what: str, unit: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim == 0 and n == 1:
        arr = arr.reshape(1)
    if arr.shape != (n,):
        raise MapError(f"{what} of shape {tuple(arr.shape)} do not fit {n} {unit}; expected ({n},)")
    return arr


def check_stamps(stamps: float | ArrayLike, n: int, *, unit: str = "descriptors") -> np.ndarray:
    """(n,) float64 finite seconds (a float for one entry)."""
    arr = _one_per_row(stamps, n, "stamps", unit)
    if arr.dtype.kind not in "fiu":
        raise MapError(f"stamps have dtype {arr.dtype}; expected float seconds")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise MapError(f"stamps {arr[~np.isfinite(arr)][:5].tolist()} are not finite; expected finite seconds")
    return arr


def check_poses(poses: ArrayLike | None, n: int, shape: tuple[int, ...], *, unit: str = "descriptors") -> np.ndarray:
    """(n, *shape) float64; None -> all NaN (unknown); one ``shape`` pose for one entry."""
    if poses is None:
        return np.full((n, *shape), np.nan)
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MapError(f"poses cannot be read as {shape} floats: {err}") from err
    if arr.shape == shape and n == 1:
        arr = arr.reshape(1, *shape)
    if arr.shape != (n, *shape):
        expected = ", ".join(str(d) for d in (n, *shape))
        raise MapError(f"poses of shape {arr.shape} do not fit {n} {unit}; expected ({expected})")
    if np.isinf(arr).any():
        raise MapError("poses contain inf; expected finite values, or NaN for unknown")
    return arr


class MapRows:
    """Ids, stamps and poses of a growing map, one row per entry, in insertion order."""

    def __init__(self, pose_shape: tuple[int, ...], *, unit: str = "descriptors") -> None:
        self.pose_shape = pose_shape
        self.unit = unit  # what an entry is called in messages
        self._ids = GrowableArray(np.int64)
        self._stamps = GrowableArray(np.float64)
        self._poses = GrowableArray(np.float64, pose_shape)
        self.next_id = 0
        self.ids_increasing = True  # ids strictly increasing in insertion order
        self.stamps_sorted = True  # stamps non-decreasing in insertion order

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def ids(self) -> np.ndarray:
        """(N,) int64, read-only."""
        return self._ids.view()

    @property
    def stamps(self) -> np.ndarray:
        """(N,) float64 seconds, read-only."""
        return self._stamps.view()

    @property
    def poses(self) -> np.ndarray:
        """(N, *pose_shape) float64, NaN where unknown; read-only."""
        return self._poses.view()

    def check(self, n: int, *, stamps: float | ArrayLike, poses: ArrayLike | None,
              ids: int | ArrayLike | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, stamps, poses) of ``n`` new entries, checked; MapError names what is wrong."""
        t = check_stamps(stamps, n, unit=self.unit)
        p = check_poses(poses, n, self.pose_shape, unit=self.unit)
        return self._check_new_ids(ids, n), t, p

    def _check_new_ids(self, ids: int | ArrayLike | None, n: int) -> np.ndarray:
        if ids is None:
            return np.arange(self.next_id, self.next_id + n, dtype=np.int64)
        arr = _one_per_row(ids, n, "ids", self.unit)
        if arr.dtype.kind not in "iu":
            raise MapError(f"ids have dtype {arr.dtype}; expected an integer dtype")
        arr = arr.astype(np.int64)
        if n == 0:
            return arr
        rule = "ids must be unique, unused and >= 0"
        if arr.min() < 0:
            raise MapError(f"id {int(arr.min())} is negative; {rule}")
        uniq, counts = np.unique(arr, return_counts=True)
        if len(uniq) != n:
            raise MapError(f"ids given to add() repeat (e.g. {int(uniq[counts > 1][0])}); {rule}")
        existing = self.ids
        if len(existing) and not (self.ids_increasing and uniq[0] > existing[-1]):
            taken = uniq[np.isin(uniq, existing)]
            if len(taken):
                raise MapError(f"ids {taken[:5].tolist()} are already in the map; {rule}")
        return arr

    def append(self, ids: np.ndarray, stamps: np.ndarray, poses: np.ndarray) -> None:
        """Add checked rows (from :meth:`check`) and keep the order flags."""
        if len(ids) == 0:
            return
        last_stamp = self.stamps[-1] if len(self) else -np.inf
        self.stamps_sorted = self.stamps_sorted and stamps[0] >= last_stamp and bool(np.all(np.diff(stamps) >= 0))
        if self.ids_increasing:
            last_id = self.ids[-1] if len(self) else -1
            self.ids_increasing = ids[0] > last_id and bool(np.all(np.diff(ids) > 0))
        self._ids.extend(ids)
        self._stamps.extend(stamps)
        self._poses.extend(poses)
        self.next_id = max(self.next_id, int(ids.max()) + 1)


class RowAccess:
    """``len()``, ``ids``, ``stamps`` and ``poses`` of a map that keeps its entries in ``self._rows``."""

    _rows: MapRows

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def ids(self) -> np.ndarray:
        """(N,) int64, read-only."""
        return self._rows.ids

    @property
    def stamps(self) -> np.ndarray:
        """(N,) float64 seconds, read-only."""
        return self._rows.stamps

    @property
    def poses(self) -> np.ndarray:
        """(N, 3) x, y, z (descriptor map) or (N, 4, 4) world_T_lidar (scan database); NaN where unknown.
        Read-only."""
        return self._rows.poses
