"""vseq2pc_node's parameters: every leaf of NodeConfig, walked by :mod:`ros_common.params`.

Every leaf of :class:`~vseq2pc_ros.config.NodeConfig` is one parameter named by its
dotted path (``match.top_k``, ``extrinsics.rpy``, ``map.path`` ...), its default the
dataclass default. Descriptions, ranges and the run-time-settable flag come from
:data:`DOCS` below (not lcpr_node's table: the names overlap but mean other things).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from rclpy.node import Node

from ros_common.config import SHARED_DOCS
from ros_common.params import Leaf, ParamDoc, build, describe, leaves, to_yaml, unique
from ros_common.ros_params import RuntimeParameters

from .config import EXTRINSICS_FORMATS, NodeConfig

BIG = 2**31 - 1

YAML_HEADER = """vseq2pc_node parameters (node name vseq2pc) with their defaults, from vseq2pc_ros.config.NodeConfig.
Use: vseq2pc_node --ros-args --params-file config/vseq2pc.yaml
Regenerate after adding fields:
  python -c "from vseq2pc_ros.params import yaml_text; print(yaml_text(), end='')" > config/vseq2pc.yaml
"""

DOCS: dict[str, ParamDoc] = {
    **SHARED_DOCS,
    "lidar_topic": ParamDoc("sensor_msgs/PointCloud2 with x, y, z and a label field (SemanticKITTI ids) for the map"),
    "depth_topic": ParamDoc("sensor_msgs/Image metric depth: 32FC1 metres or 16UC1 millimetres (0 = unknown)"),
    "labels_topic": ParamDoc("sensor_msgs/Image SemanticKITTI label ids (mono8/8UC1/mono16/16UC1, 32SC1 = uint32 "
                             "bits), pixel-aligned with the depth image"),
    "camera_info_topic": ParamDoc("sensor_msgs/CameraInfo of the depth/label camera (pinhole K, no distortion)"),
    "image_topic": ParamDoc("the colour image; only counted in /diagnostics (the network reads depth + labels); "
                            "empty = not subscribed"),
    "odom_topic": ParamDoc("nav_msgs/Odometry: poses at cloud and camera stamps (sequence distances, map poses)"),
    "model.sequence": ParamDoc("VSeq2PC sequence-model weights: a file, or bundled (trained on synthetic drives "
                               "with a depth network's depth), bundled-exact (exact depth: LiDAR, stereo, RGB-D) or "
                               "seeded (random, testing only), the same name in model.descriptor"),
    "model.descriptor": ParamDoc("VSeq2PC descriptor-model weights (a file, or model.sequence's name); a map file "
                                 "must have been made with them"),
    "model.seed": ParamDoc("seed of the random weights (model.sequence seeded)", 0, BIG),
    "model.device": ParamDoc("torch device, e.g. cpu or cuda:0"),
    "model.threads": ParamDoc("torch intra-op threads; 0 = torch's default", 0, 1024),
    "match.top_k": ParamDoc("candidates per query", 1, 1000, dynamic=True),
    "match.exclude_recent_s": ParamDoc("scans stamped later than the query stamp minus this are not matched",
                                       0.0, 1e9, dynamic=True),
    "match.min_probability": ParamDoc("candidates with a lower match probability are not published",
                                      0.0, 1.0, dynamic=True),
    "match.prefilter": ParamDoc("0 = score every scan; M = FAISS top-M scans by descriptor distance first",
                                0, BIG, dynamic=True),
    "verify.enabled": ParamDoc("register each query's camera pseudo-cloud (depth over the sequence, stacked with "
                               "odometry) against its candidate scans' clouds; ~/loop_closure then publishes verified "
                               "loops only (false: the most probable candidate, unverified)", dynamic=True),
    "verify.top_k": ParamDoc("the best this-many candidates of each query are registered", 1, 1000, dynamic=True),
    "verify.min_fitness": ParamDoc("share of the pseudo-cloud within reach of the scan's surfaces a verified "
                                   "candidate needs", 0.0, 1.0, dynamic=True),
    "verify.min_support": ParamDoc("accepted candidates (itself included) that must put the camera at one map pose "
                                   "(1 m, 3 deg) for a candidate to count as verified; 1 = no consensus rule",
                                   1, 1000, dynamic=True),
    "verify.max_depth": ParamDoc("m along the optical axis: farther depth is left out of the pseudo-cloud "
                                 "(a depth network's error grows with range)", 0.5, 1000.0, dynamic=True),
    "verify.max_frames": ParamDoc("camera frames stacked into one pseudo-cloud at most (evenly spaced)", 1, 1000,
                                  dynamic=True),
    "verify.consistency": ParamDoc("queries (this one included) that must verify and agree on the camera's map pose "
                                   "through odometry before a loop is published; 1 = no temporal gate", 1, 16,
                                   dynamic=True),
    "verify.consistency_m": ParamDoc("m: how far an earlier query's verified camera pose, moved on by odometry, may "
                                     "land from this query's", 0.01, 100.0, dynamic=True),
    "verify.consistency_deg": ParamDoc("deg: the same for the rotation", 0.01, 180.0, dynamic=True),
    "verify.consistency_spacing": ParamDoc("m of odometry travel between the queries of the chain at least "
                                           "(0 = consecutive queries)", 0.0, 1000.0, dynamic=True),
    "verify.consistency_backfill": ParamDoc("a loop the chain confirms also confirms the earlier queries of its "
                                            "chain: their loops are published then, late (/diagnostics: 'frames "
                                            "loops confirmed late'); false = only the confirming query's",
                                            dynamic=True),
    "sequence.offsets": ParamDoc("m after the query frame of the sequence's later frames (ascending)"),
    "sequence.min_query_spacing": ParamDoc("m between query frames; 0 = every camera frame", 0.0, 1e6),
    "sequence.max_pending": ParamDoc("queries waiting for their last frame at most", 1, BIG),
    "scan.min_distance": ParamDoc("m travelled between clouds added to the map; 0 = every cloud", 0.0, 1e6,
                                  dynamic=True),
    "scan.min_interval": ParamDoc("s (header stamps) between clouds added to the map; 0 = off", 0.0, 3600.0,
                                  dynamic=True),
    "camera.min_distance": ParamDoc("m travelled between camera frames used; 0 = every frame", 0.0, 1e6,
                                    dynamic=True),
    "camera.min_interval": ParamDoc("s (header stamps) between camera frames used; 0 = off", 0.0, 3600.0,
                                    dynamic=True),
    "extrinsics.format": ParamDoc("which camera-to-LiDAR transform is used: xyz_rpy or matrix",
                                  choices=EXTRINSICS_FORMATS, dynamic=True),
    "extrinsics.xyz": ParamDoc("camera optical-frame origin in the LiDAR frame, m (default: KITTI-like rig)",
                               dynamic=True),
    "extrinsics.rpy": ParamDoc("roll, pitch, yaw of the optical frame in the LiDAR frame, rad (R = Rz Ry Rx)",
                               dynamic=True),
    "extrinsics.matrix": ParamDoc("lidar_T_cam 4 x 4 row-major (16 values), used when extrinsics.format = matrix",
                                  dynamic=True),
    "sync.slop": ParamDoc("s: depth and label images this close pair up; odometry nearest within this",
                          0.0, 10.0, dynamic=True),
    "sync.odom_max_gap": ParamDoc("s: odometry neighbours at most this far apart are interpolated", 0.0, 60.0,
                                  dynamic=True),
    "sync.max_wait": ParamDoc("s of wall time a cloud or camera frame waits for its pose and camera_info",
                              0.0, 60.0, dynamic=True),
    "sync.image_buffer": ParamDoc("unpaired depth / label images kept per stream", 1, 1000),
    "sync.max_pending": ParamDoc("clouds and camera frames waiting for a pose at most (oldest dropped)", 1, 10000),
    "sync.jump_back": ParamDoc("s: a header stamp this much older than its stream's newest (a bag played again, "
                               "--loop, a simulator reset) starts a new session in the same map; 0 = refuse it "
                               "as out of order", 0.0, 86400.0),
    "map.path": ParamDoc("scan map file (.npz), loaded at start when it exists, saved on ~/save_map and at "
                         "shutdown; empty = in memory only"),
    "worker.max_waiting": ParamDoc("clouds / camera frames queued for the worker (oldest dropped when full)",
                                   1, 100000),
}


def all_leaves() -> list[Leaf]:
    """Every parameter of the node, names unique."""
    return unique(leaves(NodeConfig(), docs=DOCS))


def settings_from(values: Mapping[str, Any]) -> NodeConfig:
    """NodeConfig from Python-typed parameter values; ConfigError with the reason if refused."""
    return build(NodeConfig, values)


def yaml_text() -> str:
    """config/vseq2pc.yaml: every parameter with its default and description."""
    return to_yaml(all_leaves(), header=YAML_HEADER)


def make_runtime(node: Node, leaves_: Sequence[Leaf], apply: Any) -> RuntimeParameters:
    """ros_common's run-time validation, building this node's config."""
    return RuntimeParameters(node, leaves_, apply, build=settings_from)


def describe_all() -> str:
    """The parameter list of ``vseq2pc_node --help``."""
    return describe(all_leaves())


MARKDOWN_PAGE = "docs/reference/vseq2pc_node_parameters.md"
MARKDOWN_HEADER = f"""# vseq2pc_node parameters

Every parameter of `vseq2pc_node` (node name `vseq2pc`) with its default, type, accepted range and
description, generated from `vseq2pc_ros.config.NodeConfig` and `vseq2pc_ros.params.DOCS`, as
`config/vseq2pc.yaml` is. "run time" marks the parameters that can change while the node runs
(`ros2 param set`); the others are read at start. Invalid values are refused with the reason, at
start (exit 1) and at run time. `vseq2pc_node --help` prints the same list.

Do not edit this page: `test/project/test_docs_site.py` fails when it differs from the dataclasses.
Regenerate it with

```bash
.venv/bin/python -c "from vseq2pc_ros.params import markdown_text; print(markdown_text(), end='')" > {MARKDOWN_PAGE}
```
"""


def markdown_text() -> str:
    """docs/reference/vseq2pc_node_parameters.md: every parameter as Markdown tables (the docs site's page)."""
    from ros_common.params import to_markdown

    return f"{MARKDOWN_HEADER}\n{to_markdown(all_leaves())}"
