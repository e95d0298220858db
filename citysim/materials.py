"""Surface appearance: albedo patterns (windows, foliage, cars, signs), glass and reflectivity."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import ground as g
from .hashing import fractal_noise, sample_noise, table_uniform
from .labels import Mat
from .raycast import TOP, WALL, Surfaces
from .world import Objects

WINDOW_DAY = np.array([0.10, 0.13, 0.17], dtype=np.float32)
WINDOW_LIT = np.array([1.00, 0.80, 0.48], dtype=np.float32)
LAMP_LIT = np.array([1.00, 0.86, 0.62], dtype=np.float32)


@dataclass
class ObjectLook:
    """Per object pixel (M): albedo, emitted light (night windows, lamps) and glass (LiDAR drops it)."""

    albedo: np.ndarray  # M x 3 float32
    emissive: np.ndarray | None  # M x 3 float32, or None when nothing glows
    glass: np.ndarray  # M bool


def _frac(x: np.ndarray) -> np.ndarray:
    return x - np.floor(x)


def object_look(objects: Objects, s: Surfaces, *, night: bool, want_color: bool = True) -> ObjectLook:
    """Albedo/emission/glass of every object pixel of ``s``. ``want_color=False``: glass only (LiDAR)."""
    o = s.o_obj
    m = objects.mat[o]
    z, a, face = s.o_z, s.o_along, s.o_face  # float32
    n = o.size
    glass = np.zeros(n, dtype=bool)
    albedo = objects.color[o] if want_color else np.zeros((0, 3), np.float32)  # a new array (fancy index)
    emissive = np.zeros((n, 3), dtype=np.float32) if (want_color and night) else None
    tex = fractal_noise()

    sel = np.nonzero((m == Mat.FACADE) | (m == Mat.WALL))[0]
    if sel.size and want_color:  # wall grain and roofs
        base = albedo[sel]
        base *= (1.0 + 0.07 * sample_noise(tex, a[sel] * 9.0, z[sel] * 9.0))[:, None]
        roof = face[sel] == TOP
        base[roof] = 0.35 + 0.2 * base[roof]
        albedo[sel] = base
    sel = sel[(m[sel] == Mat.FACADE) & (face[sel] == WALL)]
    if sel.size:  # windows: a grid in (along, height) from the building's parameters
        oi = o[sel]
        p = objects.params[oi]
        zz, aa = z[sel], a[sel]
        ws, fh, wwf, whf, gf, style = (p[:, k] for k in range(6))
        ws = np.maximum(ws, 0.5)
        col_f = aa / ws
        zg = zz - gf
        row_f = zg / np.maximum(fh, 1.0)
        row_frac = _frac(row_f)
        in_col = np.where(style == 1, _frac(aa / 1.6) > 0.06, np.abs(_frac(col_f) - 0.5) < wwf / 2)
        in_row = (np.abs(row_frac - 0.5) < whf / 2) & (zg > 0) & (zz < objects.z1[oi] - 0.9)
        shop = (style == 2) & (zz > 0.35) & (zg < -0.6) & (np.abs(_frac(col_f / 1.5) - 0.5) < 0.42)
        window = (in_col & in_row) | shop
        glass[sel] = window
        if want_color:
            slab = (row_frac < 0.035) & (zg > 0) & (style != 1)
            albedo[sel[slab & ~window]] *= 0.82
            w = np.nonzero(window)[0]
            wseed = objects.seed[oi[w]].astype(np.int64)
            wi = np.floor(col_f[w]).astype(np.int64) + wseed * 37
            wj = np.floor(row_f[w]).astype(np.int64) + wseed * 101 + np.where(shop[w], 500, 0)
            h = table_uniform(wi, wj)
            albedo[sel[w]] = WINDOW_DAY[None, :] * (0.7 + 1.6 * h[:, None])
            if emissive is not None:  # night (colours are wanted here)
                lit = table_uniform(wi + 511, wj + 257) < np.where(shop[w], 0.6, 0.3)
                emissive[sel[w[lit]]] = WINDOW_LIT * (0.35 + 0.45 * h[lit, None])

    sel = np.nonzero(m == Mat.CABIN)[0]
    if sel.size:
        oi = o[sel]
        length = np.where(np.abs(s.o_nx[sel] * objects.cos[oi] + s.o_ny[sel] * objects.sin[oi]) > 0.7,
                          2 * objects.hy[oi], 2 * objects.hx[oi])
        pillar = (a[sel] < 0.18) | (a[sel] > length - 0.18) | (z[sel] > objects.z1[oi] - 0.08)
        win = (face[sel] == WALL) & ~pillar
        glass[sel] = win
        if want_color:
            albedo[sel[win]] = WINDOW_DAY * 0.8

    if want_color:
        sel = np.nonzero(m == Mat.CAR)[0]
        if sel.size:
            zz = z[sel]
            albedo[sel[zz < 0.38]] = (0.05, 0.05, 0.05)
            albedo[sel[np.abs(zz - 0.62) < 0.03]] *= 0.6
        sel = np.nonzero(m == Mat.FOLIAGE)[0]
        if sel.size:
            leaf = (sample_noise(tex, a[sel] * 14.0, z[sel] * 14.0)
                    + 0.5 * sample_noise(tex, a[sel] * 3.0 + 91, z[sel] * 3.0))
            albedo[sel] *= np.clip(0.8 + 0.55 * leaf, 0.3, 1.6)[:, None]
            albedo[sel[face[sel] != WALL]] *= 0.55
        sel = np.nonzero(m == Mat.TRUNK)[0]
        if sel.size:
            albedo[sel] *= (0.85 + 0.25 * sample_noise(tex, a[sel] * 30.0, z[sel] * 4.0))[:, None]
        sel = np.nonzero(m == Mat.SIGN)[0]
        if sel.size:
            oi = o[sel]
            front = (s.o_nx[sel] * objects.cos[oi] + s.o_ny[sel] * objects.sin[oi]) > 0.5
            size = objects.params[oi, 0]
            edge = np.minimum.reduce([a[sel], np.abs(size - a[sel]), z[sel] - objects.z0[oi], objects.z1[oi] - z[sel]])
            albedo[sel[front & (edge < 0.06)]] = (0.92, 0.92, 0.9)
            albedo[sel[~front]] = (0.45, 0.46, 0.47)
        sel = np.nonzero(m == Mat.FENCE)[0]
        if sel.size:
            oi = o[sel]
            bars = (_frac(a[sel] / objects.params[oi, 0]) < 0.2) | (z[sel] > objects.z1[oi] - 0.06)
            albedo[sel[~bars]] = albedo[sel[~bars]] * 0.5 + 0.2
        if emissive is not None:  # night (colours are wanted here)
            sel = np.nonzero((m == Mat.LAMP) & (face != TOP))[0]
            emissive[sel] = LAMP_LIT * 1.5
    return ObjectLook(albedo=albedo, emissive=emissive, glass=glass)


def ground_look(codes: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """G x 3 albedo of ground points with ground codes ``codes``."""
    shade = sample_noise(fractal_noise(), x * 6.0, y * 6.0)  # blotches from ~0.3 m to ~5 m
    shade *= g.CODE_TEXTURE[codes]
    shade += 1.0
    return g.CODE_COLOR[codes] * shade[:, None]
