"""Placing buildings and street furniture: off the streets, apart from each other, seeded."""
from __future__ import annotations

from typing import Any

import numpy as np

from . import ground as g
from .labels import Label, Mat
from .world import ObjectsBuilder, as_rgb

FACADE_COLORS = np.array([
    (0.76, 0.70, 0.58), (0.55, 0.27, 0.20), (0.45, 0.22, 0.17), (0.60, 0.60, 0.58), (0.85, 0.84, 0.80),
    (0.35, 0.36, 0.38), (0.85, 0.76, 0.50), (0.55, 0.65, 0.72), (0.62, 0.70, 0.60), (0.72, 0.62, 0.45),
    (0.30, 0.42, 0.52), (0.80, 0.60, 0.50),
], dtype=np.float32)
SIGN_COLORS = np.array([(0.75, 0.08, 0.08), (0.08, 0.25, 0.70), (0.92, 0.76, 0.10), (0.90, 0.90, 0.88),
                        (0.08, 0.48, 0.25)], dtype=np.float32)
FOLIAGE_COLORS = np.array([(0.16, 0.30, 0.10), (0.22, 0.36, 0.12), (0.12, 0.24, 0.10), (0.30, 0.36, 0.14)],
                          dtype=np.float32)

BUILDING_GROUND = (g.TERRAIN, g.PLAZA)
FURNITURE_GROUND = (g.SIDEWALK, g.TERRAIN, g.PLAZA, g.KERB)
SLOT_GROUND = (g.ROAD_EDGE, g.PARKING, g.PARKING_LINE)
ANY_GROUND = tuple(range(g.N_CODES))
FREE, BUILDING, PROP, SLOT = 0, 1, 2, 3


class Placer:
    """Collects the city's prisms, lamps and parking slots while checking where they go."""

    def __init__(self, painter: g.GroundPainter, *, seed: int, res: float = 0.5,
                 floors: tuple[float, float] = (1.3, 0.6)) -> None:
        self.painter, self.seed, self.res = painter, seed, res
        self.floors = floors  # log-normal (mu, sigma) of the storey count
        self.nx = int(np.ceil(painter.nx * painter.res / res))
        self.ny = int(np.ceil(painter.ny * painter.res / res))
        self.occ = np.zeros((self.ny, self.nx), dtype=np.uint8)
        self.objects = ObjectsBuilder()
        self.lamps: list[tuple[float, float, float]] = []
        self.slots: list[tuple[float, float, float]] = []
        self.count = 0

    # --------------------------------------------------------------- footprints
    def _samples(self, cx: float, cy: float, hx: float, hy: float, yaw: float,
                 margin: float) -> tuple[np.ndarray, np.ndarray]:
        ax = np.linspace(-hx - margin, hx + margin, max(int(np.ceil(2 * (hx + margin) / 0.45)) + 1, 3))
        ay = np.linspace(-hy - margin, hy + margin, max(int(np.ceil(2 * (hy + margin) / 0.45)) + 1, 3))
        lx, ly = np.meshgrid(ax, ay)
        c, s = np.cos(yaw), np.sin(yaw)
        return (cx + c * lx - s * ly).ravel(), (cy + s * lx + c * ly).ravel()

    def _cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ix = np.floor((x - self.painter.x0) / self.res).astype(np.int64)
        iy = np.floor((y - self.painter.y0) / self.res).astype(np.int64)
        ok = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        return ix, iy, ok

    def ground_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        p = self.painter
        ix = np.floor((np.asarray(x) - p.x0) / p.res).astype(np.int64)
        iy = np.floor((np.asarray(y) - p.y0) / p.res).astype(np.int64)
        ok = (ix >= 0) & (ix < p.nx) & (iy >= 0) & (iy < p.ny)
        out = np.full(ix.shape, 255, dtype=np.uint8)
        out[ok] = p.codes[iy[ok], ix[ok]]
        return out

    def fits(self, cx: float, cy: float, hx: float, hy: float, yaw: float, *, ground: tuple[int, ...],
             margin: float, blocked: tuple[int, ...] = (BUILDING, PROP, SLOT)) -> bool:
        """Footprint (grown by margin) lies on allowed ground and on no blocked occupancy."""
        x, y = self._samples(cx, cy, hx, hy, yaw, margin)
        allowed = np.zeros(256, dtype=bool)
        allowed[list(ground)] = True
        if not allowed[self.ground_at(x, y)].all():
            return False
        ix, iy, ok = self._cells(x, y)
        if not ok.all():
            return False
        stop = np.zeros(256, dtype=bool)
        stop[list(blocked)] = True
        return not stop[self.occ[iy, ix]].any()

    def mark(self, cx: float, cy: float, hx: float, hy: float, yaw: float, value: int) -> None:
        x, y = self._samples(cx, cy, hx, hy, yaw, 0.0)
        ix, iy, ok = self._cells(x, y)
        self.occ[iy[ok], ix[ok]] = value

    def keep_clear(self, xy: np.ndarray, radius: float) -> None:
        """Reserve a corridor of ``radius`` metres around the points xy (N x 2): nothing is placed there."""
        step = self.res * 0.8
        off = np.arange(-radius, radius + 1e-9, step)
        ox, oy = np.meshgrid(off, off)
        disc = ox ** 2 + oy ** 2 <= radius ** 2
        ox, oy = ox[disc], oy[disc]
        for chunk in range(0, len(xy), 2048):
            pts = xy[chunk:chunk + 2048]
            ix, iy, ok = self._cells((pts[:, 0:1] + ox).ravel(), (pts[:, 1:2] + oy).ravel())
            cells = self.occ[iy[ok], ix[ok]]
            self.occ[iy[ok], ix[ok]] = np.where(cells == FREE, PROP, cells)

    # --------------------------------------------------------------- buildings
    def building(self, cx: float, cy: float, yaw: float, frontage: float, depth: float, back: float,
                 rng: np.random.Generator, *, setback: float = 0.0) -> bool:
        """A building whose front faces the street (``back`` = +1/-1: which side of its local y is away)."""
        hx, hy = frontage / 2, depth / 2
        if not self.fits(cx, cy, hx, hy, yaw, ground=BUILDING_GROUND, margin=0.3):
            return False
        self.count += 1
        bid = self.count
        storeys = int(np.clip(np.round(np.exp(rng.normal(*self.floors))), 1, 30))
        floor_h = float(rng.uniform(2.9, 3.8))
        height = storeys * floor_h + float(rng.uniform(0.4, 1.2))
        base = FACADE_COLORS[int(rng.integers(len(FACADE_COLORS)))]
        color = as_rgb(np.clip(base + rng.uniform(-0.05, 0.05, 3), 0.05, 0.95))
        style = float(rng.choice([0, 0, 0, 1, 2, 2]))  # 0 punched windows, 1 ribbon windows, 2 shop front
        params = (float(rng.uniform(2.2, 4.2)), floor_h, float(rng.uniform(0.35, 0.7)), float(rng.uniform(0.4, 0.65)),
                  float(rng.uniform(3.5, 4.8)) if style == 2 else floor_h, style)
        mat = Mat.WALL if rng.uniform() < 0.08 else Mat.FACADE
        refl = float(rng.uniform(0.2, 0.45))
        kw: dict[str, Any] = dict(label=int(Label.BUILDING), mat=mat, color=color, params=params, seed=bid, refl=refl)
        self.objects.box(cx, cy, hx, hy, yaw, 0.0, height, **kw)
        self.mark(cx, cy, hx, hy, yaw, BUILDING)
        c, s = np.cos(yaw), np.sin(yaw)
        ux, uy, nx_, ny_ = c, s, -s * back, c * back  # along the street; away from it
        self.painter.box(cx - nx_ * setback / 2, cy - ny_ * setback / 2, hx + 0.5, hy + setback / 2 + 0.5, yaw, g.PLAZA)
        if rng.uniform() < 0.35 and frontage > 10:  # wing behind: an L-shaped footprint
            wf = frontage * float(rng.uniform(0.35, 0.6))
            wd = float(rng.uniform(6.0, 14.0))
            shift = (frontage - wf) / 2 * float(rng.choice([-1.0, 1.0]))
            wx = cx + ux * shift + nx_ * (hy + wd / 2)
            wy = cy + uy * shift + ny_ * (hy + wd / 2)
            if self.fits(wx, wy, wf / 2, wd / 2, yaw, ground=BUILDING_GROUND, margin=0.2):
                wh = max(3.0, height * float(rng.uniform(0.5, 1.3)))
                self.objects.box(wx, wy, wf / 2, wd / 2, yaw, 0.0, wh, **kw)
                self.mark(wx, wy, wf / 2, wd / 2, yaw, BUILDING)
        if storeys >= 6 and rng.uniform() < 0.35:  # set-back top storeys
            k = float(rng.uniform(0.55, 0.8))
            extra = floor_h * int(rng.integers(2, 8))
            self.objects.box(cx + nx_ * hy * (1 - k), cy + ny_ * hy * (1 - k), hx * k, hy * k, yaw, height,
                             height + extra, **kw)
        return True

    # --------------------------------------------------------------- furniture
    def tree(self, x: float, y: float, rng: np.random.Generator, *, max_radius: float = 3.5) -> bool:
        trunk_r = float(rng.uniform(0.12, 0.25))
        if max_radius < 1.0 or not self.fits(x, y, trunk_r, trunk_r, 0.0, ground=FURNITURE_GROUND, margin=0.7):
            return False
        r = float(rng.uniform(1.0, max_radius))
        if not self.fits(x, y, r, r, 0.0, ground=ANY_GROUND, margin=0.0, blocked=(BUILDING,)):
            r = 1.0
        z0 = float(rng.uniform(2.4, 3.4))
        z1 = z0 + float(rng.uniform(max(2.0, r), 2.5 * r + 1.5))
        leaf = FOLIAGE_COLORS[int(rng.integers(len(FOLIAGE_COLORS)))] * rng.uniform(0.85, 1.15)
        color = as_rgb(leaf)
        self.count += 1
        self.objects.cylinder(x, y, trunk_r, 0.0, z0 + 0.6, label=int(Label.TRUNK), mat=Mat.TRUNK,
                              color=(0.28, 0.2, 0.14), seed=self.count, refl=0.25)
        self.objects.cylinder(x, y, r, z0, z1, label=int(Label.VEGETATION), mat=Mat.FOLIAGE, color=color,
                              dome=min(r, 0.5 * (z1 - z0)), seed=self.count, refl=0.35)
        self.mark(x, y, trunk_r + 0.3, trunk_r + 0.3, 0.0, PROP)
        return True

    def lamp(self, x: float, y: float, to_road: float, rng: np.random.Generator) -> bool:
        if not self.fits(x, y, 0.15, 0.15, 0.0, ground=FURNITURE_GROUND, margin=0.35):
            return False
        h = float(rng.uniform(6.5, 9.0))
        self.count += 1
        kw: dict[str, Any] = dict(label=int(Label.POLE), seed=self.count, refl=0.45)
        self.objects.cylinder(x, y, 0.11, 0.0, h, mat=Mat.POLE, color=(0.42, 0.43, 0.45), **kw)
        hx, hy = x + 1.3 * np.cos(to_road), y + 1.3 * np.sin(to_road)
        self.objects.box(hx, hy, 0.75, 0.16, to_road, h - 0.3, h, mat=Mat.LAMP, color=(0.5, 0.5, 0.52), **kw)
        self.lamps.append((hx, hy, h - 0.3))
        self.mark(x, y, 0.4, 0.4, 0.0, PROP)
        return True

    def sign(self, x: float, y: float, facing: float, rng: np.random.Generator) -> bool:
        if not self.fits(x, y, 0.1, 0.1, 0.0, ground=FURNITURE_GROUND, margin=0.5):
            return False
        z = float(rng.uniform(2.0, 2.6))
        size = float(rng.uniform(0.55, 0.9))
        self.count += 1
        self.objects.cylinder(x, y, 0.04, 0.0, z + size * 0.9, label=int(Label.POLE), mat=Mat.POLE,
                              color=(0.55, 0.56, 0.58), seed=self.count, refl=0.45)
        color = as_rgb(SIGN_COLORS[int(rng.integers(len(SIGN_COLORS)))])
        self.objects.box(x + 0.06 * np.cos(facing), y + 0.06 * np.sin(facing), 0.03, size / 2, facing, z, z + size,
                         label=int(Label.TRAFFIC_SIGN), mat=Mat.SIGN, color=color, params=(size,), seed=self.count,
                         refl=0.95)
        self.mark(x, y, 0.3, 0.3, 0.0, PROP)
        return True

    def fence(self, a: np.ndarray, b: np.ndarray, rng: np.random.Generator, *, height: float | None = None) -> None:
        d = np.asarray(b, float) - np.asarray(a, float)
        length = float(np.hypot(*d))
        if length < 0.5:
            return
        h = float(rng.uniform(1.1, 2.0)) if height is None else height
        c = (np.asarray(a, float) + np.asarray(b, float)) / 2
        self.count += 1
        self.objects.box(c[0], c[1], length / 2, 0.04, float(np.arctan2(d[1], d[0])), 0.0, h, label=int(Label.FENCE),
                         mat=Mat.FENCE, color=(0.40, 0.45, 0.40), params=(float(rng.uniform(0.15, 0.4)),),
                         seed=self.count, refl=0.3)

    def slot(self, x: float, y: float, yaw: float, *, length: float = 5.2, width: float = 2.0) -> bool:
        if not self.fits(x, y, length / 2, width / 2, yaw, ground=SLOT_GROUND, margin=0.0):
            return False
        self.slots.append((x, y, yaw))
        self.mark(x, y, length / 2 - 0.2, width / 2 - 0.2, yaw, SLOT)
        return True
