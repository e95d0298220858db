"""lcpr_backend's settings as typed config: one dataclass walked into dotted ROS parameters.

Topics, frames, the LiDAR mount and the graph file are the node's own; ``keyframes.*``,
``odometry.*`` and ``loops.*`` are :mod:`lcpr_core.backend`'s dataclasses themselves, and the
``*_sigma_deg`` / ``up_warmup_m`` fields take their default and metadata from
:class:`~lcpr_core.backend.BackendConfig`'s, so a parameter and the core option it sets are one
field. Each field carries its description, range or choices (:func:`lcpr_common.params.param`).
No rclpy import (tested without ROS).
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lcpr_common.params import param, param_from
from lcpr_core.backend import BackendConfig, KeyframeRule, LoopPolicy, OdometryNoise
from lcpr_core.geometry import pose_from_xyz_rpy
from ros_common.config import DiagnosticsConfig, MapFileConfig, check_node_fields, input_qos_param, require
from ros_common.params import Leaf, build, describe, leaves, read_params_file, to_yaml, unique

__all__ = ["BackendNodeConfig", "GraphFileConfig", "LidarMount", "all_leaves", "describe_all", "settings_from",
           "settings_from_file", "yaml_text"]


@dataclass(frozen=True, kw_only=True)
class LidarMount:
    """base_T_lidar: where the LiDAR the loops are measured in sits on the vehicle (odometry's child frame)."""

    xyz: tuple[float, ...] = param((0.0, 0.0, 0.0), "m: the LiDAR in the base frame (the odometry's child frame); "
                                                    "loops and clouds are in the LiDAR's frame, poses in the base "
                                                    "frame's")
    # as URDF and tf2
    rpy: tuple[float, ...] = param((0.0, 0.0, 0.0), "rad: roll, pitch, yaw of the LiDAR in the base frame (R = Rz Ry "
                                                    "Rx)")

    def __post_init__(self) -> None:
        require(len(self.xyz) == 3 and all(math.isfinite(v) for v in self.xyz),
                f"xyz={list(self.xyz)}; give 3 finite metres")
        require(len(self.rpy) == 3 and all(math.isfinite(v) for v in self.rpy),
                f"rpy={list(self.rpy)}; give 3 finite radians (roll, pitch, yaw)")

    def matrix(self) -> np.ndarray:
        return pose_from_xyz_rpy(self.xyz, self.rpy)


@dataclass(frozen=True)
class GraphFileConfig(MapFileConfig):
    """Where the graph is kept between runs (a map file of its own, described as such)."""

    path: str = param("", "graph file (.npz): loaded at start when it exists (the graph continues), saved by "
                          "~/save_graph and at shutdown; empty = in memory only")
    save_on_shutdown: bool = param(True, "save the graph to graph.path when the node stops (Ctrl-C, SIGTERM)")


@dataclass(frozen=True, kw_only=True)
class BackendNodeConfig:
    odom_topic: str = param("/odom", "nav_msgs/Odometry of any odometry (KISS-ICP, LIO, wheels): world_T_base, in "
                                     "stamp order")
    candidates_topic: str = param("/lcpr/candidates", "the detector's ~/candidates (std_msgs/Float64MultiArray); "
                                                      "rows with verified = 1 become loops")
    up_topic: str = param("/lcpr/up", "the detector's ~/up (geometry_msgs/Vector3Stamped: each keyframe's up "
                                      "measured from its walls, in the LiDAR frame); empty = not subscribed")
    input_qos: str = input_qos_param("QoS of the odometry subscription: best_available, sensor_data (best effort) or "
                                     "reliable")
    map_frame: str = param("map", "frame of the corrected poses (~/odometry, ~/path) and parent of map -> odom")
    odom_frame: str = param("", "child of map -> odom; empty = the odometry messages' header.frame_id")
    base_frame: str = param("", "child_frame_id of ~/odometry; empty = the odometry messages' child_frame_id")
    lidar: LidarMount = field(default_factory=LidarMount)
    path_period: float = param(1.0, "s between ~/path messages at most (a loop publishes one at once)", lo=0.01,
                               hi=3600.0)
    pending_s: float = param(5.0, "s of header time a loop waits for the odometry of its stamps before it is "
                                  "refused", lo=0.0, hi=3600.0)
    level_sigma_deg: float = param_from(BackendConfig, "level_sigma_deg")
    gravity_sigma_deg: float = param_from(BackendConfig, "gravity_sigma_deg")
    up_sigma_deg: float = param_from(BackendConfig, "up_sigma_deg")
    up_warmup_m: float = param_from(BackendConfig, "up_warmup_m")
    up_world_sigma_deg: float = param_from(BackendConfig, "up_world_sigma_deg")
    graph: GraphFileConfig = field(default_factory=GraphFileConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)
    keyframes: KeyframeRule = field(default_factory=KeyframeRule)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    loops: LoopPolicy = field(default_factory=LoopPolicy)

    def __post_init__(self) -> None:
        check_node_fields(self)
        require(bool(self.odom_topic), "odom_topic is empty; the back end needs an odometry")
        require(bool(self.candidates_topic), "candidates_topic is empty; give the detector's ~/candidates topic")
        require(bool(self.map_frame), "map_frame is empty; give the corrected frame's name (map)")

    def backend(self) -> BackendConfig:
        return BackendConfig(base_T_lidar=self.lidar.matrix(), keyframes=self.keyframes, odometry=self.odometry,
                             loops=self.loops, level_sigma_deg=self.level_sigma_deg,
                             gravity_sigma_deg=self.gravity_sigma_deg, up_sigma_deg=self.up_sigma_deg,
                             up_warmup_m=self.up_warmup_m, up_world_sigma_deg=self.up_world_sigma_deg)


YAML_HEADER = """lcpr_backend parameters (node name lcpr_backend) with their defaults, from
backend_ros.config.BackendNodeConfig (keyframes.*, odometry.*, loops.*: lcpr_core.backend).
Use: lcpr_backend --ros-args --params-file config/lcpr_backend.yaml
Regenerate after adding fields:
  python -c "from backend_ros.config import yaml_text; print(yaml_text(), end='')" > config/lcpr_backend.yaml
"""


def all_leaves() -> list[Leaf]:
    """Every parameter of the node, names unique."""
    return unique(leaves(BackendNodeConfig()))


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
