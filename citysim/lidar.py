"""LiDAR rendering: ranges, labels and intensities from the 2.5-D cast, with noise and dropouts."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import ground as g
from .materials import object_look
from .raycast import WALL, View, cast
from .rigs import LidarModel
from .world import GroundMap, Objects

CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"),
                        ("label", "<u4")])


@dataclass(frozen=True)
class LidarNoise:
    """Imperfections of the simulated LiDAR (all off = exact geometry)."""

    range_sigma: float = 0.02  # metres, plus 0.1 % of the range
    dropout: float = 0.05  # random missing returns
    glass_dropout: float = 0.6  # missing returns on windows
    intensity_sigma: float = 0.02  # fraction of full scale
    azimuth_jitter: bool = True  # random azimuth phase per scan

    @staticmethod
    def off() -> LidarNoise:
        return LidarNoise(0.0, 0.0, 0.0, 0.0, False)


def render_lidar(objects: Objects, ground: GroundMap, lidar: LidarModel, world_T_lidar: np.ndarray, vehicle_yaw: float,
                 rng: np.random.Generator, *, noise: LidarNoise = LidarNoise()) -> np.ndarray:
    """One scan as a structured array (CLOUD_DTYPE) in the LiDAR frame, ordered by azimuth then ring.

    The scan is cast in a level frame turned like the vehicle (x forward), then rotated
    into the LiDAR's own axes; ``world_T_lidar`` gives its position and orientation.
    """
    H = len(lidar.elevations_deg)
    phase = float(rng.uniform()) if noise.azimuth_jitter else 0.5
    view = View.lidar(np.asarray(lidar.elevations_deg), lidar.azimuth_steps, max_dist=lidar.max_range, phase=phase)
    ox, oy, oz = (float(v) for v in world_T_lidar[:3, 3])
    s = cast(objects, view, x=ox, y=oy, z=oz, heading=vehicle_yaw)
    W = view.shape[1]

    pix = np.concatenate([s.o_pix, s.g_pix])
    t = np.concatenate([s.o_t, s.g_t])
    v, u = np.divmod(pix, W)
    slope = view.g[v]
    norm = np.sqrt(1.0 + slope * slope)
    rng3 = t * norm
    codes = ground.lookup(s.g_x, s.g_y)
    look = object_look(objects, s, night=False, want_color=False)
    label = np.concatenate([objects.label[s.o_obj], g.CODE_LABEL[codes]]).astype(np.uint32)
    refl = np.concatenate([np.where(look.glass, 0.05, objects.refl[s.o_obj]), g.CODE_REFL[codes]])
    # incidence: walls by their normal, roofs/undersides/ground by the slope
    az = vehicle_yaw + view.angles[u[:s.o_pix.size]]
    wall_cos = np.abs(s.o_nx * np.cos(az) + s.o_ny * np.sin(az)) / norm[:s.o_pix.size]
    flat_cos = np.abs(slope) / norm
    cos_inc = np.concatenate([np.where(s.o_face == WALL, wall_cos, flat_cos[:s.o_pix.size]), flat_cos[s.o_pix.size:]])
    intensity = refl * (0.25 + 0.75 * cos_inc) * np.clip(1.0 - rng3 / 250.0, 0.3, 1.0)
    far = rng3 / lidar.max_range
    drop_p = noise.dropout * (1.0 + 2.0 * far * far + 4.0 * far * (refl < 0.1))  # far, dark surfaces drop more
    glass = np.concatenate([look.glass, np.zeros(s.g_pix.size, dtype=bool)])
    drop_p = np.where(glass, np.maximum(drop_p, noise.glass_dropout), drop_p)
    keep = (rng3 >= lidar.min_range) & (rng3 <= lidar.max_range)
    if noise.dropout > 0 or noise.glass_dropout > 0:
        keep &= rng.uniform(size=rng3.size) >= drop_p
    if noise.range_sigma > 0:
        rng3 = rng3 + rng.normal(0.0, 1.0, rng3.size) * (noise.range_sigma + 0.001 * rng3)
    if noise.intensity_sigma > 0:
        intensity = intensity + rng.normal(0.0, noise.intensity_sigma, intensity.size)
    order = np.lexsort((-v[keep], u[keep]))  # by azimuth, then ring (lowest beam first)
    k = np.nonzero(keep)[0][order]
    ang = view.angles[u[k]]
    hor = rng3[k] / norm[k]
    p_level = np.stack([hor * np.cos(ang), hor * np.sin(ang), hor * slope[k]], axis=1)  # x fwd, y left, z up
    level_R_lidar = _level_R_lidar(world_T_lidar, vehicle_yaw)
    p = p_level @ level_R_lidar  # = (level_R_lidar^T p_level^T)^T
    cloud = np.empty(k.size, dtype=CLOUD_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = p[:, 0], p[:, 1], p[:, 2]
    cloud["intensity"] = np.clip(intensity[k], 0.0, 1.0) * lidar.intensity_max
    cloud["ring"] = (H - 1 - v[k]).astype(np.uint16)
    cloud["label"] = label[k]
    return cloud


def _level_R_lidar(world_T_lidar: np.ndarray, vehicle_yaw: float) -> np.ndarray:
    """Rotation of the LiDAR axes in the level frame turned by vehicle_yaw."""
    c, s = np.cos(vehicle_yaw), np.sin(vehicle_yaw)
    world_R_level = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return world_R_level.T @ world_T_lidar[:3, :3]
