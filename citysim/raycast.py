"""2.5-D ray casting: vertical prisms over a flat ground, one vertical plane of rays per column.

A level sensor's rays in one image column (or one LiDAR azimuth) share a horizontal
direction; ray (v, u) climbs ``g[v] / scale[u]`` metres per horizontal metre. Each object
a column passes through is a rectangle [t_in, t_out] x [z0, z1] in that plane (convex
footprints), so the rows it covers follow from the slopes to the rectangle's corners.
Nearer objects are painted over farther ones; uncovered rays hit the ground or the sky.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .world import Objects

WALL, TOP, BOTTOM = 0, 1, 2


@dataclass(frozen=True)
class View:
    """The rays of one level sensor, relative to its position and heading."""

    angles: np.ndarray  # W, ascending, radians counter-clockwise from the heading
    scale: np.ndarray  # W, >= 1 (pinhole: sqrt(1 + x_n^2); LiDAR: 1)
    g: np.ndarray  # H, descending: slope numerator per row
    max_dist: float  # horizontal metres; nothing farther is seen

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.g.shape[0]), int(self.angles.shape[0])

    @functools.cached_property
    def pixel_slope(self) -> np.ndarray:
        """H * W float32: rise per horizontal metre of each ray (flat, row-major)."""
        return (self.g[:, None] / self.scale[None, :]).astype(np.float32).ravel()

    @functools.cached_property
    def pixel_col(self) -> np.ndarray:
        """H * W int64: column of each flat pixel index."""
        return np.tile(np.arange(self.shape[1], dtype=np.int64), self.shape[0])

    @staticmethod
    def pinhole(K: np.ndarray, width: int, height: int, *, max_dist: float) -> View:
        """A level pinhole camera. View column j is image column width - 1 - j."""
        fx, cx, fy, cy = K[0, 0], K[0, 2], K[1, 1], K[1, 2]
        xn = (np.arange(width)[::-1] - cx) / fx
        return View(angles=-np.arctan(xn), scale=np.sqrt(1.0 + xn * xn), g=(cy - np.arange(height)) / fy,
                    max_dist=max_dist)

    @staticmethod
    def lidar(elevations_deg: np.ndarray, azimuth_steps: int, *, max_dist: float, phase: float = 0.5) -> View:
        """A spinning LiDAR: rows are beams (descending elevation), columns azimuths from -pi."""
        el = np.asarray(elevations_deg, dtype=np.float64)
        if np.any(np.diff(el) >= 0):
            raise ValueError("LiDAR elevations must be strictly descending (row 0 = top beam)")
        angles = -np.pi + (np.arange(azimuth_steps) + phase) * (2 * np.pi / azimuth_steps)
        return View(angles=angles, scale=np.ones(azimuth_steps), g=np.tan(np.deg2rad(el)), max_dist=max_dist)


@dataclass
class Surfaces:
    """What each ray of a view hits. Pixels index the view's H x W grid (flat, row-major).

    Object hits (M): ``o_*``; ground hits (G): ``g_*``; every other ray sees the sky.
    Distances ``t`` are horizontal metres from the sensor; x, y, z are world coordinates.
    """

    shape: tuple[int, int]
    o_pix: np.ndarray  # M int64
    o_obj: np.ndarray  # M int64, index into the objects passed to cast()
    o_t: np.ndarray  # M float32
    o_z: np.ndarray  # M float32
    o_face: np.ndarray  # M uint8: WALL, TOP, BOTTOM
    o_along: np.ndarray  # M float32, metres along the face (walls)
    o_nx: np.ndarray  # M float32, wall normal (world)
    o_ny: np.ndarray
    o_x: np.ndarray  # M float32
    o_y: np.ndarray
    g_pix: np.ndarray  # G int64
    g_t: np.ndarray  # G float32
    g_x: np.ndarray  # G float32
    g_y: np.ndarray
    sky_pix: np.ndarray  # S int64, rays that hit nothing


def _intersect(objects: Objects, obj: np.ndarray, ox: float, oy: float, dx: np.ndarray,
               dy: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per (ray, object) pair: hit, t_in, t_out, entry normal (x, y), along, z0, z1 (domes applied), wall_ok.

    wall_ok is False when the ray starts inside the footprint (it can only meet a roof or an underside).
    """
    kind = objects.kind[obj]
    cx, cy = objects.cx[obj], objects.cy[obj]
    hx, hy = objects.hx[obj], objects.hy[obj]
    c, s = objects.cos[obj], objects.sin[obj]
    wx, wy = ox - cx, oy - cy
    # boxes (slabs in the box frame)
    px, py = wx * c + wy * s, -wx * s + wy * c
    ldx, ldy = dx * c + dy * s, -dx * s + dy * c
    ldx = np.where(np.abs(ldx) < 1e-12, 1e-12, ldx)
    ldy = np.where(np.abs(ldy) < 1e-12, 1e-12, ldy)
    ax, bx = (-hx - px) / ldx, (hx - px) / ldx
    ay, by = (-hy - py) / ldy, (hy - py) / ldy
    tx0, tx1 = np.minimum(ax, bx), np.maximum(ax, bx)
    ty0, ty1 = np.minimum(ay, by), np.maximum(ay, by)
    b_in, b_out = np.maximum(tx0, ty0), np.minimum(tx1, ty1)
    xface = tx0 >= ty0
    lnx = np.where(xface, -np.sign(ldx), 0.0)
    lny = np.where(xface, 0.0, -np.sign(ldy))
    b_along = np.where(xface, py + ldy * b_in + hy, px + ldx * b_in + hx)
    # cylinders
    bb = wx * dx + wy * dy
    disc = bb * bb - (wx * wx + wy * wy - hx * hx)
    sq = np.sqrt(np.maximum(disc, 0.0))
    c_in, c_out = -bb - sq, -bb + sq
    rho = np.abs(wx * dy - wy * dx) / hx
    is_box = kind == 0
    t_in = np.where(is_box, b_in, c_in)
    t_out = np.where(is_box, b_out, c_out)
    hit = np.where(is_box, b_out > b_in, disc > 0) & (t_out > 1e-3)
    cnx, cny = (wx + dx * c_in) / hx, (wy + dy * c_in) / hx
    nx = np.where(is_box, c * lnx - s * lny, cnx)
    ny = np.where(is_box, s * lnx + c * lny, cny)
    along = np.where(is_box, b_along, hx * (np.arctan2(cny, cnx) + np.pi))
    bulge = objects.dome[obj] * (1.0 - np.sqrt(np.maximum(1.0 - rho * rho, 0.0)))
    z0 = objects.z0[obj] + 0.35 * bulge
    z1 = objects.z1[obj] - bulge
    wall_ok = t_in > 1e-3
    t_in = np.maximum(t_in, 1e-3)
    return hit, t_in, t_out, nx, ny, along, z0, z1, wall_ok


def cast(objects: Objects, view: View, *, x: float, y: float, z: float, heading: float) -> Surfaces:
    """Cast every ray of ``view`` from (x, y, z) looking along ``heading`` (radians, world)."""
    H, W = view.shape
    col_dx, col_dy = np.cos(heading + view.angles), np.sin(heading + view.angles)
    neg_g = -view.g
    # 1. which columns each object can touch (angular interval of its bounding circle)
    dxo, dyo = objects.cx - x, objects.cy - y
    dist = np.hypot(dxo, dyo)
    rb = objects.radius
    idx = np.nonzero((dist - rb < view.max_dist) & (objects.z1 > objects.z0))[0]
    theta = np.mod(np.arctan2(dyo[idx], dxo[idx]) - heading + np.pi, 2 * np.pi) - np.pi
    with np.errstate(divide="ignore", invalid="ignore"):
        half = np.where(dist[idx] <= rb[idx], np.pi, np.arcsin(np.clip(rb[idx] / dist[idx], 0.0, 1.0)) + 1e-9)
    lo, hi = theta - half, theta + half
    a_lo, a_hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
    b_lo = np.where(lo < -np.pi, lo + 2 * np.pi, np.where(hi > np.pi, -np.pi, 1.0))
    b_hi = np.where(lo < -np.pi, np.pi, np.where(hi > np.pi, hi - 2 * np.pi, 0.0))
    starts = np.searchsorted(view.angles, np.concatenate([a_lo, b_lo]), side="left")
    counts = np.maximum(np.searchsorted(view.angles, np.concatenate([a_hi, b_hi]), side="right") - starts, 0)
    obj = np.repeat(np.concatenate([idx, idx]), counts)
    offs = np.cumsum(counts) - counts
    col = np.arange(obj.size) - np.repeat(offs, counts) + np.repeat(starts, counts)
    # 2. ray-footprint intersections, rows covered
    hit, t_in, t_out, nx, ny, along, z0, z1, wall_ok = _intersect(objects, obj, x, y, col_dx[col], col_dy[col])
    zl, zh = z0 - z, z1 - z
    s_hi = np.maximum(zh / t_in, zh / t_out)
    s_lo = np.minimum(zl / t_in, zl / t_out)
    sc = view.scale[col]
    r0 = np.searchsorted(neg_g, -s_hi * sc, side="left")
    r1 = np.searchsorted(neg_g, -s_lo * sc, side="right")
    keep = hit & (r1 > r0) & (t_in < view.max_dist)
    full = keep & (r0 == 0) & (r1 == H)  # covers the whole column: hides everything behind
    occ = np.full(W, np.inf)
    np.minimum.at(occ, col[full], t_in[full])
    keep &= t_in <= occ[col]
    k = np.nonzero(keep)[0]
    k = k[np.argsort(-t_in[k], kind="stable")]  # far -> near: a nearer pair gets a higher rank
    obj, col, t_in, t_out, nx, ny, along, z0, z1, wall_ok, r0, r1 = (
        a[k] for a in (obj, col, t_in, t_out, nx, ny, along, z0, z1, wall_ok, r0, r1))
    # 3. paint: each pixel keeps its highest-ranked (nearest) covering pair
    n_rows = r1 - r0
    offs = np.cumsum(n_rows) - n_rows
    rank = np.repeat(np.arange(k.size, dtype=np.int32), n_rows)
    rows = np.arange(rank.size) - np.repeat(offs - r0, n_rows)
    buf = np.full(H * W, -1, dtype=np.int32)
    np.maximum.at(buf, rows * W + np.repeat(col, n_rows), rank)
    # 4. object pixels: front wall, roof or underside (float32 from here on)
    f32 = np.float32
    zf = f32(z)
    o_pix = np.flatnonzero(buf >= 0)
    p = buf[o_pix]
    u = view.pixel_col[o_pix]
    slope = view.pixel_slope[o_pix]
    ti, to, pz0, pz1 = (a.astype(f32)[p] for a in (t_in, t_out, z0, z1))
    z_in = zf + slope * ti
    wall = wall_ok[p] & (z_in >= pz0 - f32(1e-5)) & (z_in <= pz1 + f32(1e-5))
    top = ~wall & (z_in > pz1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_cap = (np.where(top, pz1, pz0) - zf) / slope
    t_cap = np.clip(np.nan_to_num(t_cap, nan=0.0, posinf=0.0, neginf=0.0), ti, to)
    t = np.where(wall, ti, t_cap)
    face = np.where(wall, WALL, np.where(top, TOP, BOTTOM)).astype(np.uint8)
    cdx, cdy = col_dx.astype(f32), col_dy.astype(f32)
    # 5. free rays going down hit the ground
    free = np.flatnonzero(buf < 0)
    fs = view.pixel_slope[free]
    with np.errstate(divide="ignore"):
        tg = zf / -fs
    on_ground = (fs < 0) & (tg <= view.max_dist)
    gsel = np.nonzero(on_ground)[0]
    g_pix, g_t = free[gsel], tg[gsel]
    g_u = view.pixel_col[g_pix]
    return Surfaces(
        shape=(H, W), o_pix=o_pix, o_obj=obj[p], o_t=t, o_z=zf + slope * t, o_face=face,
        o_along=along.astype(f32)[p], o_nx=nx.astype(f32)[p], o_ny=ny.astype(f32)[p],
        o_x=f32(x) + cdx[u] * t, o_y=f32(y) + cdy[u] * t,
        g_pix=g_pix, g_t=g_t, g_x=f32(x) + cdx[g_u] * g_t, g_y=f32(y) + cdy[g_u] * g_t, sky_pix=free[~on_ground],
    )
