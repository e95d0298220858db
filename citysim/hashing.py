"""Counter-based random numbers (splitmix64) and tileable value-noise textures.

Hashing instead of a sequential generator keeps every random choice a pure function
of its keys (seed, object, visit, ...), so results do not depend on evaluation order
or on how frames are spread over worker processes.
"""
from __future__ import annotations

import functools

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix(h: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        h = (h ^ (h >> np.uint64(30))) * _M1
        h = (h ^ (h >> np.uint64(27))) * _M2
        return h ^ (h >> np.uint64(31))


def hash_u64(*keys: int | np.ndarray) -> np.ndarray:
    """Hash integer keys (scalars or broadcastable arrays) to uint64."""
    h = np.zeros((), dtype=np.uint64)
    with np.errstate(over="ignore"):
        for key in keys:
            k = np.asarray(key).astype(np.int64).astype(np.uint64)
            h = _mix(h + _GOLDEN + k)
    return h


def hash_uniform(*keys: int | np.ndarray) -> np.ndarray:
    """Hash integer keys to float64 uniform in [0, 1)."""
    return (hash_u64(*keys) >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


DRIVE_KEY = 0x0D21FE  # marks the keys of drive K > 0 (non-zero: numpy seed sequences ignore trailing zeros)
DAY_S = 86400.0


def drive_keys(drive: int, *, variant: int = 0) -> tuple[int, ...]:
    """Extra random keys for drive ``drive`` of a city: none for drive 0 (its streams stay as they were).

    Appended to the keys of a route, noise or lighting stream, they give each drive of one
    city its own stream while drive 0 keeps exactly the numbers of a city's single drive.
    ``variant`` > 0 draws another route for the same drive (one that met a pole is re-planned).
    """
    if drive < 0:
        raise ValueError(f"drive={drive}; it must be 0 (the city's first drive) or a positive drive number")
    if variant < 0 or (drive == 0 and variant):
        raise ValueError(f"variant={variant} of drive {drive}; drive 0 has only variant 0, other drives 0 or more")
    if drive == 0:
        return ()
    return (DRIVE_KEY, drive, variant) if variant else (DRIVE_KEY, drive)


def rng_for(*keys: int) -> np.random.Generator:
    """A numpy Generator seeded by integer keys (order matters)."""
    return np.random.default_rng([int(k) & 0xFFFFFFFF for k in keys])


@functools.lru_cache(maxsize=8)
def value_noise(size: int, cell: int, seed: int) -> np.ndarray:
    """size x size float32 tileable smooth noise in about [-1, 1] (bilinear-smoothstep of a cell lattice)."""
    if size % cell:
        raise ValueError(f"noise size {size} must be a multiple of cell {cell}")
    n = size // cell
    lattice = np.random.default_rng(seed).uniform(-1.0, 1.0, (n, n)).astype(np.float32)
    f = (np.arange(size, dtype=np.float32) % cell) / cell
    f = f * f * (3.0 - 2.0 * f)  # smoothstep
    i0 = np.arange(size) // cell
    i1 = (i0 + 1) % n
    rows0, rows1 = lattice[i0], lattice[i1]  # size x n
    a = rows0[:, i0] * (1 - f)[None, :] + rows0[:, i1] * f[None, :]
    b = rows1[:, i0] * (1 - f)[None, :] + rows1[:, i1] * f[None, :]
    out = a * (1 - f)[:, None] + b * f[:, None]
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=4)
def fractal_noise(size: int = 512, seed: int = 7) -> np.ndarray:
    """size x size float32 tileable noise with three octaves, about [-1, 1]."""
    out = (value_noise(size, 32, seed) * 0.55 + value_noise(size, 8, seed + 1) * 0.3
           + value_noise(size, 2, seed + 2) * 0.15)
    out = out.astype(np.float32)
    out.flags.writeable = False
    return out


def sample_noise(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Nearest-texel lookup of a tileable texture at texel coordinates (u, v), wrapping."""
    n = tex.shape[0]
    iu = np.floor(u).astype(np.int64) & (n - 1)
    iv = np.floor(v).astype(np.int64) & (n - 1)
    return tex[iv, iu]


@functools.lru_cache(maxsize=2)
def random_table(size: int = 1024, seed: int = 99) -> np.ndarray:
    """size x size float32 uniform [0, 1) lookup table (cheap per-pixel randomness by integer keys)."""
    out = np.random.default_rng(seed).uniform(0.0, 1.0, (size, size)).astype(np.float32)
    out.flags.writeable = False
    return out


def table_uniform(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) values keyed by integer arrays (i, j); wraps every 1024."""
    tab = random_table()
    return tab[np.asarray(i, dtype=np.int64) & 1023, np.asarray(j, dtype=np.int64) & 1023]
