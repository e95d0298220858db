"""The node's settings as typed config; every leaf becomes a dotted ROS parameter.

``__post_init__`` refuses a bad value with a ValueError naming it (turned into a
ConfigError by :mod:`vseq2pc_ros.params`). The default extrinsics are KITTI's published
sensor setup (camera 0 0.27 m ahead of the Velodyne, 0.06 m left, 0.08 m lower, level,
looking along +x; the simulator's KITTI-like rig copies the same numbers); any other vehicle
must set ``extrinsics.*`` to its own calibration, and the node warns at start while they are
left at this default.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lcpr_core.keyframes import KeyframeConfig
from lcpr_core.pretrained import BUNDLED, VSEQ2PC_WEIGHTS_NAMES
from lcpr_core.vseq2pc.consistency import ConsistencyConfig
from lcpr_core.vseq2pc.detector import SequenceDetectorConfig
from lcpr_core.vseq2pc.retrieval import SearchConfig
from lcpr_core.vseq2pc.sequence import OFFSETS, SequenceConfig
from lcpr_core.vseq2pc.verify import SequenceVerifyConfig
from msg_tools.frames import KITTI_TOPICS
from ros_common.config import INPUT_QOS, DiagnosticsConfig, MapFileConfig, require, require_finite_non_negative

EXTRINSICS_FORMATS = ("xyz_rpy", "matrix")
DEFAULT_VERIFY = SequenceVerifyConfig()
HALF_PI = math.pi / 2

#: lidar_T_cam of KITTI's sensor setup, camera 0 in the Velodyne frame (optical frame: z forward, x right, y down).
KITTI_LIDAR_T_CAM: tuple[float, ...] = (
    0.0, 0.0, 1.0, 0.27,
    -1.0, 0.0, 0.0, 0.06,
    0.0, -1.0, 0.0, -0.08,
    0.0, 0.0, 0.0, 1.0,
)


@dataclass(frozen=True)
class Vseq2pcModelConfig:
    sequence: str = BUNDLED  # sequence-model weights (a file), or bundled / bundled-exact / seeded
    descriptor: str = BUNDLED  # descriptor-model weights (a file), or the same name as sequence
    seed: int = 0  # seed of the random weights (seeded; testing only)
    device: str = "cpu"
    threads: int = 0  # torch intra-op threads; 0 = torch's default

    def __post_init__(self) -> None:
        named = [w in VSEQ2PC_WEIGHTS_NAMES for w in (self.sequence, self.descriptor)]
        require(named[0] == named[1] and (not named[0] or self.sequence == self.descriptor),
                f"model.sequence={self.sequence!r}, model.descriptor={self.descriptor!r}: give two weight files, "
                f"or the same name in both ({', '.join(VSEQ2PC_WEIGHTS_NAMES)})")
        require(self.seed >= 0, f"seed={self.seed}; it must be >= 0")
        require(self.threads >= 0, f"threads={self.threads}; it must be >= 0")
        require(bool(self.device), "device is empty; e.g. cpu or cuda:0")


@dataclass(frozen=True)
class Vseq2pcMatchConfig:
    top_k: int = 10  # candidates per query
    exclude_recent_s: float = 30.0  # scans stamped later than query stamp - this are not matched
    min_probability: float = 0.0  # candidates under this probability are not published
    prefilter: int = 0  # 0 = exact head on every scan; M = FAISS top-M scans first (approximate)

    def __post_init__(self) -> None:
        require(self.top_k >= 1, f"top_k={self.top_k}; it must be >= 1")
        require_finite_non_negative(self, "exclude_recent_s")
        require(0.0 <= self.min_probability <= 1.0, f"min_probability={self.min_probability}; it must lie in [0, 1]")
        require(self.prefilter >= 0, f"prefilter={self.prefilter}; it must be >= 0 (0 = exact)")

    def search(self) -> SearchConfig:
        return SearchConfig(k=self.top_k, exclude_recent_s=self.exclude_recent_s,
                            prefilter=self.prefilter or None)


@dataclass(frozen=True)
class Vseq2pcVerifyParams:
    enabled: bool = True  # register each query's pseudo-cloud against its candidates; loops must be verified
    top_k: int = 10  # the best this-many candidates of a query are registered
    min_fitness: float = DEFAULT_VERIFY.min_fitness  # share of the pseudo-cloud on the scan's surfaces
    min_support: int = DEFAULT_VERIFY.min_support  # accepted candidates agreeing on the camera's map pose
    max_depth: float = DEFAULT_VERIFY.pseudo.max_depth  # m: depth farther along the optical axis is left out
    max_frames: int = DEFAULT_VERIFY.pseudo.max_frames  # camera frames stacked into one pseudo-cloud at most
    consistency: int = DEFAULT_VERIFY.consistency.count  # queries whose verified camera poses must agree (1 = off)
    consistency_m: float = DEFAULT_VERIFY.consistency.max_m  # m: an earlier pose moved on by odometry vs this one
    consistency_deg: float = DEFAULT_VERIFY.consistency.max_deg  # deg: the same for the rotation
    consistency_spacing: float = DEFAULT_VERIFY.consistency.spacing_m  # m of odometry travel between those queries
    consistency_backfill: bool = DEFAULT_VERIFY.consistency.backfill  # a confirmed loop confirms its chain's too

    def __post_init__(self) -> None:
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
    offsets: tuple[float, ...] = OFFSETS  # m after the query frame
    min_query_spacing: float = 0.0  # m between query frames; 0 = every camera frame
    max_pending: int = 4096  # queries waiting for their last member

    def __post_init__(self) -> None:
        try:
            self.builder()
        except ValueError as err:
            raise ValueError(str(err).replace("min_query_spacing_m", "min_query_spacing")) from None

    def builder(self) -> SequenceConfig:
        return SequenceConfig(offsets=tuple(self.offsets), min_query_spacing_m=self.min_query_spacing,
                              max_pending=self.max_pending)


@dataclass(frozen=True)
class FilterConfig:
    min_distance: float = 0.0  # m travelled since the last one used; 0 = off
    min_interval: float = 0.0  # s (header stamps) since the last one used; 0 = off

    def __post_init__(self) -> None:
        require_finite_non_negative(self, "min_distance", "min_interval")

    def keyframes(self) -> KeyframeConfig:
        return KeyframeConfig(min_interval=self.min_interval, min_distance=self.min_distance)


@dataclass(frozen=True)
class ExtrinsicsConfig:
    format: str = "xyz_rpy"  # which of the two below is used: xyz_rpy | matrix
    xyz: tuple[float, ...] = (0.27, 0.06, -0.08)  # camera origin in the LiDAR frame, m
    rpy: tuple[float, ...] = (-HALF_PI, 0.0, -HALF_PI)  # rad; R = Rz(yaw) Ry(pitch) Rx(roll)
    matrix: tuple[float, ...] = KITTI_LIDAR_T_CAM  # 4 x 4 lidar_T_cam, row-major

    def __post_init__(self) -> None:
        require(self.format in EXTRINSICS_FORMATS,
               f"format={self.format!r}; accepted: {', '.join(EXTRINSICS_FORMATS)}")
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
    slop: float = 0.02  # s: depth and label images this close pair up; odometry nearest within this
    odom_max_gap: float = 1.0  # s: odometry neighbours at most this far apart are interpolated
    max_wait: float = 0.5  # s of wall time a cloud / camera frame waits for its pose (and camera_info)
    image_buffer: int = 16  # unpaired depth / label images kept per stream
    max_pending: int = 32  # clouds and camera frames waiting for poses at most (oldest dropped)
    jump_back: float = 5.0  # s: a stamp this much older than its stream's newest starts a new session; 0 = refuse

    def __post_init__(self) -> None:
        require_finite_non_negative(self, "slop", "odom_max_gap", "max_wait", "jump_back")
        require(self.image_buffer >= 1, f"image_buffer={self.image_buffer}; it must be >= 1")
        require(self.max_pending >= 1, f"max_pending={self.max_pending}; it must be >= 1")


@dataclass(frozen=True)
class WorkerConfig:
    max_waiting: int = 8  # scans / camera frames queued for the worker (oldest dropped when full)

    def __post_init__(self) -> None:
        require(self.max_waiting >= 1, f"max_waiting={self.max_waiting}; it must be >= 1")


@dataclass(frozen=True)
class NodeConfig:
    lidar_topic: str = KITTI_TOPICS.lidar
    depth_topic: str = KITTI_TOPICS.depth[0]
    labels_topic: str = KITTI_TOPICS.labels[0]
    camera_info_topic: str = KITTI_TOPICS.camera_info[0]
    image_topic: str = KITTI_TOPICS.cameras[0]  # counted in diagnostics only; "" = not subscribed
    odom_topic: str = KITTI_TOPICS.odom
    input_qos: str = "best_available"  # ros_common.qos
    model: Vseq2pcModelConfig = field(default_factory=Vseq2pcModelConfig)
    match: Vseq2pcMatchConfig = field(default_factory=Vseq2pcMatchConfig)
    verify: Vseq2pcVerifyParams = field(default_factory=Vseq2pcVerifyParams)
    sequence: SequenceParams = field(default_factory=SequenceParams)
    scan: FilterConfig = field(default_factory=FilterConfig)
    camera: FilterConfig = field(default_factory=FilterConfig)
    extrinsics: ExtrinsicsConfig = field(default_factory=ExtrinsicsConfig)
    sync: SyncConfig = field(default_factory=SyncConfig)
    map: MapFileConfig = field(default_factory=MapFileConfig)
    worker: WorkerConfig = field(default_factory=WorkerConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)

    def __post_init__(self) -> None:
        require(self.input_qos in INPUT_QOS, f"input_qos={self.input_qos!r}; accepted: {', '.join(INPUT_QOS)}")
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
