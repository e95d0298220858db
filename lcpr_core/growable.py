"""A numpy array that grows by amortised doubling: per-entry metadata of the growing maps."""
from __future__ import annotations

import numpy as np


class GrowableArray:
    """Rows of ``dtype`` (each of shape ``width``) appended in amortised O(1)."""

    def __init__(self, dtype: type | np.dtype, width: tuple[int, ...] = ()) -> None:
        self._data = np.empty((16, *width), dtype=dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def extend(self, values: np.ndarray) -> None:
        need = self._n + len(values)
        if need > len(self._data):
            grown = np.empty((max(need, 2 * len(self._data)), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._n] = self._data[: self._n]
            self._data = grown
        self._data[self._n : need] = values
        self._n = need

    def view(self) -> np.ndarray:
        """Read-only view of the filled rows (a snapshot: later appends don't show)."""
        out = self._data[: self._n]
        out.flags.writeable = False
        return out
