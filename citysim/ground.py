"""Ground codes (what covers the ground at a point) and the raster painter that makes them."""
from __future__ import annotations

import numpy as np

from .labels import Label
from .world import GroundMap

TERRAIN, ROAD, ROAD_EDGE, MARK_WHITE, MARK_YELLOW, CROSSWALK, SIDEWALK, KERB, PARKING, PARKING_LINE, PLAZA = range(11)
N_CODES = 11

#: ground code -> SemanticKITTI label
CODE_LABEL = np.array([
    Label.TERRAIN, Label.ROAD, Label.ROAD, Label.LANE_MARKING, Label.LANE_MARKING, Label.LANE_MARKING,
    Label.SIDEWALK, Label.SIDEWALK, Label.PARKING, Label.PARKING, Label.OTHER_GROUND,
], dtype=np.uint32)

#: ground code -> albedo (RGB, 0..1)
CODE_COLOR = np.array([
    (0.28, 0.36, 0.16),  # terrain: grass
    (0.27, 0.27, 0.28),  # road asphalt
    (0.25, 0.25, 0.26),  # parking strip
    (0.82, 0.82, 0.80),  # white marking
    (0.80, 0.64, 0.18),  # yellow marking
    (0.80, 0.80, 0.78),  # crosswalk
    (0.55, 0.54, 0.52),  # sidewalk
    (0.68, 0.67, 0.65),  # kerb
    (0.22, 0.22, 0.23),  # parking lot
    (0.78, 0.78, 0.76),  # parking line
    (0.50, 0.47, 0.43),  # plaza / lot concrete
], dtype=np.float32)

#: ground code -> texture amplitude (fraction of albedo)
CODE_TEXTURE = np.array([0.35, 0.14, 0.14, 0.08, 0.08, 0.08, 0.10, 0.06, 0.14, 0.08, 0.12], dtype=np.float32)

#: ground code -> LiDAR reflectivity
CODE_REFL = np.array([0.18, 0.08, 0.08, 0.55, 0.5, 0.55, 0.2, 0.25, 0.08, 0.5, 0.2], dtype=np.float32)

# painting priority: a cell takes a new code only if its priority is higher than the old one's;
# code 255 means 'leave the cell'
PRIORITY = np.zeros(256, dtype=np.uint8)
PRIORITY[:N_CODES] = [1, 8, 7, 9, 9, 9, 5, 6, 3, 4, 2]

LANE_WIDTH = 3.5
PARKING_WIDTH = 2.4


class GroundPainter:
    """Paints streets, lots and patches into a ground-code raster."""

    def __init__(self, *, xmin: float, ymin: float, xmax: float, ymax: float, res: float) -> None:
        self.x0, self.y0, self.res = float(xmin), float(ymin), float(res)
        self.nx = int(np.ceil((xmax - xmin) / res))
        self.ny = int(np.ceil((ymax - ymin) / res))
        self.codes = np.zeros((self.ny, self.nx), dtype=np.uint8)
        self.prio = np.full((self.ny, self.nx), PRIORITY[TERRAIN], dtype=np.uint8)

    def _window(self, xmin: float, xmax: float, ymin: float, ymax: float):
        i0 = max(int(np.floor((xmin - self.x0) / self.res)), 0)
        i1 = min(int(np.ceil((xmax - self.x0) / self.res)), self.nx)
        j0 = max(int(np.floor((ymin - self.y0) / self.res)), 0)
        j1 = min(int(np.ceil((ymax - self.y0) / self.res)), self.ny)
        if i1 <= i0 or j1 <= j0:
            return None
        x = (self.x0 + (np.arange(i0, i1) + 0.5) * self.res)[None, :].astype(np.float32)  # 1 x w
        y = (self.y0 + (np.arange(j0, j1) + 0.5) * self.res)[:, None].astype(np.float32)  # h x 1
        return (slice(j0, j1), slice(i0, i1)), x, y

    def _apply(self, sl, code: np.ndarray) -> None:
        """Write code (h x w, 255 = leave) where its priority is higher than the cell's."""
        new_p = PRIORITY[code]
        sub_p = self.prio[sl]
        win = new_p > sub_p
        self.codes[sl][win] = code[win]
        sub_p[win] = new_p[win]

    def street(self, a: np.ndarray, b: np.ndarray, *, half: float, parking: float, sidewalk: float,
               marks: tuple[tuple[float, str], ...], cut0: float = 0.0, cut1: float = 0.0, s_offset: float = 0.0,
               crosswalks: bool = False) -> None:
        """One straight street a -> b (round ends), ``half`` metres from centre line to kerb.

        ``parking`` metres next to each kerb are a parking strip; ``marks`` are lines at
        those lateral distances on both sides ('dashed', 'solid', 'yellow'), drawn for
        along-distances in [cut0, length - cut1] so that intersections stay free.
        ``s_offset`` phases the dashes of consecutive pieces of one polyline.
        """
        a, b = np.asarray(a, float), np.asarray(b, float)
        reach = half + sidewalk
        win = self._window(min(a[0], b[0]) - reach, max(a[0], b[0]) + reach,
                           min(a[1], b[1]) - reach, max(a[1], b[1]) + reach)
        if win is None:
            return
        sl, x, y = win
        d = b - a
        length = float(np.hypot(*d))
        ux, uy = d / max(length, 1e-9)
        rx, ry = x - np.float32(a[0]), y - np.float32(a[1])
        ux, uy = np.float32(ux), np.float32(uy)
        s = rx * ux + ry * uy  # along
        lat = ry * ux - rx * uy  # left of the direction a -> b
        dist = np.hypot(s - np.clip(s, 0.0, length), lat)
        if not (dist <= reach).any():
            return
        code = np.full(dist.shape, 255, dtype=np.uint8)
        code[dist <= reach] = SIDEWALK
        code[(dist > half) & (dist <= half + 0.3)] = KERB
        road = dist <= half
        code[road] = ROAD
        alat = np.abs(lat)
        if parking > 0:
            code[road & (dist > half - parking)] = ROAD_EDGE
        inner = road & (s >= cut0) & (s <= length - cut1)
        dashed = ((s + s_offset) % 9.0) < 3.0
        for offset, style in marks:
            line = inner & (np.abs(alat - offset) < 0.075)
            if style == "dashed":
                line &= dashed
            code[line] = MARK_YELLOW if style == "yellow" else MARK_WHITE
        if crosswalks:
            band = road & (alat < half - 0.4) & ((lat % 1.2) < 0.6)
            code[band & (s >= cut0 - 4.0) & (s < cut0 - 0.8)] = CROSSWALK
            code[band & (s <= length - cut1 + 4.0) & (s > length - cut1 + 0.8)] = CROSSWALK
        self._apply(sl, code)

    def box(self, cx: float, cy: float, hx: float, hy: float, yaw: float, code: int, *, lines: float = 0.0) -> None:
        """An oriented rectangle of one code; ``lines`` > 0 draws parking-slot lines that far apart."""
        c, s = np.cos(yaw), np.sin(yaw)
        ex, ey = abs(c) * hx + abs(s) * hy, abs(s) * hx + abs(c) * hy
        win = self._window(cx - ex, cx + ex, cy - ey, cy + ey)
        if win is None:
            return
        sl, x, y = win
        lx = (x - cx) * c + (y - cy) * s
        ly = -(x - cx) * s + (y - cy) * c
        inside = (np.abs(lx) <= hx) & (np.abs(ly) <= hy)
        out = np.where(inside, np.uint8(code), np.uint8(255))
        if lines > 0:
            stripe = inside & ((((lx + hx) % lines) < 0.12) | (np.abs(np.abs(ly) - hy) < 0.12))
            out[stripe] = PARKING_LINE
        self._apply(sl, out)

    def finish(self, lamps: np.ndarray, *, lamp_res: float = 0.5, lamp_radius: float = 9.0) -> GroundMap:
        """The ground map, with street-light pools around ``lamps`` (L x 3 head positions)."""
        my = int(np.ceil(self.ny * self.res / lamp_res))
        mx = int(np.ceil(self.nx * self.res / lamp_res))
        light = np.zeros((my, mx), dtype=np.float32)
        reach = 2.5 * lamp_radius
        n = int(np.ceil(reach / lamp_res))
        for lx, ly, lz in lamps:
            i = int(np.floor((lx - self.x0) / lamp_res))
            j = int(np.floor((ly - self.y0) / lamp_res))
            i0, i1, j0, j1 = max(i - n, 0), min(i + n + 1, mx), max(j - n, 0), min(j + n + 1, my)
            if i1 <= i0 or j1 <= j0:
                continue
            dx = self.x0 + (np.arange(i0, i1) + 0.5) * lamp_res - lx
            dy = self.y0 + (np.arange(j0, j1) + 0.5) * lamp_res - ly
            r2 = dx[None, :] ** 2 + dy[:, None] ** 2
            light[j0:j1, i0:i1] += (1.0 * lz * lz / (lz * lz + r2)) * np.exp(-r2 / (2 * lamp_radius ** 2))
        return GroundMap(self.codes, self.x0, self.y0, self.res, light, lamp_res)
