"""Spherical projection of a LiDAR cloud into the range image LCPR reads."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from lcpr_common.params import param

from ...errors import InputShapeError, InvalidValueError
from ...points import turn_cos_sin

NO_RETURN = -1.0  # a range-image pixel no point falls in


@dataclass(frozen=True)
class LidarPreset:
    """How one LiDAR's cloud becomes a range image.

    yaw_offset_deg rotates the cloud about z so that x points forward (REP-103);
    points with |x| < min_xy and |y| < min_xy (the ego vehicle) are dropped, as are
    ranges outside (0, max_range).
    """

    yaw_offset_deg: float
    min_xy: float
    fov_up_deg: float
    fov_down_deg: float
    height: int
    width: int
    max_range: float


@dataclass(frozen=True)
class LidarGeometry:
    """The geometry of a LiDAR no preset knows (``lidar = "custom"``; rows and columns: ``range_size``).

    Defaults: a 32-beam +10 / -30 deg sensor in a REP-103 frame. ``yaw_offset_deg`` turns the
    cloud about z so that x points forward; ``min_xy`` drops the ego box; ``max_range`` in m.
    """

    fov_up_deg: float = param(10.0, "deg, top of the vertical field of view (model.lidar custom)")
    fov_down_deg: float = param(-30.0, "deg, bottom of the vertical field of view (model.lidar custom)")
    yaw_offset_deg: float = param(0.0, "deg about z that turns the cloud's x forward (model.lidar custom)")
    max_range: float = param(80.0, "m, farther points are left out (model.lidar custom)")
    min_xy: float = param(2.0, "m, half size of the ego box left out (model.lidar custom)")

    def __post_init__(self) -> None:
        values = dataclasses.astuple(self)
        if not all(np.isfinite(values)):
            raise InvalidValueError(f"lidar_geometry {self}: every value must be finite")
        _check_config(self.preset(1, 1), prefix="lidar_geometry.")

    def preset(self, height: int, width: int) -> LidarPreset:
        """This geometry at a range image of ``height`` x ``width``."""
        return LidarPreset(self.yaw_offset_deg, self.min_xy, self.fov_up_deg, self.fov_down_deg, int(height),
                           int(width), self.max_range)


PRESETS: dict[str, LidarPreset] = {
    # nuScenes LIDAR_TOP (x right, y forward): the released LCPR configuration.
    "nuscenes_lidar_top": LidarPreset(-90.0, 2.0, 10.0, -30.0, 32, 1056, 80.0),
    # Velodyne HDL-64E as in KITTI, cloud in a REP-103 frame (x forward, y left).
    "kitti_hdl64e": LidarPreset(0.0, 2.0, 3.0, -25.0, 64, 1056, 80.0),
    # Velodyne VLP-16 (Puck), REP-103 frame.
    "velodyne_vlp16": LidarPreset(0.0, 1.0, 15.0, -15.0, 16, 1056, 80.0),
    # Ouster OS1-64 / OS1-128 (45 deg vertical field of view) and OS2-128 (22.5 deg), cloud in
    # ouster-ros' os_sensor frame (x forward, REP-103).
    "ouster_os1_64": LidarPreset(0.0, 1.0, 22.5, -22.5, 64, 1056, 100.0),
    "ouster_os1_128": LidarPreset(0.0, 1.0, 22.5, -22.5, 128, 1056, 100.0),
    "ouster_os2_128": LidarPreset(0.0, 2.0, 11.25, -11.25, 128, 1056, 200.0),
    # Hesai Pandar64 (+15 / -25 deg), REP-103 frame.
    "hesai_pandar64": LidarPreset(0.0, 2.0, 15.0, -25.0, 64, 1056, 200.0),
}
#: ``lidar`` value that takes the geometry from explicit settings instead of a preset.
CUSTOM = "custom"


def lidar_preset(name: str) -> LidarPreset:
    try:
        return PRESETS[name]
    except KeyError as err:
        raise InvalidValueError(f"unknown LiDAR preset {name!r}; accepted: {', '.join(sorted(PRESETS))}") from err


def points_array(points: np.ndarray) -> np.ndarray:
    """``points`` as an N x (>=3) array, else :class:`InputShapeError` naming the shape found."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise InputShapeError(f"points have shape {pts.shape}; expected N x 3 or more columns (x, y, z, ...)")
    return pts


def range_image(
    points: np.ndarray,
    *,
    preset: str | LidarPreset = "nuscenes_lidar_top",
    yaw_offset_deg: float | None = None,
    min_xy: float | None = None,
    fov_up_deg: float | None = None,
    fov_down_deg: float | None = None,
    height: int | None = None,
    width: int | None = None,
    max_range: float | None = None,
) -> np.ndarray:
    """N x (>=3) points -> height x width float32 ranges in metres, -1 where no point falls.

    Options left as None come from ``preset``. Non-finite points are dropped. Each
    pixel keeps its nearest point. Computed in float64 as the released code does.
    """
    base = lidar_preset(preset) if isinstance(preset, str) else preset
    given: dict[str, Any] = dict(yaw_offset_deg=yaw_offset_deg, min_xy=min_xy, fov_up_deg=fov_up_deg,
                 fov_down_deg=fov_down_deg, height=height, width=width, max_range=max_range)
    cfg = dataclasses.replace(base, **{k: v for k, v in given.items() if v is not None})
    _check_config(cfg)
    pts = points_array(points)
    # one contiguous float64 array per axis: the arithmetic below reads each column many times
    x, y, z = (pts[:, k].astype(np.float64) for k in range(3))
    keep = np.isfinite(x + y + z) & ~((np.abs(x) < cfg.min_xy) & (np.abs(y) < cfg.min_xy))  # finite, not the ego box
    x, y, z = x[keep], y[keep], z[keep]
    if cfg.yaw_offset_deg != 0:
        c, s = turn_cos_sin(cfg.yaw_offset_deg)
        x, y = c * x - s * y, s * x + c * y
    rng = np.sqrt(x * x + y * y + z * z)  # np.linalg.norm's arithmetic, in its order
    keep = (rng > 0) & (rng < cfg.max_range)
    x, y, z, rng = x[keep], y[keep], z[keep], rng[keep]
    pixel = _pixels(np.arctan2(y, x), np.arcsin(z / rng), cfg, np)

    image = np.full(cfg.height * cfg.width, np.inf)
    np.minimum.at(image, pixel, rng)  # each pixel keeps its nearest point
    image[np.isinf(image)] = NO_RETURN
    return image.astype(np.float32).reshape(cfg.height, cfg.width)


def range_image_tensor(points: torch.Tensor, *, preset: LidarPreset) -> torch.Tensor:
    """:func:`range_image` in torch, on the points' device (a GPU keeps the cloud where the network runs).

    N x (>=3) points -> height x width float32; the same arithmetic in float64, the nearest point
    per pixel by a scatter-min. No point is selected by a mask (which would wait for the device to
    count them): dropped points go to a spare pixel instead. Equal to :func:`range_image` except where
    a libm and the device's sqrt / arctan / arcsin differ in the last bits at a pixel border; on the CPU
    torch's sqrt (MKL) is not always correctly rounded, which is why the CPU path uses the numpy one.
    """
    return range_images_tensor([points], preset=preset)[0]


def range_images_tensor(clouds: list[torch.Tensor], *, preset: LidarPreset) -> torch.Tensor:
    """:func:`range_image_tensor` of B clouds at once -> B x height x width: one pass of the arithmetic and one
    scatter-min over all their points (a frame's dozen kernels launched once per batch, not once per cloud).
    Each result equals that cloud's :func:`range_image_tensor`: the arithmetic is per point."""
    for points in clouds:
        if points.dim() != 2 or points.shape[1] < 3:
            raise InputShapeError(f"points have shape {tuple(points.shape)}; expected N x 3 or more columns")
    if not clouds:
        raise InputShapeError("no clouds given; expected at least one N x 3 cloud")
    _check_config(preset)
    device = clouds[0].device
    points = clouds[0][:, :3] if len(clouds) == 1 else torch.cat([c[:, :3] for c in clouds])
    x, y, z = (points[:, k].to(torch.float64) for k in range(3))
    keep = torch.isfinite(x + y + z) & ~((x.abs() < preset.min_xy) & (y.abs() < preset.min_xy))
    if preset.yaw_offset_deg != 0:
        c, s = turn_cos_sin(preset.yaw_offset_deg)
        x, y = c * x - s * y, s * x + c * y
    rng = torch.sqrt(x * x + y * y + z * z)
    keep &= (rng > 0) & (rng < preset.max_range)
    pixels = preset.height * preset.width
    spare = len(clouds) * pixels  # where dropped points land
    pixel = _pixels(torch.atan2(y, x), torch.asin(z / rng), preset, torch, valid=keep, spare=spare)
    if len(clouds) > 1:  # cloud b's pixels are the b-th block of the flat image
        counts = torch.tensor([c.shape[0] for c in clouds], device=device)
        offsets = torch.repeat_interleave(torch.arange(len(clouds), device=device) * pixels, counts,
                                          output_size=points.shape[0])
        pixel = torch.where(keep, pixel + offsets, pixel)
    image = torch.full((spare + 1,), float("inf"), dtype=torch.float64, device=device)
    image.scatter_reduce_(0, pixel, torch.where(keep, rng, torch.inf), reduce="amin")
    image = image[:spare].masked_fill_(torch.isinf(image[:spare]), NO_RETURN)
    return image.to(torch.float32).view(len(clouds), preset.height, preset.width)


def _pixels(azimuth: Any, elevation: Any, cfg: LidarPreset, xp: Any, *, valid: Any = None, spare: int = 0) -> Any:
    """Flat pixel index of each point from its azimuth and elevation (numpy or torch arrays, ``xp`` says which);
    with ``valid`` (torch), points outside it get index ``spare``."""
    fov_down = abs(np.deg2rad(cfg.fov_down_deg))
    fov = abs(np.deg2rad(cfg.fov_up_deg)) + fov_down
    u = xp.clip(xp.floor(0.5 * (-azimuth / np.pi + 1.0) * cfg.width), 0, cfg.width - 1)
    v = xp.clip(xp.floor((1.0 - (elevation + fov_down) / fov) * cfg.height), 0, cfg.height - 1)
    flat = v * cfg.width + u
    if xp is np:
        return flat.astype(np.int64)
    if valid is not None:
        flat = torch.where(valid, flat, float(spare))
    return flat.to(torch.int64)


def _check_config(cfg: LidarPreset, *, prefix: str = "") -> None:
    if cfg.height < 1 or cfg.width < 1:
        raise InvalidValueError(f"range image size {cfg.height} x {cfg.width}; both must be positive")
    if not cfg.fov_up_deg > cfg.fov_down_deg:
        raise InvalidValueError(
            f"{prefix}fov_up_deg={cfg.fov_up_deg} must be above {prefix}fov_down_deg={cfg.fov_down_deg}")
    if not cfg.max_range > 0:
        raise InvalidValueError(f"{prefix}max_range={cfg.max_range}; it must be positive (metres)")
    if cfg.min_xy < 0:
        raise InvalidValueError(f"{prefix}min_xy={cfg.min_xy}; it must be >= 0 (metres)")
