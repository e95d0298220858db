"""PointCloud2 messages laid out byte for byte as common LiDAR drivers publish them.

Built by hand (PointField list, offsets, padding, point_step, row_step), independently of
msg_tools' writer, from the drivers' point types:
- Ouster (ouster-ros ``PointXYZIRT``-style "original" layout): x y z + 4 pad bytes,
  intensity f32 @16, t u32 @20, reflectivity u16 @24, ring u16 @26, ambient u16 @28,
  range u32 @32, padded to 48; organised rows x 1024; no return = x = y = z = 0.
- Velodyne (velodyne_pointcloud ``PointXYZIRT``): x y z + pad, intensity f32 @16, ring u16 @20,
  time f32 @24, point_step 32; unorganised, or organised by ring with NaN for no return.
- Hesai (HesaiLidar ROS ``PointXYZIT``): x y z + pad, intensity f32 @16, timestamp f64 @24,
  ring u16 @32, point_step 48.
- Livox (livox_ros_driver2 PointCloud2): x y z intensity f32, tag u8 @16, line u8 @17,
  timestamp f64 @18 (unaligned), point_step 26.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msg_tools.types import message_class

PointCloud2 = message_class("sensor_msgs/msg/PointCloud2")
PointField = message_class("sensor_msgs/msg/PointField")
Header = message_class("std_msgs/msg/Header")
Time = message_class("builtin_interfaces/msg/Time")

ROS_DATATYPES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


@dataclass(frozen=True)
class DriverLayout:
    name: str
    fields: tuple[tuple[str, str, int], ...]  # (name, numpy type code, offset)
    point_step: int
    rows: int  # 1 = unorganised
    invalid: str  # how a beam without a return is published: "zero", "nan" or "absent"

    def dtype(self) -> np.dtype:
        return np.dtype({"names": [f[0] for f in self.fields], "formats": ["<" + f[1] for f in self.fields],
                         "offsets": [f[2] for f in self.fields], "itemsize": self.point_step})


XYZ = (("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8))
LAYOUTS = {
    "ouster_os1_64": DriverLayout("ouster_os1_64", XYZ + (("intensity", "f4", 16), ("t", "u4", 20),
                                  ("reflectivity", "u2", 24), ("ring", "u2", 26), ("ambient", "u2", 28),
                                  ("range", "u4", 32)), 48, 64, "zero"),
    "ouster_os2_128": DriverLayout("ouster_os2_128", XYZ + (("intensity", "f4", 16), ("t", "u4", 20),
                                   ("reflectivity", "u2", 24), ("ring", "u2", 26), ("ambient", "u2", 28),
                                   ("range", "u4", 32)), 48, 128, "zero"),
    "velodyne_vlp16": DriverLayout("velodyne_vlp16", XYZ + (("intensity", "f4", 16), ("ring", "u2", 20),
                                   ("time", "f4", 24)), 32, 1, "absent"),
    "velodyne_hdl32_organised": DriverLayout("velodyne_hdl32_organised", XYZ + (("intensity", "f4", 16),
                                             ("ring", "u2", 20), ("time", "f4", 24)), 32, 32, "nan"),
    "hesai_pandar64": DriverLayout("hesai_pandar64", XYZ + (("intensity", "f4", 16), ("timestamp", "f8", 24),
                                   ("ring", "u2", 32)), 48, 1, "absent"),
    "livox": DriverLayout("livox", XYZ + (("intensity", "f4", 12), ("tag", "u1", 16), ("line", "u1", 17),
                          ("timestamp", "f8", 18)), 26, 1, "absent"),
}


def driver_cloud(layout: DriverLayout, xyz: np.ndarray, valid: np.ndarray, *, stamp: float = 1.0,
                 bigendian: bool = False, rclpy_types: bool = False) -> object:
    """A PointCloud2 of ``layout`` holding ``xyz`` (rows * columns points, row-major for organised
    layouts); points where ``valid`` is False are published as the driver marks a missing return
    ("absent" layouts leave them out). Padding bytes hold 0xEE, as uninitialised memory might.
    A rosbags message, or with ``rclpy_types`` one of the installed ROS 2 message classes."""
    dt = layout.dtype()
    if bigendian:
        dt = dt.newbyteorder(">")
    keep = np.ones(len(xyz), bool) if layout.invalid != "absent" else valid
    n = int(keep.sum())
    raw = np.full(n * layout.point_step, 0xEE, np.uint8)
    points = np.ndarray((n,), dtype=dt, buffer=raw)
    for name, _, _ in layout.fields:
        points[name] = 0
    xyz_kept = xyz[keep].astype(np.float64)
    missing = ~valid[keep]
    if layout.invalid == "zero":
        xyz_kept[missing] = 0.0
    elif layout.invalid == "nan":
        xyz_kept[missing] = np.nan
    names = {f[0] for f in layout.fields}
    for k, axis in enumerate("xyz"):
        if axis in names:
            points[axis] = xyz_kept[:, k]
    if "intensity" in names:
        points["intensity"] = 7.0
    if "ring" in names:
        points["ring"] = np.arange(n) % max(layout.rows, 16)
    if "range" in names:
        points["range"] = np.where(missing, 0, np.round(np.linalg.norm(np.nan_to_num(xyz_kept), axis=1) * 1000))
    height = layout.rows if layout.rows > 1 else 1
    width = n // height
    if rclpy_types:
        from builtin_interfaces.msg import Time as CloudTime
        from sensor_msgs.msg import PointCloud2 as Cloud
        from sensor_msgs.msg import PointField as Field
        from std_msgs.msg import Header as CloudHeader
        data: object = raw.tobytes()
    else:
        Cloud, Field, CloudHeader, CloudTime, data = PointCloud2, PointField, Header, Time, raw
    fields = [Field(name=name, offset=offset, datatype=ROS_DATATYPES[code], count=1)
              for name, code, offset in layout.fields]
    sec = int(stamp)
    header = CloudHeader(stamp=CloudTime(sec=sec, nanosec=int(round((stamp - sec) * 1e9))), frame_id="lidar")
    return Cloud(header=header, height=height, width=width, fields=fields, is_bigendian=bigendian,
                 point_step=layout.point_step, row_step=layout.point_step * width, data=data,
                 is_dense=layout.invalid == "absent")


def scan(rows: int, columns: int = 1024, *, seed: int = 0, missing: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(rows * columns x 3 points of a spinning LiDAR in a 20 m room with pillars, row-major by beam;
    whether each beam returned)."""
    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(15.0, -15.0, rows))[:, None]
    azimuth = np.radians(np.linspace(180.0, -180.0, columns, endpoint=False))[None, :]
    distance = 8.0 + 4.0 * np.cos(3 * azimuth) + 0.0 * elevation + rng.uniform(0, 0.05, (rows, columns))
    xyz = np.stack([distance * np.cos(elevation) * np.cos(azimuth), distance * np.cos(elevation) * np.sin(azimuth),
                    distance * np.sin(elevation) + 0.0 * azimuth], axis=-1).reshape(-1, 3)
    valid = rng.random(rows * columns) >= missing
    return xyz, valid
