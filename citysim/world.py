"""The city model: vertical prisms (boxes, cylinders), a ground map, parking slots, lamps.

Everything is in a flat world frame (x, y in metres on the ground, z up). Static objects
come from the generators in :mod:`citygen`; parked cars depend on the time of the visit
(:func:`parked_cars`), so a place looks different when the drive comes back.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, fields

import numpy as np

from .hashing import hash_u64, hash_uniform
from .labels import INSTANCE_SHIFT, Label, Mat

N_PARAMS = 6  # material parameters per object (meaning depends on the material)


def as_rgb(values: Iterable[float]) -> tuple[float, float, float]:
    """A colour row (numpy array, list) -> the (r, g, b) float tuple :class:`ObjectsBuilder` takes."""
    r, g, b = (float(v) for v in values)
    return r, g, b


@dataclass
class Objects:
    """N vertical prisms: oriented boxes (kind 0) and cylinders (kind 1), with appearance.

    A box has centre (cx, cy), half extents (hx along its heading, hy across) and heading
    (cos, sin); a cylinder has radius hx (= hy). It spans z0..z1; ``dome`` (cylinders)
    rounds the top by that many metres (a tree canopy).
    """

    kind: np.ndarray  # N uint8
    cx: np.ndarray  # N float64
    cy: np.ndarray
    hx: np.ndarray
    hy: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    z0: np.ndarray
    z1: np.ndarray
    dome: np.ndarray  # N float64, metres
    label: np.ndarray  # N uint32 (class | instance << 16)
    mat: np.ndarray  # N uint8 (labels.Mat)
    color: np.ndarray  # N x 3 float32 albedo in [0, 1]
    params: np.ndarray  # N x N_PARAMS float32
    seed: np.ndarray  # N uint32
    refl: np.ndarray  # N float32 LiDAR reflectivity in [0, 1]

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    @property
    def radius(self) -> np.ndarray:
        """N bounding-circle radii."""
        return np.hypot(self.hx, self.hy) * (self.kind == 0) + self.hx * (self.kind == 1)

    def take(self, idx: np.ndarray) -> Objects:
        return Objects(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})

    @staticmethod
    def concat(parts: list[Objects]) -> Objects:
        parts = [p for p in parts if len(p)] or parts[:1]
        return Objects(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Objects)})

    @staticmethod
    def empty() -> Objects:
        return ObjectsBuilder().build()


class ObjectsBuilder:
    """Collects prisms one at a time; :meth:`build` makes the column arrays."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def box(self, cx: float, cy: float, hx: float, hy: float, yaw: float, z0: float, z1: float, *,
            label: int, mat: Mat, color: tuple[float, float, float], params: tuple[float, ...] = (),
            seed: int = 0, refl: float = 0.3) -> None:
        self.rows.append((0, cx, cy, hx, hy, np.cos(yaw), np.sin(yaw), z0, z1, 0.0, label, mat, color,
                          params, seed, refl))

    def cylinder(self, cx: float, cy: float, r: float, z0: float, z1: float, *, label: int, mat: Mat,
                 color: tuple[float, float, float], dome: float = 0.0, params: tuple[float, ...] = (),
                 seed: int = 0, refl: float = 0.3) -> None:
        self.rows.append((1, cx, cy, r, r, 1.0, 0.0, z0, z1, dome, label, mat, color, params, seed, refl))

    def __len__(self) -> int:
        return len(self.rows)

    def build(self) -> Objects:
        n = len(self.rows)
        cols = list(zip(*self.rows, strict=True)) if n else [()] * 16
        params = np.zeros((n, N_PARAMS), dtype=np.float32)
        for i, p in enumerate(cols[13]):
            params[i, :len(p)] = p
        f64 = lambda c: np.asarray(c, dtype=np.float64).reshape(n)  # noqa: E731
        return Objects(
            kind=np.asarray(cols[0], dtype=np.uint8).reshape(n),
            cx=f64(cols[1]), cy=f64(cols[2]), hx=f64(cols[3]), hy=f64(cols[4]),
            cos=f64(cols[5]), sin=f64(cols[6]), z0=f64(cols[7]), z1=f64(cols[8]), dome=f64(cols[9]),
            label=np.asarray(cols[10], dtype=np.uint32).reshape(n),
            mat=np.asarray(cols[11], dtype=np.uint8).reshape(n),
            color=np.asarray(cols[12], dtype=np.float32).reshape(n, 3),
            params=params,
            seed=np.asarray(cols[14], dtype=np.uint32).reshape(n),
            refl=np.asarray(cols[15], dtype=np.float32).reshape(n),
        )


@dataclass
class GroundMap:
    """Ground codes (see :mod:`ground`) on a regular raster; outside it is terrain."""

    codes: np.ndarray  # ny x nx uint8
    x0: float  # world x of column 0's left edge
    y0: float  # world y of row 0's lower edge
    res: float  # metres per cell
    lamp_light: np.ndarray  # my x mx float32, street-light irradiance on the ground
    lamp_res: float

    def lookup(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground codes at world points (nearest cell); 0 (terrain) outside the map."""
        ny, nx = self.codes.shape
        ix = np.floor((x - self.x0) / self.res).astype(np.int64)
        iy = np.floor((y - self.y0) / self.res).astype(np.int64)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = np.zeros(ix.shape, dtype=np.uint8)
        out[ok] = self.codes[iy[ok], ix[ok]]
        return out

    def light(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Street-light irradiance at world points (0 outside the map)."""
        my, mx = self.lamp_light.shape
        ix = np.floor((x - self.x0) / self.lamp_res).astype(np.int64)
        iy = np.floor((y - self.y0) / self.lamp_res).astype(np.int64)
        ok = (ix >= 0) & (ix < mx) & (iy >= 0) & (iy < my)
        out = np.zeros(ix.shape, dtype=np.float32)
        out[ok] = self.lamp_light[iy[ok], ix[ok]]
        return out

    @staticmethod
    def uniform(code: int, *, x0: float = -200.0, y0: float = -200.0, size: float = 400.0,
                res: float = 0.5) -> GroundMap:
        """A map of one code (for tests and hand-made worlds)."""
        n = int(round(size / res))
        return GroundMap(np.full((n, n), code, np.uint8), x0, y0, res, np.zeros((1, 1), np.float32), size)


class SpatialIndex:
    """Objects bucketed by centre on a square grid, for 'everything within r of p' queries."""

    def __init__(self, objects: Objects, *, cell: float = 32.0) -> None:
        self.cell = cell
        self.max_radius = float(objects.radius.max()) if len(objects) else 0.0
        ix = np.floor(objects.cx / cell).astype(np.int64)
        iy = np.floor(objects.cy / cell).astype(np.int64)
        self.ix0, self.iy0 = (int(ix.min()), int(iy.min())) if len(objects) else (0, 0)
        self.nx = int(ix.max()) - self.ix0 + 1 if len(objects) else 1
        self.ny = int(iy.max()) - self.iy0 + 1 if len(objects) else 1
        key = (iy - self.iy0) * self.nx + (ix - self.ix0)
        self.order = np.argsort(key, kind="stable")
        self.starts = np.searchsorted(key[self.order], np.arange(self.nx * self.ny + 1))
        self.cx, self.cy, self.radius = objects.cx, objects.cy, objects.radius

    def near(self, x: float, y: float, r: float) -> np.ndarray:
        """Sorted indices of objects whose bounding circle comes within r of (x, y)."""
        reach = r + self.max_radius
        i0 = max(int(np.floor((x - reach) / self.cell)) - self.ix0, 0)
        i1 = min(int(np.floor((x + reach) / self.cell)) - self.ix0, self.nx - 1)
        j0 = max(int(np.floor((y - reach) / self.cell)) - self.iy0, 0)
        j1 = min(int(np.floor((y + reach) / self.cell)) - self.iy0, self.ny - 1)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, dtype=np.int64)
        rows = [j * self.nx for j in range(j0, j1 + 1)]
        chunks = [self.order[self.starts[r + i0]:self.starts[r + i1 + 1]] for r in rows]
        idx = np.sort(np.concatenate(chunks))
        d = np.hypot(self.cx[idx] - x, self.cy[idx] - y) - self.radius[idx]
        return idx[d < r]


@dataclass
class ParkingSlots:
    """Places where a car may be parked: centre, heading."""

    x: np.ndarray  # N float64
    y: np.ndarray
    yaw: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])


@dataclass
class World:
    """A generated city: static prisms, ground, parking slots and street lights."""

    objects: Objects
    ground: GroundMap
    slots: ParkingSlots
    lamps: np.ndarray  # L x 3 lamp-head positions
    seed: int
    parking_period_s: float = 120.0  # how long a parked car stays, on average
    parking_occupancy: float = 0.55
    index: SpatialIndex = field(init=False, repr=False)
    _slot_index: SpatialIndex = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.index = SpatialIndex(self.objects)
        slot_boxes = ObjectsBuilder()
        for x, y in zip(self.slots.x, self.slots.y, strict=True):
            slot_boxes.cylinder(x, y, 3.0, 0.0, 1.0, label=0, mat=Mat.CAR, color=(0, 0, 0))
        self._slot_index = SpatialIndex(slot_boxes.build())

    def objects_near(self, x: float, y: float, r: float, *, stamp: float, empty_slots: np.ndarray | None = None
                     ) -> Objects:
        """Static objects and the cars parked at ``stamp`` within r metres of (x, y).

        ``empty_slots`` (a bool per slot) leaves those slots without a car (a drive's own lane).
        """
        static = self.objects.take(self.index.near(x, y, r))
        slots = self._slot_index.near(x, y, r)
        if empty_slots is not None:
            slots = slots[~empty_slots[slots]]
        cars = parked_cars(self.slots, slots, stamp=stamp, seed=self.seed, period_s=self.parking_period_s,
                           occupancy=self.parking_occupancy)
        return Objects.concat([static, cars])

    def clearance(self, xy: np.ndarray, *, reach: float = 3.0, below: float = 2.0) -> np.ndarray:
        """Per ground point (N x 2): metres to the nearest static object a car could hit (its base lower
        than ``below`` metres: walls, fences, poles, trunks); ``reach`` (or more) where none is that near.

        A route planned without the city (a second drive) must keep clear of them.
        """
        xy = np.asarray(xy, dtype=np.float64)
        out = np.full(len(xy), float(reach))
        for lo, idx in _chunks_near(xy, self.index, reach):
            idx = idx[self.objects.z0[idx] < below]
            if len(idx):
                d = footprint_distance(xy[lo:lo + _CHUNK], self.objects.take(idx)).min(axis=1)
                out[lo:lo + _CHUNK] = np.minimum(out[lo:lo + _CHUNK], d)
        return out

    def slots_near(self, xy: np.ndarray, *, radius: float = 2.2) -> np.ndarray:
        """A bool per parking slot: would a car there (5.2 x 2 m) come within ``radius`` metres of xy (N x 2)?

        The city keeps drive 0's corridor free of parked cars by this rule; a later drive
        leaves the slots near its own route empty.
        """
        xy = np.asarray(xy, dtype=np.float64)
        out = np.zeros(len(self.slots), dtype=bool)
        for lo, idx in _chunks_near(xy, self._slot_index, radius):
            slot_cars = _slot_boxes(self.slots, idx)
            near = (footprint_distance(xy[lo:lo + _CHUNK], slot_cars) < radius).any(axis=0)
            out[idx[near]] = True
        return out


_CHUNK = 64  # ground points per spatial query


def _chunks_near(xy: np.ndarray, index: SpatialIndex, reach: float) -> Iterator[tuple[int, np.ndarray]]:
    """(first point, indices of objects within ``reach`` of any of the next _CHUNK points) along xy."""
    for lo in range(0, len(xy), _CHUNK):
        pts = xy[lo:lo + _CHUNK]
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        spread = float(np.hypot(*(pts - centre).T).max())
        yield lo, index.near(float(centre[0]), float(centre[1]), spread + reach)


def _slot_boxes(slots: ParkingSlots, idx: np.ndarray) -> Objects:
    b = ObjectsBuilder()
    for i in idx:
        b.box(float(slots.x[i]), float(slots.y[i]), 2.6, 1.0, float(slots.yaw[i]), 0.0, 1.5, label=0, mat=Mat.CAR,
              color=(0.0, 0.0, 0.0))
    return b.build()


def footprint_distance(xy: np.ndarray, objects: Objects) -> np.ndarray:
    """M x N ground-plane distances from points xy (M x 2) to the footprints of N objects (negative inside)."""
    dx = xy[:, 0:1] - objects.cx[None, :]
    dy = xy[:, 1:2] - objects.cy[None, :]
    along = np.abs(dx * objects.cos + dy * objects.sin) - objects.hx
    across = np.abs(-dx * objects.sin + dy * objects.cos) - objects.hy
    box = np.hypot(np.maximum(along, 0.0), np.maximum(across, 0.0)) + np.minimum(np.maximum(along, across), 0.0)
    return np.where(objects.kind == 0, box, np.hypot(dx, dy) - objects.hx)


CAR_COLORS = np.array([
    (0.85, 0.85, 0.86), (0.08, 0.08, 0.09), (0.45, 0.46, 0.48), (0.62, 0.63, 0.65), (0.55, 0.06, 0.07),
    (0.08, 0.18, 0.45), (0.80, 0.78, 0.70), (0.15, 0.30, 0.18), (0.75, 0.45, 0.10), (0.30, 0.33, 0.40),
], dtype=np.float32)


def parked_cars(slots: ParkingSlots, idx: np.ndarray, *, stamp: float, seed: int, period_s: float,
                occupancy: float) -> Objects:
    """The cars in slots ``idx`` at time ``stamp``: body + cabin boxes each.

    Each slot draws a new car (or none) every ``period_s`` seconds on average, with a
    slot-specific phase; about a third of the slots hold the same car for the whole drive.
    """
    idx = np.asarray(idx, dtype=np.int64)
    phase = hash_uniform(seed, 11, idx) * period_s
    permanent = hash_uniform(seed, 12, idx) < 0.35
    epoch = np.where(permanent, -1, np.floor((stamp + phase) / period_s)).astype(np.int64)
    u = [hash_uniform(seed, 13, idx, epoch, k) for k in range(8)]
    occupied = u[0] < occupancy
    b = ObjectsBuilder()
    for n in np.nonzero(occupied)[0]:
        i = idx[n]
        big = u[1][n] < 0.15
        length = 4.6 + 0.9 * u[2][n] if big else 3.8 + 1.1 * u[2][n]
        width = 1.9 + 0.15 * u[3][n] if big else 1.68 + 0.22 * u[3][n]
        height = 1.9 + 0.4 * u[4][n] if big else 1.38 + 0.25 * u[4][n]
        color = as_rgb(CAR_COLORS[int(u[5][n] * len(CAR_COLORS))])
        yaw = slots.yaw[i] + (u[6][n] - 0.5) * 0.06 + (np.pi if u[7][n] < 0.2 else 0.0)
        shift = (u[6][n] - 0.5) * 0.8
        cx = slots.x[i] + np.cos(slots.yaw[i]) * shift
        cy = slots.y[i] + np.sin(slots.yaw[i]) * shift
        inst = int(hash_u64(seed, 14, i, epoch[n]) % np.uint64(65534)) + 1
        label = int(Label.CAR) | (inst << INSTANCE_SHIFT)
        refl = 0.25 + 0.5 * float(u[4][n])
        body_top = height * (0.85 if big else 0.6)
        b.box(cx, cy, length / 2, width / 2, yaw, 0.0, body_top, label=label, mat=Mat.CAR, color=color,
              params=(length, body_top), seed=inst, refl=refl)
        cab_len = length * (0.8 if big else 0.52)
        off = -0.1 * length if not big else -0.05 * length
        b.box(cx + np.cos(yaw) * off, cy + np.sin(yaw) * off, cab_len / 2, width / 2 - 0.08, yaw, body_top, height,
              label=label, mat=Mat.CABIN, color=color, params=(cab_len, height - body_top), seed=inst, refl=0.08)
    return b.build()
