"""lcpr_backend's settings as typed config: one dataclass walked into dotted ROS parameters.

Topics, frames, the LiDAR mount and the graph file are the node's own; ``keyframes.*``,
``odometry.*`` and ``loops.*`` are :mod:`lcpr_core.backend`'s dataclasses themselves, so a parameter
and the core option it sets are one field. No rclpy import (tested without ROS).
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lcpr_core.backend import BackendConfig, KeyframeRule, LoopPolicy, OdometryNoise
from lcpr_core.geometry import pose_from_xyz_rpy
from ros_common.config import INPUT_QOS, SHARED_DOCS, DiagnosticsConfig, MapFileConfig, require
from ros_common.params import Leaf, ParamDoc, build, describe, leaves, read_params_file, to_yaml, unique

__all__ = ["BackendNodeConfig", "DOCS", "LidarMount", "all_leaves", "describe_all", "settings_from",
           "settings_from_file", "yaml_text"]

BIG = 2**31 - 1


@dataclass(frozen=True, kw_only=True)
class LidarMount:
    """base_T_lidar: where the LiDAR the loops are measured in sits on the vehicle (odometry's child frame)."""

    xyz: tuple[float, ...] = (0.0, 0.0, 0.0)  # m, the LiDAR origin in the base frame
    rpy: tuple[float, ...] = (0.0, 0.0, 0.0)  # rad; R = Rz(yaw) Ry(pitch) Rx(roll), as URDF and tf2

    def __post_init__(self) -> None:
        require(len(self.xyz) == 3 and all(math.isfinite(v) for v in self.xyz),
                f"xyz={list(self.xyz)}; give 3 finite metres")
        require(len(self.rpy) == 3 and all(math.isfinite(v) for v in self.rpy),
                f"rpy={list(self.rpy)}; give 3 finite radians (roll, pitch, yaw)")

    def matrix(self) -> np.ndarray:
        return pose_from_xyz_rpy(self.xyz, self.rpy)


@dataclass(frozen=True, kw_only=True)
class BackendNodeConfig:
    odom_topic: str = "/odom"  # nav_msgs/Odometry of any odometry (world_T_base)
    candidates_topic: str = "/lcpr/candidates"  # the detector's ~/candidates table
    up_topic: str = "/lcpr/up"  # the detector's ~/up (geometry_msgs/Vector3Stamped); "" = not subscribed
    input_qos: str = "best_available"  # of the odometry subscription (ros_common.qos)
    map_frame: str = "map"
    odom_frame: str = ""  # "" = the odometry messages' header.frame_id
    base_frame: str = ""  # "" = the odometry messages' child_frame_id
    lidar: LidarMount = field(default_factory=LidarMount)
    path_period: float = 1.0  # s (wall) between ~/path messages at most; a loop publishes at once
    pending_s: float = 5.0  # s of header time a loop waits for the odometry of its stamps
    level_sigma_deg: float = 0.0  # > 0: each node's up axis pulled to the world's up (ground vehicles); 0 = off
    gravity_sigma_deg: float = 0.0  # > 0: each node's tilt held to the odometry's (LIO: it measures gravity); 0 = off
    up_sigma_deg: float = BackendConfig().up_sigma_deg  # std dev of a measured up (up_topic); 0 = ignored
    up_warmup_m: float = BackendConfig().up_warmup_m  # m of travel whose measured ups set the world's up
    up_world_sigma_deg: float = BackendConfig().up_world_sigma_deg  # > 0: the world's up a graph variable
    graph: MapFileConfig = field(default_factory=MapFileConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)
    keyframes: KeyframeRule = field(default_factory=KeyframeRule)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    loops: LoopPolicy = field(default_factory=LoopPolicy)

    def __post_init__(self) -> None:
        require(bool(self.odom_topic), "odom_topic is empty; the back end needs an odometry")
        require(bool(self.candidates_topic), "candidates_topic is empty; give the detector's ~/candidates topic")
        require(self.input_qos in INPUT_QOS, f"input_qos={self.input_qos!r}; accepted: {', '.join(INPUT_QOS)}")
        require(bool(self.map_frame), "map_frame is empty; give the corrected frame's name (map)")
        require(math.isfinite(self.path_period) and self.path_period > 0,
                f"path_period={self.path_period}; it must be > 0 s")
        require(math.isfinite(self.pending_s) and self.pending_s >= 0, f"pending_s={self.pending_s}; it must be >= 0")
        for name in ("level_sigma_deg", "gravity_sigma_deg", "up_sigma_deg", "up_warmup_m", "up_world_sigma_deg"):
            value = getattr(self, name)
            require(math.isfinite(value) and value >= 0, f"{name}={value}; it must be >= 0 (0 = off)")

    def backend(self) -> BackendConfig:
        return BackendConfig(base_T_lidar=self.lidar.matrix(), keyframes=self.keyframes, odometry=self.odometry,
                             loops=self.loops, level_sigma_deg=self.level_sigma_deg,
                             gravity_sigma_deg=self.gravity_sigma_deg, up_sigma_deg=self.up_sigma_deg,
                             up_warmup_m=self.up_warmup_m, up_world_sigma_deg=self.up_world_sigma_deg)


DOCS: dict[str, ParamDoc] = {
    **SHARED_DOCS,
    "odom_topic": ParamDoc("nav_msgs/Odometry of any odometry (KISS-ICP, LIO, wheels): world_T_base, in stamp order"),
    "candidates_topic": ParamDoc("the detector's ~/candidates (std_msgs/Float64MultiArray); rows with verified = 1 "
                                 "become loops"),
    "up_topic": ParamDoc("the detector's ~/up (geometry_msgs/Vector3Stamped: each keyframe's up measured from its "
                         "walls, in the LiDAR frame); empty = not subscribed"),
    "input_qos": ParamDoc("QoS of the odometry subscription: best_available, sensor_data (best effort) or reliable",
                          choices=INPUT_QOS),
    "map_frame": ParamDoc("frame of the corrected poses (~/odometry, ~/path) and parent of map -> odom"),
    "odom_frame": ParamDoc("child of map -> odom; empty = the odometry messages' header.frame_id"),
    "base_frame": ParamDoc("child_frame_id of ~/odometry; empty = the odometry messages' child_frame_id"),
    "lidar.xyz": ParamDoc("m: the LiDAR (the loops' frame) in the base frame (the odometry's child frame)"),
    "lidar.rpy": ParamDoc("rad: roll, pitch, yaw of the LiDAR in the base frame (R = Rz Ry Rx)"),
    "path_period": ParamDoc("s between ~/path messages at most (a loop publishes one at once)", 0.01, 3600.0),
    "pending_s": ParamDoc("s of header time a loop waits for the odometry of its stamps before it is refused",
                          0.0, 3600.0),
    "level_sigma_deg": ParamDoc("deg: std dev of a level prior on every graph node (a ground vehicle level on "
                                "average, or an IMU's gravity; removes the tilt loops cannot see); 0 = off",
                                0.0, 90.0),
    "gravity_sigma_deg": ParamDoc("deg: std dev holding every graph node's roll and pitch to the odometry's, for an "
                                  "odometry that measures gravity (FAST-LIO2, LIO-SAM, Point-LIO: 0.5); 0 = off "
                                  "(KISS-ICP and other LiDAR-only odometry drift in tilt)", 0.0, 90.0),
    "up_sigma_deg": ParamDoc("deg: std dev of a keyframe's up measured from its walls (up_topic; Huber kernel): "
                             "holds the roll and pitch loops cannot see, on slopes too; 0 = ignored", 0.0, 90.0),
    "up_warmup_m": ParamDoc("m of travel from the first node whose measured ups, averaged, set the world's up",
                            0.0, 1e6),
    "up_world_sigma_deg": ParamDoc("deg: > 0 makes the world's up a graph variable held to the warm-up's mean with "
                                   "this std dev and refined by every up (noisy ups tilt the map less; add_loop p95 "
                                   "several times dearer); 0 = fixed at the warm-up's mean", 0.0, 90.0),
    "graph.path": ParamDoc("graph file (.npz): loaded at start when it exists (the graph continues), saved by "
                           "~/save_graph and at shutdown; empty = in memory only"),
    "graph.save_on_shutdown": ParamDoc("save the graph to graph.path when the node stops (Ctrl-C, SIGTERM)"),
    "keyframes.distance": ParamDoc("m moved since the last graph node that makes a message a node; 0 = off",
                                   0.0, 1e6),
    "keyframes.angle_deg": ParamDoc("deg turned since the last node that makes a message a node; 0 = off", 0.0, 360.0),
    "keyframes.interval": ParamDoc("s since the last node that makes a message a node (standing still); 0 = off",
                                   0.0, 1e6),
    "odometry.translation_frac": ParamDoc("std dev of x and y between nodes, per metre moved", 1e-6, 1.0),
    "odometry.z_frac": ParamDoc("std dev of z between nodes, per metre moved", 1e-6, 1.0),
    "odometry.yaw_deg_per_m": ParamDoc("yaw std dev between nodes, deg per sqrt(metre moved)", 1e-6, 100.0),
    "odometry.roll_pitch_deg_per_m": ParamDoc("roll and pitch std dev between nodes, deg per sqrt(metre)",
                                              1e-6, 100.0),
    "odometry.rotation_frac": ParamDoc("extra rotation std dev between nodes, per radian turned", 0.0, 1.0),
    "loops.robust": ParamDoc("robust kernel of loop factors", choices=("none", "huber", "cauchy")),
    "loops.robust_param": ParamDoc("the kernel's k, in whitened (Mahalanobis) units", 1e-3, 1e3),
    "loops.default_sigmas": ParamDoc("std devs of a loop without a covariance: x, y, z (m), roll, pitch, yaw (deg)"),
    "loops.stamp_tolerance": ParamDoc("s: a loop stamp farther than this from every odometry message is refused",
                                      0.0, 60.0),
    "loops.attach_tolerance": ParamDoc("s: the graph node nearest to a loop stamp must be this close", 0.0, 3600.0),
    "loops.gate": ParamDoc("chi-square probability of the consistency check (6 dof); 1 = no check", 1e-6, 1.0),
    "loops.iterations": ParamDoc("extra iSAM2 updates after a loop that moved the graph, at most", 0, 100),
    "loops.min_spacing_m": ParamDoc("m of travel: a loop whose both ends lie within this of an accepted loop's ends "
                                    "is skipped as redundant (fewer iSAM2 updates where a place is closed again and "
                                    "again); 0 = take every loop", 0.0, 1e6),
    "loops.covariance_scale": ParamDoc("every loop covariance (given or default) is multiplied by this: a detector "
                                       "whose covariances are too tight (> 1) or too loose (< 1)", 1e-6, 1e6),
}

YAML_HEADER = """lcpr_backend parameters (node name lcpr_backend) with their defaults, from
lcpr_ros.backend_config.BackendNodeConfig (keyframes.*, odometry.*, loops.*: lcpr_core.backend).
Use: lcpr_backend --ros-args --params-file config/lcpr_backend.yaml
Regenerate after adding fields:
  python -c "from lcpr_ros.backend_config import yaml_text; print(yaml_text(), end='')" > config/lcpr_backend.yaml
"""


def all_leaves() -> list[Leaf]:
    """Every parameter of the node, names unique."""
    return unique(leaves(BackendNodeConfig(), docs=DOCS))


def settings_from(values: Mapping[str, Any]) -> BackendNodeConfig:
    """The node's config from Python-typed parameter values, absent ones at their defaults (ConfigError if refused)."""
    config: BackendNodeConfig = build(BackendNodeConfig, values)
    return config


def settings_from_file(path: str | os.PathLike[str]) -> BackendNodeConfig:
    return settings_from(read_params_file(path, all_leaves()))


def yaml_text() -> str:
    return to_yaml(all_leaves(), header=YAML_HEADER)


def describe_all() -> str:
    return describe(all_leaves())
