"""lcpr_backend's settings as typed config: one dataclass walked into dotted ROS parameters.

Topics, frames, the LiDAR mount, the graph files and the session name are the node's own; ``keyframes.*``,
``odometry.*``, ``loops.*`` and ``sessions.*`` are :mod:`lcpr_core.backend`'s dataclasses themselves, and the
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
from lcpr_core.backend import MAX_SESSION_NAME, BackendConfig, KeyframeRule, LoopPolicy, OdometryNoise, SessionPolicy
from lcpr_core.geometry import pose_from_xyz_rpy
from ros_common.config import DiagnosticsConfig, MapFileConfig, check_node_fields, input_qos_param, require
from ros_common.params import Leaf, build, describe, leaves, read_params_file, to_yaml, unique

__all__ = ["MARKDOWN_PAGE", "BackendNodeConfig", "GraphFileConfig", "LidarMount", "all_leaves", "describe_all",
           "markdown_text", "settings_from", "settings_from_file", "yaml_text"]



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

    path: str = param("", "graph file (.npz): loaded at start when it exists (the graph continues, prior_graph "
                          "not read: the file already holds it), saved by ~/save_graph and at shutdown; empty = "
                          "in memory only")
    save_on_shutdown: bool = param(True, "save the graph to graph.path when the node stops (Ctrl-C, SIGTERM)")


@dataclass(frozen=True, kw_only=True)
class BackendNodeConfig:
    odom_topic: str = param("/odom", "nav_msgs/Odometry of any odometry (KISS-ICP, LIO, wheels): world_T_base, in "
                                     "stamp order")
    candidates_topic: str = param("/lcpr/candidates", "the detector's ~/candidates (std_msgs/Float64MultiArray); "
                                                      "rows with verified = 1 become loops")
    sessions_topic: str = param("/lcpr/sessions", "the detector's ~/sessions (std_msgs/String, a JSON list of "
                                                  "session names, latched): the names of the session codes in "
                                                  "~/candidates; empty = not subscribed (every row is this run's "
                                                  "session)")
    session: str = param("session", "this run's session name: its odometry's session in the graph, and the "
                                    "name the detector's rows give it (the detector's session; both default to "
                                    "'session'); a graph's held prior sessions cannot be it")
    peers: tuple[str, ...] = param((), "namespaces of the other robots whose odometry this back end merges: each "
                                        "one's <namespace>/<odom_topic without its leading slash> is subscribed "
                                        "(e.g. ['/robot2'] -> /robot2/odom) as a session of its own "
                                        "(peer_sessions); each robot's detector must run with that session name "
                                        "(session:=robot2); empty = this run's odometry only")
    peer_sessions: tuple[str, ...] = param((), "the session name of each peer, in the order of peers; empty = each "
                                                "namespace's last component ('/robot2' -> 'robot2')")
    prior_graph: str = param("", "a saved graph (.npz) loaded at start as the prior map, held at its estimates "
                                 "(this run is placed in it by inter-session loops, ~/localized); ignored when "
                                 "graph.path's file exists (that file continues and already holds the prior), "
                                 "else the prior and this run are saved to graph.path; a file that cannot be read, "
                                 "or that holds this run's session name, refuses the start; empty = none")
    prior_map: str = param("", "the detector's map file (map.path) the prior graph was saved beside: at start the "
                               "graph is checked against it (its keyframes' sessions and stamps must be the "
                               "graph's), and a graph of another map refuses the start; empty = not checked")
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
    pending_s: float = param(5.0, "s of header time a loop waits for the odometry of its stamps (or for "
                                  "~/sessions to name its session codes) before it is dropped", lo=0.0, hi=3600.0)
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
    sessions: SessionPolicy = field(default_factory=SessionPolicy)

    def __post_init__(self) -> None:
        check_node_fields(self)
        require(bool(self.odom_topic), "odom_topic is empty; the back end needs an odometry")
        require(bool(self.candidates_topic), "candidates_topic is empty; give the detector's ~/candidates topic")
        require(bool(self.map_frame), "map_frame is empty; give the corrected frame's name (map)")
        require(0 < len(self.session) <= MAX_SESSION_NAME,
                f"session={self.session!r}; give this run a non-empty name of at most {MAX_SESSION_NAME} characters "
                "(the detector's session)")
        require(all(p.startswith("/") and p.strip("/") and " " not in p for p in self.peers),
                f"peers={list(self.peers)}; give each robot's namespace from the root, e.g. ['/robot2']")
        require(len({p.rstrip("/") for p in self.peers}) == len(self.peers),
                f"peers={list(self.peers)} repeat a namespace; give each robot once")
        require(not self.peer_sessions or len(self.peer_sessions) == len(self.peers),
                f"peer_sessions={list(self.peer_sessions)} names {len(self.peer_sessions)} sessions for "
                f"{len(self.peers)} peers {list(self.peers)}; give one name per peer, or none (each namespace's "
                "last component)")
        names = [self.session, *(name for name, _ in self.peer_odometry())]
        require(all(0 < len(n) <= MAX_SESSION_NAME for n in names),
                f"peer_sessions={list(self.peer_sessions)}; give each peer a non-empty name of at most "
                f"{MAX_SESSION_NAME} characters")
        require(len(set(names)) == len(names),
                f"session={self.session!r} and the peers' sessions {names[1:]} repeat a name; give every robot a "
                "session name of its own (peer_sessions)")

    def peer_odometry(self) -> tuple[tuple[str, str], ...]:
        """(session name, odometry topic) of each peer, in the order of ``peers``."""
        names = self.peer_sessions or tuple(p.rstrip("/").rsplit("/", 1)[-1] for p in self.peers)
        return tuple((name, f"{ns.rstrip('/')}/{self.odom_topic.lstrip('/')}")
                     for name, ns in zip(names, self.peers, strict=True))

    def backend(self) -> BackendConfig:
        return BackendConfig(base_T_lidar=self.lidar.matrix(), keyframes=self.keyframes, odometry=self.odometry,
                             loops=self.loops, sessions=self.sessions, level_sigma_deg=self.level_sigma_deg,
                             gravity_sigma_deg=self.gravity_sigma_deg, up_sigma_deg=self.up_sigma_deg,
                             up_warmup_m=self.up_warmup_m, up_world_sigma_deg=self.up_world_sigma_deg)


YAML_HEADER = """lcpr_backend parameters (node name lcpr_backend) with their defaults, from
backend_ros.config.BackendNodeConfig (keyframes.*, odometry.*, loops.*, sessions.*: lcpr_core.backend).
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


MARKDOWN_PAGE = "docs/reference/lcpr_backend_parameters.md"
MARKDOWN_INTRO = """\
Every parameter of `lcpr_backend` (node name `lcpr_backend`) with its default, type, accepted range and
description, generated from the config dataclasses (`backend_ros.config.BackendNodeConfig`; `keyframes.*`,
`odometry.*`, `loops.*`, `sessions.*`: `lcpr_core.backend`'s), as `config/lcpr_backend.yaml` is. Every
parameter is read at start. Invalid values are refused with the reason, at start (exit 1).
`lcpr_backend --help` prints the same list. What the node does with them: [lcpr_backend](../nodes/lcpr_backend.md)."""


def markdown_text() -> str:
    """docs/reference/lcpr_backend_parameters.md: every parameter as Markdown tables (the docs site's page)."""
    from ros_common.params import markdown_page

    return markdown_page(title="lcpr_backend parameters", intro=MARKDOWN_INTRO, page=MARKDOWN_PAGE,
                         module="backend_ros.config", leaves=all_leaves())
