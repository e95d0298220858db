"""The node's settings as typed config; every leaf becomes a dotted ROS parameter.

Each field carries its description, range or choices and run-time flag
(:func:`lcpr_common.params.param`), the one source of the parameter's descriptor, params-file
entry and reference row. ``__post_init__`` refuses a bad value with a ValueError naming it (turned
into a ConfigError by :mod:`vseq2pc_ros.params`). The default extrinsics are KITTI's published
sensor setup (camera 0 0.27 m ahead of the Velodyne, 0.06 m left, 0.08 m lower, level,
looking along +x; the simulator's KITTI-like rig copies the same numbers); any other vehicle
must set ``extrinsics.*`` to its own calibration, and the node warns at start while they are
left at this default.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lcpr_common.params import param
from lcpr_core.keyframes import KeyframeConfig
from lcpr_core.pretrained import BUNDLED, VSEQ2PC_WEIGHTS_NAMES
from lcpr_core.vseq2pc.consistency import ConsistencyConfig
from lcpr_core.vseq2pc.detector import SequenceDetectorConfig
from lcpr_core.vseq2pc.retrieval import SearchConfig
from lcpr_core.vseq2pc.sequence import OFFSETS, SequenceConfig
from lcpr_core.vseq2pc.verify import SequenceVerifyConfig
from msg_tools.frames import KITTI_TOPICS
from ros_common.config import DiagnosticsConfig, MapFileConfig, check_node_fields, input_qos_param, require

EXTRINSICS_FORMATS = ("xyz_rpy", "matrix")
DEFAULT_VERIFY = SequenceVerifyConfig()
HALF_PI = math.pi / 2
BIG = 2**31 - 1

#: lidar_T_cam of KITTI's sensor setup, camera 0 in the Velodyne frame (optical frame: z forward, x right, y down).
KITTI_LIDAR_T_CAM: tuple[float, ...] = (
    0.0, 0.0, 1.0, 0.27,
    -1.0, 0.0, 0.0, 0.06,
    0.0, -1.0, 0.0, -0.08,
    0.0, 0.0, 0.0, 1.0,
)


@dataclass(frozen=True)
class Vseq2pcModelConfig:
    sequence: str = param(BUNDLED, "VSeq2PC sequence-model weights: a file, or bundled (trained on synthetic "
                                   "drives with a depth network's depth), bundled-exact (exact depth: LiDAR, stereo, "
                                   "RGB-D) or seeded (random, testing only), the same name in model.descriptor")
    descriptor: str = param(BUNDLED, "VSeq2PC descriptor-model weights (a file, or model.sequence's name); a map "
                                     "file must have been made with them")
    seed: int = param(0, "seed of the random weights (model.sequence seeded)", lo=0, hi=BIG)
    device: str = param("cpu", "torch device, e.g. cpu or cuda:0")
    threads: int = param(0, "torch intra-op threads; 0 = torch's default", lo=0, hi=1024)

    def __post_init__(self) -> None:
        check_node_fields(self)
        named = [w in VSEQ2PC_WEIGHTS_NAMES for w in (self.sequence, self.descriptor)]
        require(named[0] == named[1] and (not named[0] or self.sequence == self.descriptor),
                f"model.sequence={self.sequence!r}, model.descriptor={self.descriptor!r}: give two weight files, "
                f"or the same name in both ({', '.join(VSEQ2PC_WEIGHTS_NAMES)})")
        require(bool(self.device), "device is empty; e.g. cpu or cuda:0")


@dataclass(frozen=True)
class Vseq2pcMatchConfig:
    top_k: int = param(10, "candidates per query", lo=1, hi=1000, dynamic=True)
    exclude_recent_s: float = param(30.0, "scans stamped later than the query stamp minus this are not matched",
                                    lo=0.0, hi=1e9, dynamic=True)
    min_probability: float = param(0.0, "candidates with a lower match probability are not published", lo=0.0,
                                   hi=1.0, dynamic=True)
    prefilter: int = param(0, "0 = score every scan; M = FAISS top-M scans by descriptor distance first", lo=0,
                           hi=BIG, dynamic=True)

    def __post_init__(self) -> None:
        check_node_fields(self)

    def search(self) -> SearchConfig:
        return SearchConfig(k=self.top_k, exclude_recent_s=self.exclude_recent_s,
                            prefilter=self.prefilter or None)


@dataclass(frozen=True)
class Vseq2pcVerifyParams:
    enabled: bool = param(True, "register each query's camera pseudo-cloud (depth over the sequence, stacked with "
                                "odometry) against its candidate scans' clouds; ~/loop_closure then publishes "
                                "verified loops only (false: the most probable candidate, unverified)", dynamic=True)
    top_k: int = param(10, "the best this-many candidates of each query are registered", lo=1, hi=1000,
                       dynamic=True)
    min_fitness: float = param(DEFAULT_VERIFY.min_fitness, "share of the pseudo-cloud within reach of the scan's "
                                                           "surfaces a verified candidate needs", lo=0.0, hi=1.0,
                               dynamic=True)
    min_support: int = param(DEFAULT_VERIFY.min_support, "accepted candidates (itself included) that must put the "
                                                         "camera at one map pose (1 m, 3 deg) for a candidate to "
                                                         "count as verified; 1 = no consensus rule", lo=1, hi=1000,
                             dynamic=True)
    max_depth: float = param(DEFAULT_VERIFY.pseudo.max_depth, "m along the optical axis: farther depth is left out "
                                                              "of the pseudo-cloud (a depth network's error grows "
                                                              "with range)", lo=0.5, hi=1000.0, dynamic=True)
    max_frames: int = param(DEFAULT_VERIFY.pseudo.max_frames, "camera frames stacked into one pseudo-cloud at most "
                                                              "(evenly spaced)", lo=1, hi=1000, dynamic=True)
    consistency: int = param(DEFAULT_VERIFY.consistency.count, "queries (this one included) that must verify and "
                                                               "agree on the camera's map pose through odometry "
                                                               "before a loop is published; 1 = no temporal gate",
                             lo=1, hi=16, dynamic=True)
    consistency_m: float = param(DEFAULT_VERIFY.consistency.max_m, "m: how far an earlier query's verified camera "
                                                                   "pose, moved on by odometry, may land from this "
                                                                   "query's", lo=0.01, hi=100.0, dynamic=True)
    consistency_deg: float = param(DEFAULT_VERIFY.consistency.max_deg, "deg: the same for the rotation", lo=0.01,
                                   hi=180.0, dynamic=True)
    consistency_spacing: float = param(DEFAULT_VERIFY.consistency.spacing_m, "m of odometry travel between the "
                                                                             "queries of the chain at least (0 = "
                                                                             "consecutive queries)", lo=0.0,
                                       hi=1000.0, dynamic=True)
    consistency_backfill: bool = param(DEFAULT_VERIFY.consistency.backfill, "a loop the chain confirms also "
                                                                            "confirms the earlier queries of its "
                                                                            "chain: their loops are published then, "
                                                                            "late (/diagnostics: 'frames loops "
                                                                            "confirmed late'); false = only the "
                                                                            "confirming query's", dynamic=True)

    def __post_init__(self) -> None:
        check_node_fields(self)
        try:
            self.core()
        except ValueError as err:
            raise ValueError(str(err).replace("verify.", "")) from None

    def core(self) -> SequenceVerifyConfig:
        pseudo = replace(DEFAULT_VERIFY.pseudo, max_depth=self.max_depth, max_frames=self.max_frames)
        gate = ConsistencyConfig(count=self.consistency, max_m=self.consistency_m, max_deg=self.consistency_deg,
                                 spacing_m=self.consistency_spacing, backfill=self.consistency_backfill)
        return replace(DEFAULT_VERIFY, enabled=self.enabled, top_k=self.top_k, min_fitness=self.min_fitness,
                       min_support=self.min_support, pseudo=pseudo, consistency=gate)


@dataclass(frozen=True)
class SequenceParams:
    offsets: tuple[float, ...] = param(OFFSETS, "m after the query frame of the sequence's later frames "
                                                "(ascending)")
    min_query_spacing: float = param(0.0, "m between query frames; 0 = every camera frame", lo=0.0, hi=1e6)
    max_pending: int = param(4096, "queries waiting for their last frame at most", lo=1, hi=BIG)

    def __post_init__(self) -> None:
        check_node_fields(self)
        try:
            self.builder()
        except ValueError as err:
            raise ValueError(str(err).replace("min_query_spacing_m", "min_query_spacing")) from None

    def builder(self) -> SequenceConfig:
        return SequenceConfig(offsets=tuple(self.offsets), min_query_spacing_m=self.min_query_spacing,
                              max_pending=self.max_pending)


class FilterConfig:
    """Which clouds or camera frames are used: at least ``min_distance`` m travelled and ``min_interval`` s
    (header stamps) after the last one used (0 = off); the two groups below each describe their own."""

    min_distance: float
    min_interval: float

    def __post_init__(self) -> None:
        check_node_fields(self)

    def keyframes(self) -> KeyframeConfig:
        return KeyframeConfig(min_interval=self.min_interval, min_distance=self.min_distance)


@dataclass(frozen=True)
class ScanFilterConfig(FilterConfig):
    """Which clouds are added to the scan map."""

    min_distance: float = param(0.0, "m travelled between clouds added to the map; 0 = every cloud", lo=0.0,
                                hi=1e6, dynamic=True)
    min_interval: float = param(0.0, "s (header stamps) between clouds added to the map; 0 = off", lo=0.0,
                                hi=3600.0, dynamic=True)


@dataclass(frozen=True)
class CameraFilterConfig(FilterConfig):
    """Which camera frames are used."""

    min_distance: float = param(0.0, "m travelled between camera frames used; 0 = every frame", lo=0.0, hi=1e6,
                                dynamic=True)
    min_interval: float = param(0.0, "s (header stamps) between camera frames used; 0 = off", lo=0.0, hi=3600.0,
                                dynamic=True)


@dataclass(frozen=True)
class ExtrinsicsConfig:
    format: str = param("xyz_rpy", "which camera-to-LiDAR transform is used: xyz_rpy or matrix",
                        choices=EXTRINSICS_FORMATS, dynamic=True)
    xyz: tuple[float, ...] = param((0.27, 0.06, -0.08), "camera optical-frame origin in the LiDAR frame, m "
                                                        "(default: KITTI-like rig)", dynamic=True)
    rpy: tuple[float, ...] = param((-HALF_PI, 0.0, -HALF_PI), "roll, pitch, yaw of the optical frame in the LiDAR "
                                                              "frame, rad (R = Rz Ry Rx)", dynamic=True)
    matrix: tuple[float, ...] = param(KITTI_LIDAR_T_CAM, "lidar_T_cam 4 x 4 row-major (16 values), used when "
                                                         "extrinsics.format = matrix", dynamic=True)

    def __post_init__(self) -> None:
        check_node_fields(self)
        require(len(self.xyz) == 3 and all(math.isfinite(v) for v in self.xyz),
               f"xyz={list(self.xyz)}; give 3 finite metres")
        require(len(self.rpy) == 3 and all(math.isfinite(v) for v in self.rpy),
               f"rpy={list(self.rpy)}; give 3 finite radians (roll, pitch, yaw)")
        require(len(self.matrix) == 16 and all(math.isfinite(v) for v in self.matrix),
               f"matrix has {len(self.matrix)} values; give 16 finite values (4 x 4, row-major)")
        T = np.asarray(self.matrix, np.float64).reshape(4, 4)
        R = T[:3, :3]
        require(np.allclose(T[3], (0, 0, 0, 1)) and np.allclose(R @ R.T, np.eye(3), atol=1e-4)
               and np.linalg.det(R) > 0,
               "matrix is not a rigid transform (rotation block orthonormal with det +1, last row 0 0 0 1)")

    def lidar_T_cam(self) -> np.ndarray:
        if self.format == "matrix":
            return np.asarray(self.matrix, np.float64).reshape(4, 4)
        return xyz_rpy_matrix(self.xyz, self.rpy)


def xyz_rpy_matrix(xyz: tuple[float, ...], rpy: tuple[float, ...]) -> np.ndarray:
    """4 x 4 from a translation and roll, pitch, yaw (rad; R = Rz Ry Rx, as URDF / tf2)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) \
        @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T[:3, 3] = xyz
    return T


@dataclass(frozen=True)
class SyncConfig:
    slop: float = param(0.02, "s: depth and label images this close pair up; odometry nearest within this",
                        lo=0.0, hi=10.0, dynamic=True)
    odom_max_gap: float = param(1.0, "s: odometry neighbours at most this far apart are interpolated", lo=0.0,
                                hi=60.0, dynamic=True)
    max_wait: float = param(0.5, "s of wall time a cloud or camera frame waits for its pose and camera_info",
                            lo=0.0, hi=60.0, dynamic=True)
    image_buffer: int = param(16, "unpaired depth / label images kept per stream", lo=1, hi=1000)
    max_pending: int = param(32, "clouds and camera frames waiting for a pose at most (oldest dropped)", lo=1,
                             hi=10000)
    jump_back: float = param(5.0, "s: a header stamp this much older than its stream's newest (a bag played again, "
                                  "--loop, a simulator reset) starts a new session in the same map; 0 = refuse it "
                                  "as out of order", lo=0.0, hi=86400.0)

    def __post_init__(self) -> None:
        check_node_fields(self)


@dataclass(frozen=True)
class WorkerConfig:
    max_waiting: int = param(8, "clouds / camera frames queued for the worker (oldest dropped when full)", lo=1,
                             hi=100000)

    def __post_init__(self) -> None:
        check_node_fields(self)


@dataclass(frozen=True)
class NodeConfig:
    lidar_topic: str = param(KITTI_TOPICS.lidar, "sensor_msgs/PointCloud2 with x, y, z and a label field "
                                                 "(SemanticKITTI ids) for the map")
    depth_topic: str = param(KITTI_TOPICS.depth[0], "sensor_msgs/Image metric depth: 32FC1 metres or 16UC1 "
                                                    "millimetres (0 = unknown)")
    labels_topic: str = param(KITTI_TOPICS.labels[0], "sensor_msgs/Image SemanticKITTI label ids (mono8/8UC1/"
                                                      "mono16/16UC1, 32SC1 = uint32 bits), pixel-aligned with the "
                                                      "depth image")
    camera_info_topic: str = param(KITTI_TOPICS.camera_info[0], "sensor_msgs/CameraInfo of the depth/label camera "
                                                                "(pinhole K, no distortion)")
    image_topic: str = param(KITTI_TOPICS.cameras[0], "the colour image; only counted in /diagnostics (the network "
                                                      "reads depth + labels); empty = not subscribed")
    odom_topic: str = param(KITTI_TOPICS.odom, "nav_msgs/Odometry: poses at cloud and camera stamps (sequence "
                                               "distances, map poses)")
    input_qos: str = input_qos_param()
    model: Vseq2pcModelConfig = field(default_factory=Vseq2pcModelConfig)
    match: Vseq2pcMatchConfig = field(default_factory=Vseq2pcMatchConfig)
    verify: Vseq2pcVerifyParams = field(default_factory=Vseq2pcVerifyParams)
    sequence: SequenceParams = field(default_factory=SequenceParams)
    scan: ScanFilterConfig = field(default_factory=ScanFilterConfig)
    camera: CameraFilterConfig = field(default_factory=CameraFilterConfig)
    extrinsics: ExtrinsicsConfig = field(default_factory=ExtrinsicsConfig)
    sync: SyncConfig = field(default_factory=SyncConfig)
    map: MapFileConfig = field(default_factory=MapFileConfig)
    worker: WorkerConfig = field(default_factory=WorkerConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)

    def __post_init__(self) -> None:
        check_node_fields(self)
        for name in ("lidar_topic", "depth_topic", "labels_topic", "camera_info_topic", "odom_topic"):
            require(bool(getattr(self, name)), f"{name} is empty; it is required")
        topics = [t for t in (self.lidar_topic, self.depth_topic, self.labels_topic, self.camera_info_topic,
                              self.image_topic, self.odom_topic) if t]
        require(len(set(topics)) == len(topics), f"topics {topics} repeat a name; give one topic per stream")

    def detector(self) -> SequenceDetectorConfig:
        """The core detector's settings (lcpr_core.vseq2pc.detector) from the node's parameters."""
        return SequenceDetectorConfig(
            scan=self.scan.keyframes(), camera=self.camera.keyframes(), sequence=self.sequence.builder(),
            search=self.match.search(), min_probability=self.match.min_probability,
            lidar_T_cam=tuple(self.extrinsics.lidar_T_cam().ravel().tolist()), verify=self.verify.core())
