"""``vseq2pc_node``: a labelled LiDAR map + a camera sequence (depth + labels) in, loop closures out.

Map side: every PointCloud2 with x, y, z and ``label`` (SemanticKITTI ids) whose pose
odometry gives becomes a map scan (thinned by ``scan.*``), or the map is loaded from
``map.path``. Query side: depth + label images (paired by stamp) with CameraInfo, the
camera-to-LiDAR extrinsics and the odometry pose make one camera feature per frame;
once the vehicle is 5/10/15 m further on, the query frame's sequence is described and
matched against the scans older than ``match.exclude_recent_s``; with ``verify.enabled`` (default) the
sequence's depth, stacked with odometry, is registered against its ``verify.top_k`` candidate scans' clouds
and only verified loops are published. Outputs: ``~/loop_closure``, ``~/candidates`` (lcpr_node's layouts and
columns; distance = 1 - probability) and ``/diagnostics`` (verified / rejected candidates by reason).
The detection itself is :class:`lcpr_core.vseq2pc.detector.SequenceDetector`; this node
declares parameters, converts messages, pairs them with poses and calls it. Conversion,
pairing, pose lookup and keyframe decisions run on the callback thread; features, the
networks and the map on one worker thread. See ``vseq2pc_node --help``.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from lcpr_core.keyframes import KEYFRAME
from lcpr_core.pretrained import describe_vseq2pc_weights, resolve_vseq2pc_weights
from lcpr_core.vseq2pc import Vseq2pcMap, Vseq2pcNet
from lcpr_core.vseq2pc.detector import CameraFrame, LabelledScan, SequenceDetector
from ros_common.diagnostics import DiagnosticsBuilder, Health
from ros_common.errors import ConfigError, InputRejected
from ros_common.inputs import (
    CLOUD_NAN,
    depth_image,
    intrinsics,
    label_image,
    labelled_cloud,
    offer_odometry,
)
from ros_common.mapstore import answer_save_request, save_under_lock
from ros_common.poses import OdometryBuffer
from ros_common.process import finish_and_save, node_parser, run_node
from ros_common.qos import CANDIDATE_QOS, QOS_ADAPTED, SensorSubscription
from ros_common.ros_params import declare
from ros_common.stamps import NS_PER_S, StampOrder, stamp_ns
from ros_common.stats import Counts, NodeStats, Window
from ros_common.worker import Worker

from .config import ExtrinsicsConfig, NodeConfig
from .mapstore import open_map
from .outputs import candidates_msg, loop_closure_msg
from .params import all_leaves, describe_all, make_runtime, settings_from
from .sync import NO_PAIR, SIZE_MISMATCH, TIME_JUMPED, ImagePairs, PoseQueue

NODE_NAME = "vseq2pc"
BUSY = "worker: item dropped while busy"
FAILED = "worker: processing failed"
RELEASE_PERIOD = 0.05
SHUTDOWN_TIMEOUT = 60.0


@dataclass
class ScanItem:
    stamp_ns: int
    scan: LabelledScan
    arrival: float


@dataclass
class CameraItem:
    stamp_ns: int
    frame: CameraFrame  # frame.session: header-time sessions started so far
    arrival: float


def build_net(cfg: NodeConfig) -> tuple[Vseq2pcNet, tuple[str, str] | None]:
    """The networks of the model.* parameters and the weight files they came from (None: seeded)."""
    m = cfg.model
    try:
        if m.threads:
            torch.set_num_threads(m.threads)
        files = resolve_vseq2pc_weights(m.sequence, m.descriptor)
        if files is not None:
            return Vseq2pcNet.from_files(sequence=files[0], descriptor=files[1], device=m.device), files
        return Vseq2pcNet.seeded(m.seed, device=m.device), None
    except Exception as err:  # noqa: BLE001 - files, formats, devices: all refuse the start
        raise ConfigError(f"cannot build the VSeq2PC networks from the model.* parameters: {err}") from err


class Vseq2pcNode(NodeStats, Node):
    """The ``vseq2pc`` node. Raises ConfigError / MapLoadError when it cannot start."""

    def __init__(self, *, parameter_overrides: list[Parameter] | None = None, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, parameter_overrides=parameter_overrides, **kwargs)
        self._leaves = all_leaves()
        self.settings: NodeConfig = settings_from(declare(self, self._leaves))
        cfg = self.settings
        log = self.get_logger()
        self.init_stats(log.warning, window=cfg.diagnostics.window)
        self.session_scans = 0
        self.queries = 0
        self.verify_time = Window(cfg.diagnostics.window)  # s: verification of one camera frame's queries
        self.verdicts = Counts()  # candidates by verdict ("accepted" or why not)
        self._closed = False

        self.net, files = build_net(cfg)
        log.info(f"VSeq2PC: {describe_vseq2pc_weights(files)}")
        if files is None:
            log.warning(f"model.sequence and model.descriptor are seeded: random weights (seed {cfg.model.seed}), "
                        "for testing only; matches mean nothing")
        if cfg.extrinsics == ExtrinsicsConfig():
            log.warning("extrinsics.* are at their default, KITTI's camera-0-to-Velodyne setup; set them to this "
                        "vehicle's camera-to-LiDAR calibration (extrinsics.xyz and extrinsics.rpy, or "
                        "extrinsics.format:=matrix with extrinsics.matrix)")
        self.detector = SequenceDetector(cfg.detector(), net=self.net,
                                         prior_map=open_map(cfg.map.path, self.net, cfg.match.search()))
        self._map_lock = threading.Lock()

        self._sensor_subscriptions: list[SensorSubscription] = []
        self._input_qos = cfg.input_qos
        self.poses = OdometryBuffer(slop=cfg.sync.slop, max_gap=cfg.sync.odom_max_gap, jump_back=cfg.sync.jump_back)
        self._subscribe(Odometry, cfg.odom_topic, self._on_odom)  # first: poses before sensors
        self.pairs = ImagePairs(slop=cfg.sync.slop, capacity=cfg.sync.image_buffer, jump_back=cfg.sync.jump_back)
        self.scan_queue = PoseQueue(self.poses, max_wait=cfg.sync.max_wait, capacity=cfg.sync.max_pending)
        self.camera_queue = PoseQueue(self.poses, max_wait=cfg.sync.max_wait, capacity=cfg.sync.max_pending)
        self._cloud_order = StampOrder(round(cfg.sync.jump_back * NS_PER_S))
        self._timelines = {"cloud": 0, "camera": 0}  # odometry timeline each stream follows (follow_jump)
        self.camera_sessions = 0  # times header time jumped back on the depth or the label stream
        self._camera: tuple[np.ndarray, int, int] | None = None  # K, width, height

        self._loop_pub = self.create_publisher(Float64MultiArray, "~/loop_closure", CANDIDATE_QOS)
        self._candidates_pub = self.create_publisher(Float64MultiArray, "~/candidates", CANDIDATE_QOS)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diagnostics = DiagnosticsBuilder(self.get_name())

        self._subscribe(CameraInfo, cfg.camera_info_topic, self._on_camera_info)
        self._subscribe(PointCloud2, cfg.lidar_topic, self._on_cloud)
        self._subscribe(Image, cfg.depth_topic, partial(self._on_image, "depth"))
        self._subscribe(Image, cfg.labels_topic, partial(self._on_image, "labels"))
        if cfg.image_topic:
            self._subscribe(Image, cfg.image_topic, lambda msg: self.rates.tick(cfg.image_topic))
        self.create_service(Trigger, "~/save_map", self._on_save_map)
        self.create_timer(RELEASE_PERIOD, self._release)
        self.create_timer(cfg.diagnostics.period, self._publish_diagnostics)

        self.worker: Worker[ScanItem | CameraItem] = Worker(
            self._process, max_waiting=cfg.worker.max_waiting, on_dropped=self._on_dropped, on_error=self._on_failed,
            name="vseq2pc-worker")
        self.worker.start()
        make_runtime(self, self._leaves, self._apply)
        log.info(f"ready: lidar {cfg.lidar_topic}, depth {cfg.depth_topic}, labels {cfg.labels_topic}, odometry "
                 f"{cfg.odom_topic}; map {cfg.map.path or 'memory only'} with {len(self.map)} scans")

    @property
    def map(self) -> Vseq2pcMap:
        return self.detector.map

    # -- inputs (callback thread) -------------------------------------------------------------
    def _reject(self, err: InputRejected) -> None:
        self.drops.add(err.reason)
        self.warnings(err.reason, err.detail)

    def _subscribe(self, msg_type: type, topic: str, callback: Callable[[Any], None]) -> None:
        self._sensor_subscriptions.append(SensorSubscription(self, msg_type, topic, callback, self._input_qos,
                                                             warn=lambda text: self.warnings(QOS_ADAPTED, text)))

    def _on_odom(self, msg: Odometry) -> None:
        self.rates.tick(self.settings.odom_topic)
        try:
            offer_odometry(self.poses, msg)
        except InputRejected as err:
            self._reject(err)
            return
        self._release()

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.rates.tick(self.settings.camera_info_topic)
        try:
            self._camera = intrinsics(msg)
        except InputRejected as err:
            self._reject(err)

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.rates.tick(self.settings.lidar_topic)
        ns = stamp_ns(msg.header)
        try:
            points, labels, removed = labelled_cloud(msg)
        except InputRejected as err:
            self._reject(err)
            return
        refused = self._cloud_order.check(ns)
        if refused is not None:
            self._reject(InputRejected(f"cloud: {refused}", f"stamp {ns / NS_PER_S:.9f}"))
            return
        if self._cloud_order.jumped_from is not None:
            self._time_jumped("cloud", ns, self._cloud_order.jumped_from)
            self.scan_queue.forget_after(ns)
            self.detector.restart_keyframing("scan")
        if removed:
            self.fixes.add(CLOUD_NAN, removed)
            self.warnings(CLOUD_NAN, f"{removed} of {removed + len(points)} points had NaN/inf x, y or z")
        self.scan_queue.put(ns, (points, labels, time.monotonic()))
        self._release()

    def _on_image(self, kind: str, msg: Image) -> None:
        topic = self.settings.depth_topic if kind == "depth" else self.settings.labels_topic
        self.rates.tick(topic)
        ns = stamp_ns(msg.header)
        try:
            image = depth_image(msg) if kind == "depth" else label_image(msg)
        except InputRejected as err:
            self._reject(InputRejected(err.reason, f"{topic}: {err.detail}"))
            return
        before = self.pairs.unpaired
        refused, pair = self.pairs.offer(kind, ns, image)
        if refused is not None:
            self._reject(InputRejected(f"{kind}: {refused}", f"{topic} stamp {ns / NS_PER_S:.9f}"))
            return
        jumped_from = self.pairs.orders[kind].jumped_from
        if jumped_from is not None:  # depth and labels each jump: frames between them none
            self._time_jumped(kind, ns, jumped_from)
            self.camera_sessions += 1
            self.camera_queue.forget_after(ns)
            self.detector.restart_keyframing("camera")
        if self.pairs.unpaired > before:
            self.drops.add(NO_PAIR, self.pairs.unpaired - before)
            self.warnings(NO_PAIR, f"no partner within sync.slop={self.settings.sync.slop} s")
        if pair is not None:
            stamp, depth, labels = pair
            if depth.shape != labels.shape:
                self._reject(InputRejected(SIZE_MISMATCH, f"depth {depth.shape[1]} x {depth.shape[0]}, labels "
                                                          f"{labels.shape[1]} x {labels.shape[0]}"))
                return
            self.camera_queue.put(stamp, (depth, labels, time.monotonic()))
            self._release()

    def _time_jumped(self, stream: str, ns: int, newest_ns: int) -> None:
        """Header time went back on one stream: odometry follows; warn once, count each time."""
        key = "camera" if stream in ("depth", "labels") else stream
        self._timelines[key] = self.poses.follow_jump(ns + self.pairs.slop_ns, self._timelines[key])
        self.fixes.add(TIME_JUMPED)
        self.warnings(TIME_JUMPED, f"{stream} stamp {ns / NS_PER_S:.3f} s is {(newest_ns - ns) / NS_PER_S:.1f} s "
                                   f"before the last one, more than sync.jump_back = {self.settings.sync.jump_back} s "
                                   "(a bag played again or with --loop, a simulator reset): a new session starts in "
                                   "the same map, whose scans stay matchable; no camera sequence spans the jump")

    def _release(self) -> None:
        if self._closed:
            return
        before = sum(self.scan_queue.drops.values()) + sum(self.camera_queue.drops.values())
        for item, pose in self.scan_queue.ready():
            points, labels, arrival = item.payload
            stamp = item.stamp_ns / NS_PER_S
            if self.detector.scan_keyframe(stamp, pose) != KEYFRAME:
                self.decisions.add("scans skipped (scan.min_distance / min_interval)")
                continue
            self.worker.submit(ScanItem(item.stamp_ns, LabelledScan(stamp, points, labels, pose), arrival))
        for item, pose in self.camera_queue.ready(lambda payload: self._camera is not None):
            depth, labels, arrival = item.payload
            assert self._camera is not None
            K, width, height = self._camera
            if depth.shape != (height, width):
                self._reject(InputRejected(SIZE_MISMATCH, f"images {depth.shape[1]} x {depth.shape[0]}, "
                                                          f"camera_info {width} x {height}"))
                continue
            stamp = item.stamp_ns / NS_PER_S
            if self.detector.camera_keyframe(stamp, pose) != KEYFRAME:
                self.decisions.add("camera frames skipped (camera.min_distance / min_interval)")
                continue
            frame = CameraFrame(stamp, depth, labels, K, pose, session=self.camera_sessions)
            self.worker.submit(CameraItem(item.stamp_ns, frame, arrival))
        after = sum(self.scan_queue.drops.values()) + sum(self.camera_queue.drops.values())
        if after > before:
            for queue in (self.scan_queue, self.camera_queue):
                for reason, n in queue.drops.items():
                    self.warnings(reason, f"{n} item(s) so far")

    # -- worker thread --------------------------------------------------------------------------
    def _process(self, item: ScanItem | CameraItem) -> None:
        start = time.monotonic()
        if isinstance(item, ScanItem):
            with self._map_lock:
                self.detector.add_scan(item.scan)
            self.session_scans += 1
            self.decisions.add("scans added")
            self.model_time.add(time.monotonic() - start)
            return
        with self._map_lock:
            result = self.detector.process(item.frame)
        if result.unfinished:
            self.decisions.add("queries left unfinished by a time jump", result.unfinished)
        self.decisions.add("camera frames")
        if result.frame_problem is not None:
            self.drops.add(f"pseudo-cloud: {result.frame_problem}")
            self.warnings(f"pseudo-cloud: {result.frame_problem}", f"camera frame {item.frame.stamp:.9f} gives no "
                          "pseudo-cloud; the candidates of the queries it belongs to stay unverified")
        for error in result.errors:
            self.warnings("verification failed", f"{error}; the candidate counts as unverified, the node goes on")
        if "verify" in result.timings:
            self.verify_time.add(result.timings["verify"])
        if not result.queries:
            return
        for query in result.queries:
            if query.late:  # an earlier query's loop, confirmed by a later one: counted once, at its own time
                self.decisions.add("loops confirmed late")
            else:
                self.queries += 1
                self.decisions.add("queries")
                if not query.candidates:
                    self.decisions.add("queries without candidates")
                    continue
                for candidate in query.candidates:
                    if candidate.verification != "off":
                        self.verdicts.add(candidate.verification)
            self._candidates_pub.publish(candidates_msg(query.stamp, query.query_id, query.candidates))
            if query.loop is None:
                self.decisions.add("queries without a verified candidate")
                continue
            self._loop_pub.publish(loop_closure_msg(query.stamp, query.loop))
            self.loops += 1
        self.latency.add(time.monotonic() - item.arrival)
        self.model_time.add(time.monotonic() - start)

    def _on_dropped(self, item: ScanItem | CameraItem) -> None:
        self.drops.add(BUSY)
        self.warnings(BUSY, f"more than worker.max_waiting={self.settings.worker.max_waiting} items waiting; "
                            "the oldest is dropped")

    def _on_failed(self, item: ScanItem | CameraItem, err: Exception) -> None:
        self.drops.add(FAILED)
        self.warnings(f"{FAILED} ({type(err).__name__})",
                      f"{type(item).__name__} {item.stamp_ns / NS_PER_S:.9f}: {err}; the map is kept, the node goes on")

    # -- parameters, map, diagnostics ----------------------------------------------------------
    def _apply(self, settings: NodeConfig) -> None:
        self.settings = settings
        self.detector.config = settings.detector()
        self.poses.configure(slop=settings.sync.slop, max_gap=settings.sync.odom_max_gap)
        self.pairs.slop_ns = round(settings.sync.slop * NS_PER_S)
        for queue in (self.scan_queue, self.camera_queue):
            queue.max_wait = settings.sync.max_wait

    def save_map(self, *, timeout: float = -1) -> int:
        """Save the map to ``map.path`` between two items; returns the number of scans."""
        def save(path: str) -> int:
            self.map.save(path)
            return len(self.map)

        return save_under_lock(self._map_lock, self.settings.map.path, save, timeout=timeout, holder="map",
                               example="/data/vseq2pc_map.npz")

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return answer_save_request(response, self.save_map, what="scans", path=self.settings.map.path,
                                   log=self.get_logger().info)

    def health(self) -> Health:
        drops = self.drops.snapshot()
        for queue in (self.scan_queue, self.camera_queue):
            for reason, n in queue.drops.items():
                drops[reason] = drops.get(reason, 0) + n
        return Health(
            rates=self.rates.rates(), totals=dict(self.rates.totals), drops=drops, fixes=self.fixes.snapshot(),
            decisions=self.decisions.snapshot(), warnings=self.warnings.causes,
            latency=self.latency.percentiles(50, 90, 99), model=self.model_time.percentiles(50, 90, 99),
            map_size=len(self.map), session_keyframes=self.session_scans, loops=self.loops,
            sync_pending=len(self.scan_queue) + len(self.camera_queue), worker_waiting=self.worker.waiting,
            worker_busy=self.worker.busy, verification=self.verdicts.snapshot(),
            verify_time=self.verify_time.percentiles(50, 90, 99),
        )

    def _publish_diagnostics(self) -> None:
        sec, nanosec = self.get_clock().now().seconds_nanoseconds()
        self._diagnostics_pub.publish(self._diagnostics.build(self.health(), sec, nanosec))

    def close(self) -> None:
        """Stop taking items, let the worker finish, then save the map (when configured)."""
        if self._closed:
            return
        self._closed = True
        finish_and_save(self, self.worker, self.settings.map, self.save_map, timeout=SHUTDOWN_TIMEOUT, what="scans")


# -- executable ---------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    return node_parser(prog="vseq2pc_node", node_name="vseq2pc",
                       summary="VSeq2PC camera-sequence to LiDAR-map loop closure",
                       params_file="config/vseq2pc.yaml", parameters=describe_all())


def main(args: Sequence[str] | None = None) -> int:
    """``vseq2pc_node``: 0 after a clean stop (Ctrl-C, SIGTERM), 1 when the node refuses to start."""
    return run_node(Vseq2pcNode, parser=_parser(), argv=args, closing="finishing queued items, then saving the map")

if __name__ == "__main__":
    sys.exit(main())
