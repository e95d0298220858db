"""Initial guesses for registration: LCPR is yaw-invariant and says nothing about the relative pose.

1. yaw: the Scan Context column shifts that best align the two clouds (a turn of the
   sensor rolls the polar grid's columns), the ``count`` best peaks of the summed
   column cosine;
2. x/y: for each yaw, the peak of the cross-correlation of two bird's-eye views whose
   cells hold the height span of the points in them (walls, poles and trees count;
   flat ground, whose rings follow the sensor, does not).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry import wrap_angle
from ..points import turn_cos_sin
from ..scan_context import ScanContextConfig, scan_context

SC_CONFIG = ScanContextConfig(num_rings=20, num_sectors=72, max_range=80.0, lidar_height=3.0)


@dataclass(frozen=True)
class Hypothesis:
    """match_T_query guess: yaw (rad) about z, then x/y (m); ``score`` in [0, 1] (BEV correlation)."""

    yaw: float
    x: float
    y: float
    score: float

    def matrix(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = (self.x, self.y)
        return T


def polar_context(xyz: np.ndarray) -> np.ndarray:
    """rings x sectors max-height grid of a cloud (the Scan Context used for yaw)."""
    return scan_context(xyz, config=SC_CONFIG)


def yaw_candidates(query_sc: np.ndarray, match_sc: np.ndarray, count: int) -> list[float]:
    """The ``count`` yaws (rad, match_T_query) whose column shifts align the contexts best.

    A query sensor turned by +psi relative to the match sees the match's columns
    rolled by -psi: ``np.roll(match_sc, s)`` aligns with ``query_sc`` at s = -psi / sector.
    Shifts are scored by the summed column cosine, not the mean: with a narrow field of
    view (a Livox sees ~70 deg) a shift that overlaps two columns by chance must not
    beat one that overlaps all of them.
    """
    score = _shift_scores(query_sc, match_sc)  # (sectors,)
    sectors = len(score)
    left, right = np.roll(score, 1), np.roll(score, -1)
    peaks = np.flatnonzero((score >= left) & (score >= right))
    order = peaks[np.argsort(-score[peaks], kind="stable")]
    if len(order) < count:  # flat profile: fill with the plain best shifts
        taken = set(order.tolist())
        rest = [s for s in np.argsort(-score, kind="stable") if s not in taken]
        order = np.concatenate([order, rest]).astype(np.int64)
    step = 2.0 * math.pi / sectors
    return [wrap_angle(-float(s) * step) for s in order[:count]]


def _shift_scores(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(sectors,) sum over columns occupied in both of cos(a[:, j], roll(b, s)[:, j]), for every shift s."""
    sectors = a.shape[1]
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    na, nb = np.linalg.norm(a64, axis=0), np.linalg.norm(b64, axis=0)
    ua = np.divide(a64, na, out=np.zeros_like(a64), where=na > 0)
    ub = np.divide(b64, nb, out=np.zeros_like(b64), where=nb > 0)
    gram = ua.T @ ub  # (j, k) = cos(a[:, j], b[:, k])
    cols = (np.arange(sectors)[None, :] - np.arange(sectors)[:, None]) % sectors  # (s, j) -> k
    return gram[np.arange(sectors)[None, :], cols].sum(axis=1)


def bev_image(xyz: np.ndarray, *, cell: float, extent: float) -> np.ndarray:
    """G x G float32 height span (max z - min z) per cell, G = 2 * extent / cell, sensor at the centre."""
    return _bev_image(xyz[:, 0], xyz[:, 1], xyz[:, 2], cell=cell, extent=extent)


def _bev_image(x: np.ndarray, y: np.ndarray, z: np.ndarray, *, cell: float, extent: float) -> np.ndarray:
    """:func:`bev_image` of the points' columns (one column at a time: fewer passes over the points)."""
    size = int(round(2.0 * extent / cell))
    i = np.floor((x + extent) / cell)  # whole numbers as floats: compared and combined exactly
    j = np.floor((y + extent) / cell)
    inside = (i >= 0) & (i < size) & (j >= 0) & (j < size)
    flat = (i[inside] * size + j[inside]).astype(np.int64)
    heights = z[inside].astype(np.float64)
    top = np.full(size * size, -np.inf)
    low = np.full(size * size, np.inf)
    np.maximum.at(top, flat, heights)
    np.minimum.at(low, flat, heights)
    span = np.where(np.isfinite(top), top - low, 0.0)
    return np.minimum(span, 3.0).reshape(size, size).astype(np.float32)


class BevMatcher:
    """x/y offset of a rotated query view against one match view by FFT cross-correlation."""

    def __init__(self, match_xyz: np.ndarray, *, cell: float, extent: float, max_offset: float) -> None:
        self.cell, self.extent = cell, extent
        image = bev_image(match_xyz, cell=cell, extent=extent)
        self.size = image.shape[0]
        reach = min(int(math.ceil(max_offset / cell)), self.size - 1)
        self._pad = _fft_size(self.size + reach)  # zero padding: no wrap-around within +-reach
        self._norm = float(np.linalg.norm(image))
        self._spectrum = np.fft.rfft2(image, s=(self._pad, self._pad))
        offsets = np.fft.fftfreq(self._pad, d=1.0 / self._pad).astype(np.int64)  # FFT index -> signed shift
        self._offsets = offsets
        self._reach = np.flatnonzero(np.abs(offsets) <= reach)  # FFT indices of the shifts within +-reach

    @property
    def key(self) -> tuple[float, float, int]:
        """(cell, extent, padded size): matchers with one key take the same query spectra."""
        return self.cell, self.extent, self._pad

    def query_spectrum(self, query_xyz: np.ndarray, yaw: float) -> tuple[np.ndarray, float]:
        """(conjugate spectrum, norm) of the query's view turned by ``yaw``: what :meth:`locate` needs of the
        query, the same for every match with this :attr:`key` (a query's candidates share it)."""
        x, y = query_xyz[:, 0], query_xyz[:, 1]
        if yaw != 0.0:  # rotate_z's arithmetic on the two columns the view reads
            c, s = turn_cos_sin(math.degrees(yaw))
            x, y = c * x - s * y, s * x + c * y
        image = _bev_image(x, y, query_xyz[:, 2], cell=self.cell, extent=self.extent)
        return np.conj(np.fft.rfft2(image, s=(self._pad, self._pad))), float(np.linalg.norm(image))

    def locate(self, query_xyz: np.ndarray, yaw: float, *,
               spectrum: tuple[np.ndarray, float] | None = None) -> Hypothesis:
        """Best x/y for ``yaw``: where match(x) ~ rotated query(x - t). ``spectrum``: :meth:`query_spectrum`'s
        answer for this query and yaw when the caller keeps it."""
        query_conj, query_norm = spectrum if spectrum is not None else self.query_spectrum(query_xyz, yaw)
        norm = query_norm * self._norm
        if norm <= 0.0:
            return Hypothesis(yaw, 0.0, 0.0, 0.0)
        corr = np.fft.irfft2(self._spectrum * query_conj, s=(self._pad, self._pad))
        inside = corr[np.ix_(self._reach, self._reach)]  # the shifts within reach, in the same (row-major) order
        a, b = np.unravel_index(int(np.argmax(inside)), inside.shape)
        i, j = self._reach[a], self._reach[b]
        di, dj = int(self._offsets[i]), int(self._offsets[j])
        return Hypothesis(yaw, di * self.cell, dj * self.cell, float(max(corr[i, j], 0.0) / norm))


def _fft_size(n: int) -> int:
    """The smallest n' >= n whose only prime factors are 2, 3 and 5 (fast for pocketfft)."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1
