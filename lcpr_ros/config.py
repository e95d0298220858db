"""The node's own settings (topics, synchronisation, map file, diagnostics) as typed config.

The detector's settings are :class:`lcpr_core.lcpr.detector.DetectorConfig`; both are
exposed as ROS parameters by :mod:`lcpr_ros.params`, which walks these dataclasses.
Every ``__post_init__`` refuses a bad value with a ValueError naming it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from lcpr_core.lcpr.detector import DetectorConfig
from msg_tools.frames import NUSCENES_TOPICS
from ros_common.config import INPUT_QOS, DiagnosticsConfig, MapFileConfig, require, require_finite_non_negative

CAMERA_TYPES = ("auto", "compressed", "raw")


@dataclass(frozen=True)
class SyncConfig:
    slop: float = 0.05  # s: each camera's image nearest the cloud stamp within this is used
    camera_timeout: float = 1.0  # s of header time: a camera silent this long counts as stopped (None)
    max_wait: float = 0.2  # s of wall time a cloud waits for images stamped after it
    min_cameras: int = 1  # frames with fewer images are dropped ("no camera")
    odom_max_gap: float = 1.0  # s: odometry neighbours at most this far apart are interpolated
    image_buffer: int = 16  # images kept per camera for matching
    max_pending: int = 8  # clouds waiting for images at most; older ones are dropped
    jump_back: float = 5.0  # s: a stamp this much older than its stream's newest starts a new session; 0 = refuse

    def __post_init__(self) -> None:
        require_finite_non_negative(self, "slop", "camera_timeout", "max_wait", "odom_max_gap", "jump_back")
        require(self.min_cameras >= 0, f"sync.min_cameras={self.min_cameras}; it must be >= 0")
        require(self.image_buffer >= 1, f"sync.image_buffer={self.image_buffer}; it must be >= 1")
        require(self.max_pending >= 1, f"sync.max_pending={self.max_pending}; it must be >= 1")


@dataclass(frozen=True)
class NodeConfig:
    camera_topics: tuple[str, ...] = NUSCENES_TOPICS.cameras  # nuScenes camera order
    camera_type: str = "auto"  # auto (".../compressed" -> CompressedImage) | compressed | raw
    lidar_topic: str = NUSCENES_TOPICS.lidar
    odom_topic: str = ""  # nav_msgs/Odometry; "" = no poses (no markers, no distance keyframing)
    input_qos: str = "best_available"  # best_available | sensor_data (best effort) | reliable (ros_common.qos)
    sync: SyncConfig = field(default_factory=SyncConfig)
    map: MapFileConfig = field(default_factory=MapFileConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)
    lidar_only: bool = False  # no camera subscriptions: every frame described with all camera slots empty
    tf_static_topic: str = "/tf_static"  # the submap mount (odometry child frame -> cloud frame) from here; "" = off

    def __post_init__(self) -> None:
        require(self.camera_type in CAMERA_TYPES,
               f"camera_type={self.camera_type!r}; accepted: {', '.join(CAMERA_TYPES)}")
        require(self.input_qos in INPUT_QOS, f"input_qos={self.input_qos!r}; accepted: {', '.join(INPUT_QOS)}")
        require(len(self.camera_topics) >= 1 and all(self.camera_topics),
               f"camera_topics={list(self.camera_topics)}; give one non-empty topic per camera")
        require(len(set(self.camera_topics)) == len(self.camera_topics),
               f"camera_topics={list(self.camera_topics)} repeat a topic; give one topic per camera")
        require(bool(self.lidar_topic), "lidar_topic is empty; a PointCloud2 topic is required")

    def subscribed_cameras(self) -> tuple[str, ...]:
        """The camera topics the node subscribes to (none when ``lidar_only``)."""
        return () if self.lidar_only else self.camera_topics

    def frame_sync(self) -> SyncConfig:
        """The synchroniser's settings: a LiDAR-only node releases every cloud without waiting for images."""
        return dataclasses.replace(self.sync, min_cameras=0) if self.lidar_only else self.sync

    def compressed(self, index: int) -> bool:
        """Whether camera ``index`` is subscribed as sensor_msgs/CompressedImage."""
        if self.camera_type == "auto":
            return self.camera_topics[index].rstrip("/").endswith("/compressed")
        return self.camera_type == "compressed"


def check_together(node: NodeConfig, detector: DetectorConfig) -> None:
    """Refuse settings that are valid alone but not together."""
    cameras = len(node.camera_topics)
    require(cameras == detector.model.num_cameras,
           f"camera_topics names {cameras} topics but model.num_cameras={detector.model.num_cameras}; "
           "give one topic per camera of the model")
    require(node.sync.min_cameras <= cameras,
           f"sync.min_cameras={node.sync.min_cameras} is more than the {cameras} cameras in camera_topics")
