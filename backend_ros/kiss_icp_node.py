"""``lcpr_kiss_icp``: LiDAR odometry for the back end when the vehicle has none (KISS-ICP, the ``odometry`` extra).

Subscribes one sensor_msgs/PointCloud2 (``lidar_topic``, read with :func:`msg_tools.pointcloud2_to_array`;
points with NaN/inf or at the origin dropped), registers each cloud with
:class:`lcpr_core.backend.lidar_odometry.KissOdometry` on a worker thread and publishes ``~/odometry``
(nav_msgs/Odometry, ``odom_frame`` -> ``base_frame``, stamped with the cloud's header stamp; the
base pose from the LiDAR's through ``lidar.xyz`` / ``lidar.rpy``) and /diagnostics. While the worker
registers one cloud, the newest waits and older ones are dropped (counted): odometry over a gap is
better than odometry that falls behind.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from lcpr_common.params import param
from lcpr_core.backend.lidar_odometry import KissConfig, KissOdometry
from lcpr_core.errors import RuntimeSetupError
from msg_tools.transforms import pose_to_odometry
from ros_common.config import DiagnosticsConfig, check_node_fields, input_qos_param, require
from ros_common.diagnostics import HARDWARE_ID
from ros_common.errors import ConfigError, InputRejected
from ros_common.inputs import CLOUD_NAN, cloud_points
from ros_common.params import Leaf, build, describe, leaves, to_yaml, unique
from ros_common.process import node_parser, run_node
from ros_common.qos import QOS_ADAPTED, SensorSubscription
from ros_common.ros_params import declare
from ros_common.stamps import NS_PER_S, StampOrder, stamp_ns
from ros_common.stats import NodeStats
from ros_common.worker import Worker

from .config import LidarMount

NODE_NAME = "lcpr_kiss_icp"
BUSY = "cloud: replaced while busy"
FAILED = "cloud: registration failed"
SHUTDOWN_TIMEOUT = 10.0


@dataclass(frozen=True, kw_only=True)
class KissNodeConfig:
    lidar_topic: str = param("/LIDAR_TOP/points", "sensor_msgs/PointCloud2 with x, y, z (any other fields are "
                                                  "ignored)")
    input_qos: str = input_qos_param()
    odom_frame: str = param("odom", "header.frame_id of ~/odometry (the odometry's world frame)")
    base_frame: str = param("base_link", "child_frame_id of ~/odometry")
    lidar: LidarMount = field(default_factory=LidarMount)
    kiss: KissConfig = field(default_factory=KissConfig)
    diagnostics: DiagnosticsConfig = field(default_factory=DiagnosticsConfig)

    def __post_init__(self) -> None:
        check_node_fields(self)
        require(bool(self.lidar_topic), "lidar_topic is empty; a PointCloud2 topic is required")
        require(bool(self.odom_frame) and bool(self.base_frame), "odom_frame and base_frame must not be empty")


def all_leaves() -> list[Leaf]:
    return unique(leaves(KissNodeConfig()))


YAML_HEADER = """lcpr_kiss_icp parameters (node name lcpr_kiss_icp) with their defaults, from
backend_ros.kiss_icp_node.KissNodeConfig (kiss.*: lcpr_core.backend.lidar_odometry.KissConfig).
Use: lcpr_kiss_icp --ros-args --params-file config/lcpr_kiss_icp.yaml
Regenerate after adding fields:
  python -c "from backend_ros.kiss_icp_node import yaml_text; print(yaml_text(), end='')" > config/lcpr_kiss_icp.yaml
"""


def yaml_text() -> str:
    return to_yaml(all_leaves(), header=YAML_HEADER)


def settings_from(values: Mapping[str, Any]) -> KissNodeConfig:
    config: KissNodeConfig = build(KissNodeConfig, values)
    return config


class KissIcpNode(NodeStats, Node):
    """The ``lcpr_kiss_icp`` node. Raises ConfigError when it cannot start."""

    def __init__(self, *, parameter_overrides: list[Parameter] | None = None, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, parameter_overrides=parameter_overrides, **kwargs)
        self.settings = cfg = settings_from(declare(self, all_leaves()))
        self.init_stats(self.get_logger().warning, window=cfg.diagnostics.window)
        try:
            self.odometry = KissOdometry(cfg.kiss, base_T_lidar=cfg.lidar.matrix())
        except RuntimeSetupError as err:
            raise ConfigError(str(err)) from err
        self._order = StampOrder()
        self._closed = False
        self._pub = self.create_publisher(Odometry, "~/odometry", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._sub = SensorSubscription(self, PointCloud2, cfg.lidar_topic, self._on_cloud, cfg.input_qos,
                                       warn=lambda text: self.warnings(QOS_ADAPTED, text))
        self.create_timer(cfg.diagnostics.period, self._publish_diagnostics)
        self.worker: Worker[tuple[Any, np.ndarray, float]] = Worker(
            self._register, on_dropped=self._on_dropped, on_error=self._on_failed, name="kiss-icp")
        self.worker.start()
        self.get_logger().info(f"ready: clouds from {cfg.lidar_topic}, odometry on ~/odometry "
                               f"({cfg.odom_frame} -> {cfg.base_frame})")

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.rates.tick(self.settings.lidar_topic)
        ns = stamp_ns(msg.header)
        try:
            points, removed = cloud_points(msg)
        except InputRejected as err:
            self.drops.add(err.reason)
            self.warnings(err.reason, err.detail)
            return
        refused = self._order.check(ns)
        if refused is not None:
            self.drops.add(f"cloud: {refused}")
            self.warnings(f"cloud: {refused}", f"stamp {ns / NS_PER_S:.9f}")
            return
        if removed:
            self.fixes.add(CLOUD_NAN, removed)
        self.worker.submit((msg.header.stamp, points, time.monotonic()))

    def _register(self, item: tuple[Any, np.ndarray, float]) -> None:
        stamp, points, arrival = item
        tic = time.perf_counter()
        pose = self.odometry.register(points, stamp.sec + stamp.nanosec / NS_PER_S)
        self.model_time.add(time.perf_counter() - tic)
        self._pub.publish(pose_to_odometry(pose, stamp=stamp, frame_id=self.settings.odom_frame,
                                           child_frame_id=self.settings.base_frame, msg_type=Odometry))
        self.latency.add(time.monotonic() - arrival)

    def _on_dropped(self, item: tuple[Any, np.ndarray, float]) -> None:
        self.drops.add(BUSY)
        self.warnings(BUSY, "clouds arrive faster than KISS-ICP registers them; the newest waits, older ones "
                            "are dropped")

    def _on_failed(self, item: tuple[Any, np.ndarray, float], err: Exception) -> None:
        self.drops.add(FAILED)
        self.warnings(f"{FAILED} ({type(err).__name__})", f"{err}; the node goes on with the next cloud")

    def _publish_diagnostics(self) -> None:
        times = self.model_time.percentiles(50, 95)
        values = {
            "clouds registered": self.odometry.frames,
            **{f"dropped {reason}": n for reason, n in sorted(self.drops.snapshot().items())},
            **{reason: n for reason, n in sorted(self.fixes.snapshot().items())},
            "registration p50 (ms)": "n/a" if times is None else f"{times[0] * 1e3:.1f}",
            "registration p95 (ms)": "n/a" if times is None else f"{times[1] * 1e3:.1f}",
            **{f"rate {s} (Hz)": f"{r:.2f}" for s, r in sorted(self.rates.rates().items())},
            "warnings": "; ".join(self.warnings.causes),
        }
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [DiagnosticStatus(level=DiagnosticStatus.OK, name=f"{self.get_name()}: odometry",
                                       hardware_id=HARDWARE_ID, message=f"{self.odometry.frames} clouds",
                                       values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        self._diagnostics_pub.publish(msg)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if not self.worker.stop(drain=True, timeout=SHUTDOWN_TIMEOUT):
            self.get_logger().error(f"KISS-ICP is still busy after {SHUTDOWN_TIMEOUT} s")


def _parser() -> argparse.ArgumentParser:
    return node_parser(prog="lcpr_kiss_icp", node_name=NODE_NAME, summary="KISS-ICP LiDAR odometry",
                       params_file="config/lcpr_kiss_icp.yaml", parameters=describe(all_leaves()))


def main(args: Sequence[str] | None = None) -> int:
    """``lcpr_kiss_icp``: 0 after a clean stop (Ctrl-C, SIGTERM), 1 when the node refuses to start."""
    return run_node(KissIcpNode, parser=_parser(), argv=args, closing="registering the queued cloud")


if __name__ == "__main__":
    sys.exit(main())

