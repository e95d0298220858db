"""The node's own settings (topics, synchronisation, map file, diagnostics) as typed config.

The detector's settings are :class:`lcpr_core.detector.DetectorConfig`; both are
exposed as ROS parameters by :mod:`lcpr_ros.params`, which walks these dataclasses. Each field
carries its description, range or choices and run-time flag (:func:`lcpr_common.params.param`);
every ``__post_init__`` refuses a bad value with a ValueError naming it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from lcpr_common.params import param
from lcpr_core.detector import DetectorConfig
from msg_tools.frames import NUSCENES_TOPICS
from ros_common.config import DiagnosticsConfig, MapFileConfig, check_node_fields, input_qos_param, require

CAMERA_TYPES = ("auto", "compressed", "raw")


@dataclass(frozen=True)
class SyncConfig:
    slop: float = param(0.05, "s: each camera's image nearest the cloud stamp within this is used", lo=0.0, hi=10.0,
                        dynamic=True)
    camera_timeout: float = param(1.0, "s of header time: a camera silent this long is stopped (frames degraded)",
                                  lo=0.0, hi=3600.0, dynamic=True)
    max_wait: float = param(0.2, "s of wall time a cloud waits for camera images stamped after it", lo=0.0, hi=10.0,
                            dynamic=True)
    min_cameras: int = param(1, "frames with fewer camera images are dropped", lo=0, hi=64, dynamic=True)
    odom_max_gap: float = param(1.0, "s: odometry neighbours at most this far apart are interpolated", lo=0.0,
                                hi=60.0, dynamic=True)
    image_buffer: int = param(16, "images kept per camera for matching", lo=1, hi=1000)
    max_pending: int = param(8, "clouds waiting for images at most; older ones are dropped", lo=1, hi=1000)
    jump_back: float = param(5.0, "s: a header stamp this much older than its stream's newest (a bag played again, "
                                  "--loop, a simulator reset) starts a new session in the same map; 0 = refuse it "
                                  "as out of order", lo=0.0, hi=86400.0)

    def __post_init__(self) -> None:
        check_node_fields(self, "sync.")


@dataclass(frozen=True)
class NodeConfig:
    camera_topics: tuple[str, ...] = param(NUSCENES_TOPICS.cameras, "camera image topics in rig (nuScenes) order")
    camera_type: str = param("auto", "message type of the camera topics; auto: topics ending in /compressed are "
                                     "sensor_msgs/CompressedImage, others sensor_msgs/Image", choices=CAMERA_TYPES)
    lidar_topic: str = param(NUSCENES_TOPICS.lidar, "sensor_msgs/PointCloud2 topic")
    odom_topic: str = param("", "nav_msgs/Odometry topic for poses (markers, keyframe.min_distance); empty = none")
    input_qos: str = input_qos_param()
    sync: SyncConfig = field(default_factory=SyncConfig)
    map: MapFileConfig = field(default_factory=MapFileConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)
    lidar_only: bool = param(False, "no camera subscriptions: every frame is described with all camera slots "
                                    "empty, verified and published as usual (a vehicle with a LiDAR and no "
                                    "surround cameras)")
    peers: tuple[str, ...] = param((), "namespaces of the robots whose keyframes this node matches against: each "
                                        "one's <namespace>/lcpr/keyframes is subscribed (e.g. ['/robot2'] -> "
                                        "/robot2/lcpr/keyframes); give every robot its own session name (session)")
    keyframes_history: int = param(256, "~/keyframes messages kept (reliable, transient local) for peers that start "
                                        "late: a keyframe every 0.5 s at most (keyframe.min_interval), so 256 cover "
                                        "2 minutes", lo=1, hi=100_000)
    tf_static_topic: str = param("/tf_static", "tf2_msgs/TFMessage topic the submap mount (submap.lidar_xyz / "
                                               "lidar_rpy) is read from: the transform from the odometry's child "
                                               "frame to the clouds' frame, once heard, replaces those parameters; "
                                               "needs tf2_msgs (a sourced ROS 2); empty = off")

    def __post_init__(self) -> None:
        check_node_fields(self)
        require(len(self.camera_topics) >= 1 and all(self.camera_topics),
               f"camera_topics={list(self.camera_topics)}; give one non-empty topic per camera")
        require(len(set(self.camera_topics)) == len(self.camera_topics),
               f"camera_topics={list(self.camera_topics)} repeat a topic; give one topic per camera")
        require(bool(self.lidar_topic), "lidar_topic is empty; a PointCloud2 topic is required")
        require(all(p.startswith("/") and p.strip("/") and " " not in p for p in self.peers),
                f"peers={list(self.peers)}; give each robot's namespace from the root, e.g. ['/robot2']")
        require(len({p.rstrip("/") for p in self.peers}) == len(self.peers),
                f"peers={list(self.peers)} repeat a namespace; give each robot once")

    def peer_topics(self) -> tuple[str, ...]:
        """The ``~/keyframes`` topic of each peer (``peers``), in order."""
        return tuple(f"{p.rstrip('/')}/lcpr/keyframes" for p in self.peers)

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
