"""Seeded city layouts: a grid city around a street graph, or a city built along a given path."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import ground as g
from .hashing import rng_for
from .props import BUILDING as RESERVED
from .props import Placer
from .route import Path, StreetGraph, StreetSpec
from .world import ParkingSlots, World

PATH_STREET = StreetSpec(lanes=1, parking=True, sidewalk=3.5, trees=True)  # the kitti00 road: 3 lanes + parking
PATH_HALF = 1.5 * g.LANE_WIDTH + g.PARKING_WIDTH
PATH_MARKS = ((0.5 * g.LANE_WIDTH, "dashed"), (1.5 * g.LANE_WIDTH, "solid"))


@dataclass(frozen=True)
class CityConfig:
    """Knobs of the generated city."""

    ground_res: float = 0.1  # metres per ground-map cell
    margin: float = 90.0  # city beyond the outermost street / path, metres
    floors: tuple[float, float] = (1.3, 0.6)  # log-normal (mu, sigma) of storeys per building
    lamp_spacing: tuple[float, float] = (24.0, 34.0)
    tree_spacing: tuple[float, float] = (8.0, 14.0)
    parking_period_s: float = 120.0  # mean time a parked car stays
    parking_occupancy: float = 0.55


class _Line:
    """Arc-length parametrised polyline: point and unit tangent at s."""

    def __init__(self, xy: np.ndarray) -> None:
        self.xy = np.asarray(xy, dtype=np.float64)
        self.s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(self.xy, axis=0).T))])
        self.length = float(self.s[-1])

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        i = int(np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2))
        d = self.xy[i + 1] - self.xy[i]
        seg = max(float(np.hypot(*d)), 1e-9)
        u = d / seg
        return self.xy[i] + u * (s - self.s[i]), u


def _furnish(placer: Placer, line: _Line, spec: StreetSpec, half: float, rng: np.random.Generator, cfg: CityConfig, *,
             s0: float = 0.0, s1: float | None = None, signs_every: float | None = None) -> None:
    """Lamps, trees, signs and kerb-side parking slots on both sides of a street line."""
    s1 = line.length if s1 is None else s1
    for side in (1.0, -1.0):
        s = s0 + rng.uniform(0, cfg.lamp_spacing[0])
        while s < s1:
            p, u = line.at(s)
            n = np.array([-u[1], u[0]]) * side
            q = p + n * (half + 0.75)
            placer.lamp(q[0], q[1], float(np.arctan2(-n[1], -n[0])), rng)
            s += rng.uniform(*cfg.lamp_spacing)
        if spec.trees:
            lat = half + min(1.3, spec.sidewalk / 2)
            max_r = min(3.5, lat - half + (g.PARKING_WIDTH if spec.parking else 0.6))
            s = s0 + rng.uniform(0, cfg.tree_spacing[0])
            while s < s1:
                p, u = line.at(s)
                q = p + np.array([-u[1], u[0]]) * side * lat
                placer.tree(q[0], q[1], rng, max_radius=max_r)
                s += rng.uniform(*cfg.tree_spacing)
        if spec.parking:
            s = s0 + rng.uniform(2.0, 4.0)
            while s < s1:
                p, u = line.at(s)
                q = p + np.array([-u[1], u[0]]) * side * (half - 1.2)
                placer.slot(q[0], q[1], float(np.arctan2(u[1], u[0])), width=1.8)
                s += rng.uniform(5.8, 6.6)
        if signs_every:
            s = s0 + rng.uniform(0, signs_every)
            while s < s1:
                p, u = line.at(s)
                q = p + np.array([-u[1], u[0]]) * side * (half + 0.45)
                facing = float(np.arctan2(u[1], u[0])) + (np.pi if side < 0 else 0.0)
                placer.sign(q[0], q[1], facing, rng)
                s += rng.uniform(0.6, 1.4) * signs_every


def _frontage(placer: Placer, line: _Line, offset: float, rng: np.random.Generator, *, s0: float = 0.0,
              s1: float | None = None, side: float, depth: tuple[float, float] = (10.0, 24.0),
              storey_boost: float = 0.0, kinds: tuple[float, float, float] = (0.8, 0.12, 0.08)) -> None:
    """Buildings (and some parks / parking lots) along one side of a line, fronts ``offset`` from it."""
    s1 = line.length if s1 is None else s1
    s = s0 + rng.uniform(0.0, 5.0)
    mu, sigma = placer.floors
    placer.floors = (mu + storey_boost, sigma)
    kind, kind_until = 0, s
    while s < s1:
        if s >= kind_until:
            kind = int(rng.choice(3, p=np.asarray(kinds) / sum(kinds)))
            kind_until = s + rng.uniform(40.0, 120.0)
        f = float(rng.uniform(9.0, 28.0))
        p, u = line.at(min(s + f / 2, s1))
        n = np.array([-u[1], u[0]]) * side
        yaw = float(np.arctan2(u[1], u[0]))
        if kind == 0:
            setback = 0.0 if rng.uniform() < 0.5 else float(rng.uniform(1.0, 5.0))
            d = float(rng.uniform(*depth))
            c = p + n * (offset + 0.4 + setback + d / 2)
            if not placer.building(c[0], c[1], yaw, f, d, side, rng, setback=setback + 0.4):
                c = p + n * (offset + 0.4 + setback + d * 0.3)
                placer.building(c[0], c[1], yaw, f * 0.6, d * 0.6, side, rng, setback=setback + 0.4)
            s += f + (0.0 if rng.uniform() < 0.55 else float(rng.uniform(1.5, 8.0)))
        elif kind == 1:  # park strip: trees on grass
            for _ in range(2):
                c = p + n * (offset + rng.uniform(2.0, 25.0)) + u * rng.uniform(-f / 2, f / 2)
                placer.tree(c[0], c[1], rng)
            s += f
        else:  # parking lot with perpendicular slots behind a low fence
            c = p + n * (offset + 8.0)
            if placer.fits(c[0], c[1], f / 2, 6.0, yaw, ground=(g.TERRAIN, g.PLAZA), margin=0.3):
                placer.painter.box(c[0], c[1], f / 2, 6.0, yaw, g.PARKING)
                row = p + n * (offset + 5.0)
                placer.painter.box(row[0], row[1], f / 2, 2.6, yaw, g.PARKING, lines=2.7)
                for k in range(int(f // 2.7)):
                    q = row + u * (-f / 2 + 1.35 + 2.7 * k)
                    placer.slot(q[0], q[1], yaw + np.pi / 2, length=5.0, width=2.2)
                placer.mark(c[0], c[1], f / 2, 6.0, yaw, RESERVED)
                back = c + n * 6.2
                placer.fence(back - u * f / 2, back + u * f / 2, rng, height=1.2)
            s += f + 2.0
    placer.floors = (mu, sigma)


def _finish(placer: Placer, seed: int, cfg: CityConfig) -> World:
    ground = placer.painter.finish(np.asarray(placer.lamps, dtype=np.float64).reshape(-1, 3))
    slots = np.asarray(placer.slots, dtype=np.float64).reshape(-1, 3)
    return World(objects=placer.objects.build(), ground=ground,
                 slots=ParkingSlots(slots[:, 0].copy(), slots[:, 1].copy(), slots[:, 2].copy()),
                 lamps=np.asarray(placer.lamps, dtype=np.float64).reshape(-1, 3), seed=seed,
                 parking_period_s=cfg.parking_period_s, parking_occupancy=cfg.parking_occupancy)


def _street_marks(spec: StreetSpec) -> tuple[tuple[float, str], ...]:
    marks: list[tuple[float, str]] = [(0.18, "yellow")] if spec.lanes >= 2 else [(0.0, "dashed")]
    marks += [(k * g.LANE_WIDTH, "dashed") for k in range(1, spec.lanes)]
    if spec.parking:
        marks.append((spec.lanes * g.LANE_WIDTH, "solid"))
    return tuple(marks)


def grid_city(graph: StreetGraph, *, seed: int, config: CityConfig | None = None, keep_clear: np.ndarray | None = None
              ) -> World:
    """Streets of the graph with sidewalks and furniture; blocks of buildings, parks and parking lots.

    ``keep_clear`` (N x 2, e.g. the driven path) gets no props or parked cars within 2.2 m.
    """
    cfg = config or CityConfig()
    rng = rng_for(seed, 20)
    pts = graph.nodes.reshape(-1, 2)
    lo, hi = pts.min(axis=0) - cfg.margin, pts.max(axis=0) + cfg.margin
    painter = g.GroundPainter(xmin=lo[0], ymin=lo[1], xmax=hi[0], ymax=hi[1], res=cfg.ground_res)
    placer = Placer(painter, seed=seed, floors=cfg.floors)
    nx, ny = graph.shape

    def crossing(n: tuple[int, int], a: tuple[int, int], b: tuple[int, int]) -> float:
        other = graph.cols[n[0]] if a[1] == b[1] else graph.rows[n[1]]
        return other.half_width + other.sidewalk + 4.5

    edges = graph.edges()
    for a, b in edges:
        spec = graph.spec(a, b)
        painter.street(graph.pos(a), graph.pos(b), half=spec.half_width,
                       parking=g.PARKING_WIDTH if spec.parking else 0.0, sidewalk=spec.sidewalk,
                       marks=_street_marks(spec), cut0=crossing(a, a, b), cut1=crossing(b, a, b), crosswalks=True)
    # blocks: parks and parking lots first (they reserve ground), buildings after
    kinds = {}
    for i in range(nx - 1):
        for j in range(ny - 1):
            kinds[i, j] = int(rng.choice(3, p=[0.74, 0.14, 0.12]))
            c4 = graph.nodes[i:i + 2, j:j + 2].reshape(4, 2)
            centre = c4.mean(axis=0)
            ax = (graph.nodes[i + 1, j] - graph.nodes[i, j]) + (graph.nodes[i + 1, j + 1] - graph.nodes[i, j + 1])
            yaw = float(np.arctan2(ax[1], ax[0]))
            inset_x = max(s.half_width + s.sidewalk for s in (graph.cols[i], graph.cols[i + 1])) + 1.0
            inset_y = max(s.half_width + s.sidewalk for s in (graph.rows[j], graph.rows[j + 1])) + 1.0
            hx = np.hypot(*ax) / 4 - inset_x
            ay = (graph.nodes[i, j + 1] - graph.nodes[i, j]) + (graph.nodes[i + 1, j + 1] - graph.nodes[i + 1, j])
            hy = np.hypot(*ay) / 4 - inset_y
            if hx < 8 or hy < 8:
                kinds[i, j] = 0
            if kinds[i, j] == 1:
                _park(placer, centre, hx, hy, yaw, rng)
            elif kinds[i, j] == 2:
                _parking_lot(placer, centre, hx, hy, yaw, rng)
    for a, b in edges:
        spec = graph.spec(a, b)
        line = _Line(np.stack([graph.pos(a), graph.pos(b)]))
        offset = spec.half_width + spec.sidewalk
        for side in (1.0, -1.0):
            _frontage(placer, line, offset, rng, side=side, kinds=(1.0, 0.0, 0.0))
            _frontage(placer, line, offset + rng.uniform(26.0, 40.0), rng, side=side, depth=(12.0, 30.0),
                      storey_boost=0.3, kinds=(1.0, 0.0, 0.0))
    if keep_clear is not None:
        placer.keep_clear(np.asarray(keep_clear, dtype=np.float64), 2.2)
    for a, b in edges:
        spec = graph.spec(a, b)
        line = _Line(np.stack([graph.pos(a), graph.pos(b)]))
        _furnish(placer, line, spec, spec.half_width, rng, cfg)
        for end, sgn in ((0.0, 1.0), (line.length, -1.0)):  # a sign before each intersection, right side
            p, u = line.at(end)
            cut = crossing(a if sgn > 0 else b, a, b) - 3.0
            n_right = np.array([u[1], -u[0]]) * sgn
            q = p + u * sgn * cut + n_right * (spec.half_width + 0.45)
            if rng.uniform() < 0.7:
                placer.sign(q[0], q[1], float(np.arctan2(-u[1] * sgn, -u[0] * sgn)), rng)
    return _finish(placer, seed, cfg)


def _park(placer: Placer, centre: np.ndarray, hx: float, hy: float, yaw: float, rng: np.random.Generator) -> None:
    c, s = np.cos(yaw), np.sin(yaw)
    placer.painter.box(centre[0], centre[1], hx, 1.5, yaw + float(rng.uniform(-0.6, 0.6)), g.PLAZA)  # a path
    for _ in range(int(hx * hy / 45)):
        lx, ly = rng.uniform(-hx, hx), rng.uniform(-hy, hy)
        placer.tree(centre[0] + c * lx - s * ly, centre[1] + s * lx + c * ly, rng, max_radius=4.5)
    placer.mark(centre[0], centre[1], hx, hy, yaw, RESERVED)


def _parking_lot(placer: Placer, centre: np.ndarray, hx: float, hy: float, yaw: float,
                 rng: np.random.Generator) -> None:
    c, s = np.cos(yaw), np.sin(yaw)
    u, n = np.array([c, s]), np.array([-s, c])
    placer.painter.box(centre[0], centre[1], hx, hy, yaw, g.PARKING)
    y = -hy + 3.0
    while y + 5.2 < hy - 1.0:
        for row_y in (y + 2.6, y + 7.8):
            if row_y + 2.6 > hy - 1.0:
                break
            row = centre + n * row_y
            placer.painter.box(row[0], row[1], hx - 3.0, 2.6, yaw, g.PARKING, lines=2.7)
            for k in range(int((2 * hx - 6.0) // 2.7)):
                q = row + u * (-hx + 3.0 + 1.35 + 2.7 * k)
                placer.slot(q[0], q[1], yaw + np.pi / 2, length=5.0, width=2.2)
        y += 2 * 5.2 + 7.0
    corners = [centre + u * sx * hx + n * sy * hy for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        mid = (a + b) / 2  # leave an entrance in the middle of each side
        gap = (b - a) / np.hypot(*(b - a)) * 3.0
        placer.fence(a, mid - gap, rng, height=1.3)
        placer.fence(mid + gap, b, rng, height=1.3)
    placer.mark(centre[0], centre[1], hx, hy, yaw, RESERVED)


def _simplify(xy: np.ndarray, tol: float) -> np.ndarray:
    """Indices kept by Douglas-Peucker simplification (iterative)."""
    keep = np.zeros(len(xy), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(xy) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = xy[i], xy[j]
        d = b - a
        length = np.hypot(*d)
        rel = xy[i + 1:j] - a
        dist = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / length if length > 1e-9 else np.hypot(*rel.T)
        k = int(np.argmax(dist))
        if dist[k] > tol:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return np.nonzero(keep)[0]


def path_city(path: Path, *, seed: int, config: CityConfig | None = None, max_piece: float = 20.0,
              keep_clear: np.ndarray | None = None) -> World:
    """A city around a driven path: a road centred on it, sidewalks, furniture and buildings beside.

    Where the path comes back along a street it has already painted, the street is kept as
    it is (a revisit may drive a little off its centre); props never overlap, so revisited
    streets get no duplicates. ``keep_clear`` (N x 2, e.g. the path after lane changes) gets
    no props or parked cars within 2.2 m, like the path itself.
    """
    cfg = config or CityConfig(floors=(1.0, 0.45))
    rng = rng_for(seed, 21)
    lo, hi = path.xy.min(axis=0) - cfg.margin, path.xy.max(axis=0) + cfg.margin
    painter = g.GroundPainter(xmin=lo[0], ymin=lo[1], xmax=hi[0], ymax=hi[1], res=cfg.ground_res)
    placer = Placer(painter, seed=seed, floors=cfg.floors)
    idx = _simplify(path.xy, 0.1)
    pts = path.xy[idx]
    road_codes = (g.ROAD, g.ROAD_EDGE, g.MARK_WHITE, g.MARK_YELLOW)
    s_acc = 0.0
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        length = float(np.hypot(*(b - a)))
        n = max(int(np.ceil(length / max_piece)), 1)
        for k in range(n):
            pa, pb = a + (b - a) * k / n, a + (b - a) * (k + 1) / n
            probe = pa + (pb - pa) * np.array([[0.2], [0.5], [0.8]])
            if not np.isin(placer.ground_at(probe[:, 0], probe[:, 1]), road_codes).all():
                painter.street(pa, pb, half=PATH_HALF, parking=g.PARKING_WIDTH, sidewalk=PATH_STREET.sidewalk,
                               marks=PATH_MARKS, s_offset=s_acc)
            s_acc += length / n
    line = _Line(path.xy)
    offset = PATH_HALF + PATH_STREET.sidewalk
    for side in (1.0, -1.0):
        _frontage(placer, line, offset, rng, side=side)
        _frontage(placer, line, offset + 30.0, rng, side=side, depth=(12.0, 30.0), storey_boost=0.3,
                  kinds=(0.85, 0.15, 0.0))
    placer.keep_clear(path.xy, 2.2)
    if keep_clear is not None:
        placer.keep_clear(np.asarray(keep_clear, dtype=np.float64), 2.2)
    _furnish(placer, line, PATH_STREET, PATH_HALF, rng, cfg, signs_every=70.0)
    return _finish(placer, seed, cfg)
