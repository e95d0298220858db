"""Camera rendering: colours from the 2.5-D cast, day/night lighting, fog, sensor noise, JPEG."""
from __future__ import annotations

import functools
import io
from dataclasses import dataclass

import numpy as np
from PIL import Image

from msg_tools.frames import CameraModel

from . import ground as g
from .hashing import drive_keys, fractal_noise, hash_uniform, sample_noise
from .materials import ground_look, object_look
from .raycast import BOTTOM, TOP, View, cast
from .world import GroundMap, Objects


@dataclass(frozen=True)
class Lighting:
    """Illumination and camera response of one lighting session."""

    night: bool
    sun: tuple[float, float, float]  # unit vector towards the sun (world)
    sun_strength: float
    ambient: float
    sky_top: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    fog_dist: float  # metres; haze halves contrast at ~0.7 of it
    tint: tuple[float, float, float]  # white balance
    exposure: float
    contrast: float  # < 1 flattens (night)
    black: float  # black level, 0..255
    noise_sigma: float  # pixel noise, 0..255 units
    lamps: float  # street-light strength
    headlights: float
    clouds: float


def lighting(*, seed: int, session: int, night: bool, drive: int = 0) -> Lighting:
    """Seeded lighting of one session (sun, haze, white balance vary per session; each drive of a city has its own)."""
    u = [float(v) for v in hash_uniform(seed, 31, session, np.arange(8), *drive_keys(drive))]
    if night:
        return Lighting(night=True, sun=(0.0, 0.0, 1.0), sun_strength=0.0, ambient=0.02 + 0.02 * u[0],
                        sky_top=(0.004, 0.006, 0.014), sky_horizon=(0.03 + 0.02 * u[1], 0.025, 0.028),
                        fog_dist=140.0 + 100 * u[2], tint=(1.0, 0.96, 0.9), exposure=1.5 + 0.5 * u[3],
                        contrast=0.8, black=5.0, noise_sigma=5.0 + 3.0 * u[4], lamps=0.45, headlights=1.0,
                        clouds=0.0)
    az, el = 2 * np.pi * u[0], np.deg2rad(20.0 + 45.0 * u[1])
    overcast = u[2]
    horizon = np.array([0.78, 0.84, 0.9]) * (1 - 0.3 * overcast) + 0.3 * overcast * np.array([0.8, 0.8, 0.8])
    sun = (float(np.cos(az) * np.cos(el)), float(np.sin(az) * np.cos(el)), float(np.sin(el)))
    top = np.array([0.30, 0.48, 0.78]) * (1 - overcast) + overcast * np.array([0.65, 0.66, 0.7])
    return Lighting(night=False, sun=sun,
                    sun_strength=0.75 * (1 - 0.7 * overcast), ambient=0.45 + 0.15 * overcast,
                    sky_top=tuple(top),
                    sky_horizon=tuple(horizon), fog_dist=260.0 + 300.0 * u[3],
                    tint=(1.0 + 0.06 * (u[4] - 0.5), 1.0, 1.0 - 0.08 * (u[4] - 0.5)), exposure=0.95 + 0.15 * u[5],
                    contrast=1.0, black=0.0, noise_sigma=2.0 + 1.5 * u[6], lamps=0.0, headlights=0.0,
                    clouds=0.6 * (1 - overcast) * u[7])


@dataclass
class CameraRender:
    """One rendered camera image with its exact depth and labels."""

    rgb: np.ndarray  # H x W x 3 uint8
    depth: np.ndarray  # H x W float32 metres along the optical axis, 0 = sky
    labels: np.ndarray  # H x W uint16 SemanticKITTI class ids, 0 = sky


@functools.lru_cache(maxsize=16)
def camera_view(K_key: tuple[float, ...], width: int, height: int, max_dist: float) -> View:
    K = np.array(K_key, dtype=np.float64).reshape(3, 3)
    return View.pinhole(K, width, height, max_dist=max_dist)


@functools.lru_cache(maxsize=8)
def _noise_bank(height: int, width: int) -> np.ndarray:
    """(H + 64) x (W + 64) x 3 float32 unit Gaussian noise; images take shifted windows of it."""
    bank = np.random.default_rng(1234).standard_normal((height + 64, width + 64, 3)).astype(np.float32)
    bank.flags.writeable = False
    return bank


def render_camera(objects: Objects, ground: GroundMap, cam: CameraModel, world_T_cam: np.ndarray, light: Lighting,
                  rng: np.random.Generator, *, vehicle_yaw: float, max_dist: float = 120.0,
                  noise: bool = True) -> CameraRender:
    """Render one level camera placed at world_T_cam (optical frame) in the world."""
    H, W = cam.height, cam.width
    view = camera_view(tuple(np.asarray(cam.K, dtype=np.float64).ravel()), W, H, max_dist)
    fwd = world_T_cam[:3, 2]
    heading = float(np.arctan2(fwd[1], fwd[0]))
    cx, cy, cz = (float(v) for v in world_T_cam[:3, 3])
    s = cast(objects, view, x=cx, y=cy, z=cz, heading=heading)
    rel = np.mod(heading + view.angles - vehicle_yaw + np.pi, 2 * np.pi) - np.pi  # column angle from vehicle forward
    beam = (light.headlights * np.exp(-(rel / 0.5) ** 2)).astype(np.float32)  # W
    inv_scale = (1.0 / view.scale).astype(np.float32)
    img = np.empty((H * W, 3), dtype=np.float32)
    labels = np.zeros(H * W, dtype=np.uint16)
    depth = np.zeros(H * W, dtype=np.float32)
    sun = np.asarray(light.sun, dtype=np.float32)
    sky_top, sky_hor = np.asarray(light.sky_top, np.float32), np.asarray(light.sky_horizon, np.float32)

    def haze(col: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Blend towards the horizon colour with distance, fully at the render limit (in place)."""
        f = -np.expm1(t * np.float32(-1.0 / light.fog_dist))
        far = np.nonzero(t > 0.7 * max_dist)[0]
        if far.size:
            e = np.clip((t[far] - 0.7 * max_dist) / (0.3 * max_dist), 0.0, 1.0)
            f[far] = np.maximum(f[far], e * e * (3 - 2 * e))
        mix = sky_hor - col
        mix *= f[:, None]
        col += mix
        return col

    def headlight(u: np.ndarray, t: np.ndarray) -> np.ndarray:
        return beam[u] / (1.0 + (t / np.float32(14.0)) ** 2)

    # sky: vertical gradient plus clouds above the horizon
    sky_pix = s.sky_pix
    if sky_pix.size:
        su = view.pixel_col[sky_pix]
        elev = view.pixel_slope[sky_pix]
        k = np.clip(elev * 1.6, 0.0, 1.0) ** 0.6
        col = sky_hor + (sky_top - sky_hor) * k[:, None]
        if light.clouds > 0:
            cl = sample_noise(fractal_noise(), (heading + view.angles[su]) * 60.0, elev * 120.0 + 300.0)
            amount = np.clip((cl - 0.1) * 2.0, 0.0, 1.0) * np.float32(light.clouds) * (elev > 0)
            col += amount[:, None] * (np.float32(0.95) - col)
        img[sky_pix] = col
    # ground
    if s.g_pix.size:
        gu = view.pixel_col[s.g_pix]
        t = s.g_t.astype(np.float32)
        codes = ground.lookup(s.g_x, s.g_y)
        col = ground_look(codes, s.g_x, s.g_y)
        irr = np.float32(light.ambient + light.sun_strength * sun[2])
        if light.night:
            irr = irr + np.float32(light.lamps) * ground.light(s.g_x, s.g_y) + headlight(gu, t)
            col *= irr[:, None]
        else:
            col *= irr
        img[s.g_pix] = haze(col, t)
        labels[s.g_pix] = g.CODE_LABEL[codes]
        depth[s.g_pix] = t * inv_scale[gu]
    # objects
    if s.o_pix.size:
        ou = view.pixel_col[s.o_pix]
        t = s.o_t.astype(np.float32)
        look = object_look(objects, s, night=light.night)
        face = s.o_face
        wall_l = (s.o_nx * sun[0] + s.o_ny * sun[1]).astype(np.float32)
        ndotl = np.where(face == TOP, sun[2], np.where(face == BOTTOM, np.float32(-0.3), wall_l))
        o_irr = np.float32(light.ambient) * np.where(face == BOTTOM, np.float32(0.55), np.float32(1.0))
        o_irr += np.float32(light.sun_strength) * np.maximum(ndotl, np.float32(0.0))
        if light.night:
            z = s.o_z.astype(np.float32)
            o_irr += np.float32(light.lamps) * ground.light(s.o_x, s.o_y) * np.exp(-z / np.float32(7.0))
            o_irr += headlight(ou, t) * np.exp(-np.maximum(z - 1.5, 0.0) / np.float32(1.5))
        col = look.albedo * o_irr[:, None]
        if look.emissive is not None:
            col += look.emissive
        img[s.o_pix] = haze(col, t)
        labels[s.o_pix] = (objects.label[s.o_obj] & 0xFFFF).astype(np.uint16)
        depth[s.o_pix] = t * inv_scale[ou]
    # camera response: exposure, white balance, contrast, noise
    out = img.reshape(H, W, 3)  # view columns (mirrored image)
    out *= np.float32(255.0 * light.exposure * light.contrast) * np.asarray(light.tint, np.float32)
    if light.black:
        out += np.float32(light.black)
    if noise:
        bank = _noise_bank(H, W)
        oy, ox = int(rng.integers(0, 64)), int(rng.integers(0, 64))
        out += np.float32(light.noise_sigma) * bank[oy:oy + H, ox:ox + W]
    np.clip(out, 0.0, 255.0, out=out)
    return CameraRender(rgb=np.ascontiguousarray(out.astype(np.uint8)[:, ::-1]),
                        depth=np.ascontiguousarray(depth.reshape(H, W)[:, ::-1]),
                        labels=np.ascontiguousarray(labels.reshape(H, W)[:, ::-1]))


def encode_jpeg(rgb: np.ndarray, *, quality: int = 85) -> bytes:
    """H x W x 3 uint8 -> JPEG bytes."""
    buf = io.BytesIO()
    Image.fromarray(rgb, mode="RGB").save(buf, format="JPEG", quality=quality)
    return buf.getvalue()
