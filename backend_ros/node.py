"""``lcpr_backend``: any odometry + the detector's verified loops in, a corrected trajectory out.

Subscribes nav_msgs/Odometry (``odom_topic``), the detector's ``~/candidates``
(``candidates_topic``; rows with verified = 1, read by the column names of
:mod:`ros_common.tables`) and its ``~/up`` (``up_topic``: each keyframe's up from its walls) and
feeds :class:`lcpr_core.backend.PoseGraphBackend` (GTSAM iSAM2).
Publishes ``~/odometry`` (every odometry message, corrected: ``map_T_odom @ odom_T_base``),
``~/path`` (the graph's keyframe poses), map -> odom on /tf (geometry_msgs/TransformStamped on
``~/map_to_odom`` where tf2_msgs is not installed) and /diagnostics; service ``~/save_graph``.

Threads: the callbacks only check messages, publish the corrected odometry with the newest
correction and queue the work; one worker thread applies odometry and loops to the graph in
arrival order (an optimisation never holds the callbacks up). A loop that arrives before the
odometry of its stamps (or an up before its odometry) waits (``pending_s`` of header time)
and is retried as odometry comes in.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TransformStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from lcpr_core.backend import BackendStats, PoseGraphBackend
from lcpr_core.errors import BackendError, MapError
from msg_tools.build import build_message
from msg_tools.geometry import pose_to_parts
from msg_tools.transforms import transforms_message
from ros_common.diagnostics import HARDWARE_ID
from ros_common.errors import ConfigError, InputRejected
from ros_common.inputs import odometry_pose
from ros_common.mapstore import answer_save_request, load_map_file, save_under_lock
from ros_common.process import finish_and_save, node_parser, run_node
from ros_common.qos import CANDIDATE_QOS, QOS_ADAPTED, SensorSubscription
from ros_common.ros_params import declare
from ros_common.stamps import NS_PER_S, StampOrder, stamp_ns
from ros_common.static_tf import tf_message_type
from ros_common.stats import NodeStats
from ros_common.tables import parse_candidates, row_covariance, row_pose
from ros_common.worker import Worker

from .config import BackendNodeConfig, all_leaves, describe_all, settings_from

TFMessage = tf_message_type()

NODE_NAME = "lcpr_backend"
MAX_WAITING = 10_000  # items queued for the worker at most (~15 min of 10 Hz odometry); older ones are dropped
SHUTDOWN_TIMEOUT = 30.0  # s the worker may take to finish its queue at shutdown
BUSY = "worker: queue full, oldest item dropped"
FAILED = "worker: item failed"
CANDIDATES_BAD = "candidates: bad table"
CANDIDATES_NO_POSE = "candidates: verified row without a pose"
LOOP_EXPIRED = "loop: its odometry never came"
UP_EXPIRED = "up: its odometry never came"


@dataclass(frozen=True)
class _Odom:
    stamp: float
    pose: np.ndarray  # odom_T_base


@dataclass(frozen=True)
class _Up:
    stamp: float
    up: np.ndarray  # (3,) in the LiDAR frame
    expired: ClassVar[str] = UP_EXPIRED  # the drop reason when its odometry never comes

    @property
    def newest(self) -> float:
        return self.stamp

    @property
    def what(self) -> str:
        return f"up {self.stamp!r}"


@dataclass(frozen=True)
class _Loop:
    query_stamp: float
    match_stamp: float
    match_T_query: np.ndarray
    covariance: np.ndarray | None
    expired: ClassVar[str] = LOOP_EXPIRED  # the drop reason when its odometry never comes

    @property
    def newest(self) -> float:
        return max(self.query_stamp, self.match_stamp)

    @property
    def what(self) -> str:
        return f"loop {self.query_stamp!r} -> {self.match_stamp!r}"


class BackendNode(NodeStats, Node):
    """The ``lcpr_backend`` node. Raises ConfigError / MapLoadError when it cannot start."""

    def __init__(self, *, parameter_overrides: list[Parameter] | None = None, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, parameter_overrides=parameter_overrides, **kwargs)
        self.settings: BackendNodeConfig = settings_from(declare(self, all_leaves()))
        cfg = self.settings
        log = self.get_logger()
        self.init_stats(log.warning, window=cfg.diagnostics.window)
        self._closed = False
        self._lock = threading.Lock()  # held by the worker per item, and to save
        backend_config = cfg.backend()

        def load(path: Path) -> PoseGraphBackend:
            try:
                return PoseGraphBackend.load(path, backend_config)
            except BackendError as err:
                raise MapError(str(err)) from err

        try:
            self.backend = load_map_file(cfg.graph.path, load) or PoseGraphBackend(backend_config)
        except BackendError as err:  # gtsam missing
            raise ConfigError(str(err)) from err
        self._stats: BackendStats = self.backend.stats()
        self._map_T_odom = self.backend.map_T_odom()
        self._frames = (cfg.odom_frame, cfg.base_frame)  # filled from the first odometry message when empty
        self._order = StampOrder()
        self._pending: list[_Loop | _Up] = []
        self._newest_odom = -np.inf
        self._path_sent = 0.0
        self._path_nodes = -1
        self._path_due = False
        self._reported_refused = 0

        self._odom_pub = self.create_publisher(Odometry, "~/odometry", 10)
        self._path_pub = self.create_publisher(PathMsg, "~/path", CANDIDATE_QOS)
        if TFMessage is not None:
            self._tf_pub = self.create_publisher(TFMessage, "/tf", 100)
        else:
            self._tf_pub = self.create_publisher(TransformStamped, "~/map_to_odom", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._odom_sub = SensorSubscription(self, Odometry, cfg.odom_topic, self._on_odom, cfg.input_qos,
                                            warn=lambda text: self.warnings(QOS_ADAPTED, text))
        self.create_subscription(Float64MultiArray, cfg.candidates_topic, self._on_candidates, CANDIDATE_QOS)
        if cfg.up_topic:
            self.create_subscription(Vector3Stamped, cfg.up_topic, self._on_up, CANDIDATE_QOS)
        self.create_service(Trigger, "~/save_graph", self._on_save_graph)
        self.create_timer(cfg.diagnostics.period, self._publish_diagnostics)

        self.worker: Worker[_Odom | _Loop | _Up] = Worker(self._process, max_waiting=MAX_WAITING, name="backend-worker",
                                                    on_dropped=self._on_dropped, on_error=self._on_failed)
        self.worker.start()
        loaded = f"continuing {cfg.graph.path} ({self._stats.nodes} nodes)" if self._stats.nodes else "a new graph"
        ups = f", ups from {cfg.up_topic}" if cfg.up_topic else ""
        log.info(f"ready: odometry {cfg.odom_topic}, loops from {cfg.candidates_topic}{ups}; {loaded}; "
                 f"map -> odom on {'/tf' if TFMessage is not None else '~/map_to_odom'}")

    # -- inputs (callback thread) -------------------------------------------------------------
    def _reject(self, err: InputRejected) -> None:
        self.drops.add(err.reason)
        self.warnings(err.reason, err.detail)

    def _on_odom(self, msg: Odometry) -> None:
        self.rates.tick(self.settings.odom_topic)
        ns = stamp_ns(msg.header)
        try:
            pose = odometry_pose(msg)
        except InputRejected as err:
            self._reject(err)
            return
        refused = self._order.check(ns)
        if refused is not None:
            self._reject(InputRejected(f"odometry: {refused}", f"stamp {ns / NS_PER_S:.9f}"))
            return
        if not self._frames[0] or not self._frames[1]:
            self._frames = (self._frames[0] or msg.header.frame_id or "odom",
                            self._frames[1] or msg.child_frame_id or "base_link")
        correction = self._map_T_odom  # the worker swaps in a new array; this one stays whole
        out = build_message("nav_msgs/msg/Odometry", {
            "header": {"stamp": {"sec": msg.header.stamp.sec, "nanosec": msg.header.stamp.nanosec},
                       "frame_id": self.settings.map_frame},
            "child_frame_id": self._frames[1]}, msg_type=Odometry)
        _set_pose(out.pose.pose, correction @ pose)
        out.pose.covariance = msg.pose.covariance
        out.twist = msg.twist  # in the child frame: the correction does not change it
        self._odom_pub.publish(out)
        self._publish_tf(msg.header.stamp, correction)
        self.worker.submit(_Odom(ns / NS_PER_S, pose))

    def _on_candidates(self, msg: Float64MultiArray) -> None:
        self.rates.tick(self.settings.candidates_topic)
        try:
            rows = parse_candidates(msg)
        except ValueError as err:
            self._reject(InputRejected(CANDIDATES_BAD, str(err)))
            return
        for row in rows:
            if row.get("verified", 0.0) != 1.0:
                continue
            rel = row_pose(row)
            if rel is None:
                self._reject(InputRejected(CANDIDATES_NO_POSE, f"query {row.get('query_stamp')!r}, match "
                                                               f"{row.get('match_stamp')!r}: tx..qw are not finite"))
                continue
            self.worker.submit(_Loop(float(row["query_stamp"]), float(row["match_stamp"]), rel, row_covariance(row)))

    def _on_up(self, msg: Vector3Stamped) -> None:
        self.rates.tick(self.settings.up_topic)
        v = msg.vector
        self.worker.submit(_Up(stamp_ns(msg.header) / NS_PER_S, np.array([v.x, v.y, v.z], np.float64)))

    # -- worker thread ------------------------------------------------------------------------
    def _process(self, item: _Odom | _Loop | _Up) -> None:
        with self._lock:
            if isinstance(item, _Odom):
                self._add_odometry(item)
            else:
                self._add_stamped(item)
            self._stats = self.backend.stats()
            self._map_T_odom = self.backend.map_T_odom()
        self._maybe_publish_path()

    def _add_odometry(self, item: _Odom) -> None:
        try:
            self.backend.add_odometry(item.stamp, item.pose)
        except BackendError as err:
            self._refused(err)
            return
        self._newest_odom = item.stamp
        waiting, self._pending = self._pending, []
        for stamped in waiting:
            self._add_stamped(stamped)

    def _add_stamped(self, item: _Loop | _Up) -> None:
        """Add a loop or an up, or keep it until the odometry reaches its stamps (``pending_s`` ahead at most)."""
        ahead = item.newest - self._newest_odom
        if ahead > self.settings.loops.stamp_tolerance:
            if ahead <= self.settings.pending_s or self._newest_odom == -np.inf:
                if len(self._pending) < MAX_WAITING:
                    self._pending.append(item)
                    return
            self.drops.add(item.expired)
            self.warnings(item.expired, f"{item.what} is {ahead:.3f} s ahead of the newest odometry "
                                             f"(pending_s = {self.settings.pending_s} s)")
            return
        try:
            if isinstance(item, _Up):
                self.backend.add_up(item.stamp, item.up)
                return
            tic = time.perf_counter()
            accepted = self.backend.add_loop(item.query_stamp, item.match_stamp, item.match_T_query, item.covariance)
        except BackendError as err:
            self._refused(err)
            return
        self.model_time.add(time.perf_counter() - tic)
        if accepted:
            self.loops += 1
            self._path_due = True  # publish the corrected path at once

    def _refused(self, err: BackendError) -> None:
        self.warnings(f"refused: {err.reason}", str(err))

    def _maybe_publish_path(self) -> None:
        """~/path after a loop, else at most every ``path_period`` s while nodes are added."""
        now = time.monotonic()
        due = self._path_due or (now - self._path_sent >= self.settings.path_period
                                 and self._stats.nodes != self._path_nodes)
        if not due:
            return
        with self._lock:
            stamps, poses = self.backend.nodes()
        self._path_due, self._path_sent, self._path_nodes = False, now, len(stamps)
        if not len(stamps):
            return
        msg = PathMsg()
        msg.header.frame_id = self.settings.map_frame
        msg.header.stamp = _stamp_msg(float(stamps[-1]))
        for t, pose in zip(stamps, poses, strict=True):
            item = PoseStamped()
            item.header.frame_id = self.settings.map_frame
            item.header.stamp = _stamp_msg(float(t))
            _set_pose(item.pose, pose)
            msg.poses.append(item)
        self._path_pub.publish(msg)

    def _on_dropped(self, item: _Odom | _Loop | _Up) -> None:
        self.drops.add(BUSY)
        self.warnings(BUSY, f"more than {MAX_WAITING} items waited for the graph; the oldest was dropped")

    def _on_failed(self, item: _Odom | _Loop | _Up, err: Exception) -> None:
        self.drops.add(FAILED)
        self.warnings(f"{FAILED} ({type(err).__name__})", f"{item!r}: {err}; the graph is kept, the node goes on")

    def _publish_tf(self, stamp: Any, correction: np.ndarray) -> None:
        parent, child = self.settings.map_frame, self._frames[0]
        if TFMessage is not None:
            self._tf_pub.publish(transforms_message([(parent, child, correction)], stamp=stamp, msg_type=TFMessage))
            return
        msg = TransformStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp.sec, stamp.nanosec
        msg.header.frame_id, msg.child_frame_id = parent, child
        t, q = pose_to_parts(correction)
        msg.transform.translation.x, msg.transform.translation.y, msg.transform.translation.z = (float(v) for v in t)
        r = msg.transform.rotation
        r.x, r.y, r.z, r.w = (float(v) for v in q)
        self._tf_pub.publish(msg)

    # -- graph file, diagnostics ---------------------------------------------------------------
    def save_graph(self, *, timeout: float = -1) -> int:
        """Save the graph to ``graph.path`` between two items; returns the number of nodes."""
        def save(path: str) -> int:
            try:
                self.backend.save(path)
            except (OSError, BackendError) as err:
                raise MapError(f"graph not saved to {path}: {err}") from err
            return self.backend.stats().nodes

        return save_under_lock(self._lock, self.settings.graph.path, save, timeout=timeout, holder="back end",
                               example="/data/lcpr_graph.npz")

    def _on_save_graph(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return answer_save_request(response, self.save_graph, what="graph nodes", path=self.settings.graph.path,
                                   log=self.get_logger().info)

    def _publish_diagnostics(self) -> None:
        stats = self._stats
        refused_total = sum(stats.refused.values()) + sum(self.drops.snapshot().values())
        new, self._reported_refused = refused_total - self._reported_refused, refused_total
        times = self.model_time.percentiles(50, 95)
        values = {
            "odometry messages": stats.odometry, "graph nodes": stats.nodes,
            "loops accepted": stats.loops_accepted, "loops rejected": stats.loops_rejected,
            "loops skipped as redundant": stats.loops_redundant,
            "ups taken": stats.ups,
            "loops waiting for odometry": len(self._pending),
            "inputs refused": refused_total,
            **{f"refused {reason}": n for reason, n in sorted(stats.refused.items())},
            **{f"dropped {reason}": n for reason, n in sorted(self.drops.snapshot().items())},
            "optimisation p50 (ms)": "n/a" if times is None else f"{times[0] * 1e3:.1f}",
            "optimisation p95 (ms)": "n/a" if times is None else f"{times[1] * 1e3:.1f}",
            "last chi2": "n/a" if stats.last_chi2 is None else f"{stats.last_chi2:.2f}",
            "worker waiting": self.worker.waiting,
            **{f"rate {s} (Hz)": f"{r:.2f}" for s, r in sorted(self.rates.rates().items())},
            "warnings": "; ".join(self.warnings.causes),
        }
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if new else DiagnosticStatus.OK, name=f"{self.get_name()}: graph",
            hardware_id=HARDWARE_ID,
            message=f"{new} inputs refused since last report" if new else
            f"{stats.nodes} nodes, {stats.loops_accepted} loops",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [status]
        self._diagnostics_pub.publish(msg)

    def close(self) -> None:
        """Stop taking messages, let the worker finish its queue, then save the graph (when configured)."""
        if self._closed:
            return
        self._closed = True
        finish_and_save(self, self.worker, self.settings.graph, self.save_graph, timeout=SHUTDOWN_TIMEOUT,
                        what="graph nodes")


def _stamp_msg(seconds: float) -> Time:
    sec, nanosec = divmod(round(seconds * NS_PER_S), NS_PER_S)
    return Time(sec=int(sec), nanosec=int(nanosec))


def _set_pose(target: Any, pose: np.ndarray) -> None:
    """Fill a geometry_msgs/Pose from a 4 x 4."""
    t, q = pose_to_parts(pose)
    target.position.x, target.position.y, target.position.z = (float(v) for v in t)
    target.orientation.x, target.orientation.y, target.orientation.z, target.orientation.w = (float(v) for v in q)


# -- executable ---------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    return node_parser(prog="lcpr_backend", node_name=NODE_NAME,
                       summary="pose-graph back end: odometry + verified loops -> corrected trajectory (GTSAM iSAM2)",
                       params_file="config/lcpr_backend.yaml", parameters=describe_all())


def main(args: Sequence[str] | None = None) -> int:
    """``lcpr_backend``: 0 after a clean stop (Ctrl-C, SIGTERM), 1 when the node refuses to start."""
    return run_node(BackendNode, parser=_parser(), argv=args, closing="finishing the queued messages, then saving")


if __name__ == "__main__":
    sys.exit(main())
