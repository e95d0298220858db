"""``lcpr_node``: six cameras + one LiDAR (+ odometry) in, loop-closure candidates out.

The node declares the parameters (:mod:`lcpr_ros.params`), builds the detector's
config, converts and synchronises messages on the callback thread and hands each
synchronised frame to one worker thread that runs :class:`LoopDetector` (the newest
frame waits in a single slot while the worker is busy). See ``lcpr_node --help``.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import Float64MultiArray, String, UInt8MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from lcpr_core.detector import DetectorConfig, Frame, LoopDetector, PeerKeyframe, Result, encode_peer_keyframe
from lcpr_core.geometry import xyz_rpy_from_pose
from lcpr_core.lcpr.preprocess.camera import CameraInput
from lcpr_core.pretrained import describe_weights, threshold_text
from ros_common.diagnostics import DiagnosticsBuilder, Health
from ros_common.errors import ConfigError, InputRejected
from ros_common.inputs import (
    CLOUD_NAN,
    IMAGE_DECODE,
    camera_input,
    cloud_points,
    compressed_payload,
    offer_odometry,
    peer_keyframe,
    raw_payload,
)
from ros_common.mapstore import answer_save_request, save_under_lock
from ros_common.poses import NoPoses, OdometryBuffer, PoseSource
from ros_common.process import finish_and_save, node_parser, run_node
from ros_common.qos import CANDIDATE_QOS, LATCHED_QOS, QOS_ADAPTED, SensorSubscription, keyframes_qos
from ros_common.ros_params import RuntimeParameters, declare
from ros_common.stamps import NS_PER_S, stamp_ns
from ros_common.static_tf import STATIC_QOS, StaticExtrinsic, tf_message_type
from ros_common.stats import Counts, NodeStats, Window
from ros_common.worker import Worker

from .config import NodeConfig
from .mapstore import load_prior_map, save_map
from .markers import LoopMarkers, MarkerSink, NoMarkers
from .outputs import SessionTable, candidates_msg, keyframe_msg, loop_closure_msg, sessions_msg, up_msg
from .params import RENAMED, Settings, all_leaves, describe_all, settings_from
from .sync import LATE_IMAGE, TIME_JUMPED, SyncedFrame, Synchroniser

NODE_NAME = "lcpr"
BUSY = "frame: replaced while busy"
LATE_IMAGE_HELP = ("{topic}: an image came after its frame had gone without it (lost in transport, then repaired). "
                   "The usual cause: a process that publishes images and clouds through Fast DDS's default 512 KiB "
                   "shared-memory segment. Give that publisher a larger segment with a Fast DDS profile "
                   "(FASTRTPS_DEFAULT_PROFILES_FILE on Jazzy, FASTDDS_DEFAULT_PROFILES_FILE on Kilted; "
                   "lcpr_ros.replay.FASTDDS_PROFILE is a template). With Kilted's Fast DDS 3, running this node "
                   "with FASTDDS_BUILTIN_TRANSPORTS=UDPv4 also helps; with Jazzy's it did not")
FAILED = "frame: processing failed"
PEER_BUSY = "peer keyframe: dropped while busy"
PEER_FAILED = "peer keyframe: processing failed"
PEER_QUEUE = 1024  # peer keyframes waiting for the detector at most (a late start's catch-up from a few peers)
RELEASE_PERIOD = 0.05  # s between checks for clouds whose wait for images ran out
SHUTDOWN_TIMEOUT = 60.0  # s the worker may take to finish its frames at shutdown



class LcprNode(NodeStats, Node):
    """The ``lcpr`` node. Raises ConfigError / MapLoadError when it cannot start."""

    def __init__(self, *, parameter_overrides: list[Parameter] | None = None, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, parameter_overrides=parameter_overrides, **kwargs)
        self._leaves = all_leaves()
        self.settings: Settings = settings_from(declare(self, self._leaves, renamed=RENAMED))
        node_cfg, det_cfg = self.settings.node, self.settings.detector
        log = self.get_logger()
        own = f"{self.get_namespace().rstrip('/')}/"
        if any(f"{p.rstrip('/')}/" == own for p in node_cfg.peers):
            raise ConfigError(f"peers={list(node_cfg.peers)} names this node's own namespace {self.get_namespace()!r}; "
                              "give the other robots' namespaces")
        self.init_stats(log.warning, window=node_cfg.diagnostics.window)
        self.verify_time = Window(node_cfg.diagnostics.window)
        self.verdicts = Counts()
        self._closed = False

        prior = load_prior_map(node_cfg.map.path, det_cfg.map)
        try:
            self.detector = LoopDetector(det_cfg, prior_map=prior)
        except Exception as err:  # noqa: BLE001 - weights, device, sizes: all refuse the start
            raise ConfigError(f"cannot build the detector from the model.* parameters: {err}") from err
        threshold = threshold_text(det_cfg.match.max_distance, self.detector.weights_threshold,
                                   verified=det_cfg.verify.enabled)
        log.info(f"LCPR: {describe_weights(self.detector.describer.config.weights)}; {threshold}")
        self._detector_lock = threading.Lock()
        self._next_detector_config: DetectorConfig | None = None

        self._sensor_subscriptions: list[SensorSubscription] = []
        self.poses, self.markers = self._pose_parts(node_cfg)  # first: see _pose_parts
        self.sync = Synchroniser(node_cfg.frame_sync(), len(node_cfg.subscribed_cameras()), poses=self.poses)

        self._loop_pub = self.create_publisher(Float64MultiArray, "~/loop_closure", CANDIDATE_QOS)
        self._candidates_pub = self.create_publisher(Float64MultiArray, "~/candidates", CANDIDATE_QOS)
        self._up_pub = self.create_publisher(Vector3Stamped, "~/up", CANDIDATE_QOS)
        self._keyframes_pub = self.create_publisher(UInt8MultiArray, "~/keyframes",
                                                    keyframes_qos(node_cfg.keyframes_history))
        self._sessions_pub = self.create_publisher(String, "~/sessions", LATCHED_QOS)
        self._sessions = SessionTable()  # the session codes of ~/candidates
        self._publish_lock = threading.Lock()  # the table and its topics: two workers publish candidates
        self._peer_sessions: frozenset[str] = frozenset()  # sessions of the peer keyframes taken so far
        self._sessions.code(det_cfg.session)
        self._sessions_pub.publish(sessions_msg(self._sessions.names))
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diagnostics = DiagnosticsBuilder(self.get_name())

        self._payload: list[Callable[[Any], Any]] = []
        for k, topic in enumerate(node_cfg.subscribed_cameras()):
            compressed = node_cfg.compressed(k)
            self._payload.append(compressed_payload if compressed else raw_payload)
            self._subscribe(CompressedImage if compressed else Image, topic, partial(self._on_image, k))
        self._subscribe(PointCloud2, node_cfg.lidar_topic, self._on_cloud)
        self._static_tf, self._frames = StaticExtrinsic(), {"base": "", "lidar": ""}
        self._mount: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # from /tf_static
        self._listen_tf_static(node_cfg.tf_static_topic)
        self.create_service(Trigger, "~/save_map", self._on_save_map)
        self.create_timer(RELEASE_PERIOD, self._release)
        self.create_timer(node_cfg.diagnostics.period, self._publish_diagnostics)

        self.worker: Worker[SyncedFrame] = Worker(self._process, on_dropped=self._on_replaced, name="lcpr-worker",
                                                  on_error=self._on_failed)
        self.worker.start()
        self.peer_worker: Worker[tuple[str, PeerKeyframe]] = Worker(
            self._process_peer, max_waiting=PEER_QUEUE, on_dropped=self._on_peer_dropped, name="lcpr-peers",
            on_error=self._on_peer_failed)
        self.peer_worker.start()
        for topic in node_cfg.peer_topics():
            self.create_subscription(UInt8MultiArray, topic, partial(self._on_peer, topic),
                                     keyframes_qos(node_cfg.keyframes_history))
        RuntimeParameters(self, self._leaves, self._apply, build=settings_from)
        where = node_cfg.map.path or "memory only"
        cameras = len(node_cfg.subscribed_cameras()) or "no (lidar_only)"
        peers = ", ".join(node_cfg.peer_topics()) or "none"
        log.info(f"ready: {cameras} cameras, lidar {node_cfg.lidar_topic}, "
                 f"odometry {node_cfg.odom_topic or 'none'}; map {where} with {len(self.detector.map)} places; "
                 f"session {det_cfg.session!r}, peers {peers}")

    def _pose_parts(self, cfg: NodeConfig) -> tuple[PoseSource, MarkerSink]:
        """Odometry buffer + markers, or their null objects when there is no odometry topic.

        The odometry subscription is created before the sensor ones: when a pose and a
        cloud are both waiting, the executor then takes the pose first.
        """
        if not cfg.odom_topic:
            return NoPoses(), NoMarkers()
        buffer = OdometryBuffer(slop=cfg.sync.slop, max_gap=cfg.sync.odom_max_gap, jump_back=cfg.sync.jump_back)
        self._subscribe(Odometry, cfg.odom_topic, partial(self._on_odom, buffer))
        return buffer, LoopMarkers(self.create_publisher(MarkerArray, "~/markers", CANDIDATE_QOS))

    def _listen_tf_static(self, topic: str) -> None:
        """Subscribe ``topic`` for the submap mount, where tf2_msgs imports (a sourced ROS 2)."""
        if not topic:
            return
        tf_type = tf_message_type()
        if tf_type is None:
            self.get_logger().info(f"tf_static_topic {topic}: tf2_msgs is not importable (no sourced ROS 2), so the "
                                   "submap mount is submap.lidar_xyz / lidar_rpy")
            return
        self.create_subscription(tf_type, topic, self._on_tf_static, STATIC_QOS)

    def _on_tf_static(self, msg: Any) -> None:
        if self._static_tf.offer(msg):
            self._find_mount()

    def _note_frame(self, which: str, frame: str) -> None:
        if frame and frame != self._frames[which]:
            self._frames[which] = frame
            self._find_mount()

    def _find_mount(self) -> None:
        """Take the mount odometry child frame -> cloud frame from /tf_static once both frames are known."""
        base, lidar = self._frames["base"], self._frames["lidar"]
        if not base or not lidar:
            return
        T = self._static_tf.lookup(base, lidar)
        if T is None:
            return
        mount = xyz_rpy_from_pose(T)
        if mount == self._mount:
            return
        self._mount = mount
        (x, y, z), (roll, pitch, yaw) = mount
        self.get_logger().info(f"submap mount from {self.settings.node.tf_static_topic} {base} -> {lidar}: "
                               f"xyz ({x:.3f}, {y:.3f}, {z:.3f}) m, rpy ({roll:.4f}, {pitch:.4f}, {yaw:.4f}) rad "
                               "(replaces submap.lidar_xyz / lidar_rpy)")
        self._apply(self.settings)

    def _with_mount(self, settings: Settings) -> Settings:
        """``settings`` with the /tf_static mount in place of submap.lidar_xyz / lidar_rpy, once one is known."""
        if self._mount is None:
            return settings
        det = settings.detector
        submap = dataclasses.replace(det.submap, lidar_xyz=self._mount[0], lidar_rpy=self._mount[1])
        return dataclasses.replace(settings, detector=dataclasses.replace(det, submap=submap))

    def _subscribe(self, msg_type: type, topic: str, callback: Callable[[Any], None]) -> None:
        self._sensor_subscriptions.append(SensorSubscription(
            self, msg_type, topic, callback, self.settings.node.input_qos,
            warn=lambda text: self.warnings(QOS_ADAPTED, text)))

    # -- inputs (callback thread) ---------------------------------------------------------
    def _reject(self, err: InputRejected) -> None:
        self.drops.add(err.reason)
        self.warnings(err.reason, err.detail)

    def _on_image(self, camera: int, msg: Any) -> None:
        topic = self.settings.node.camera_topics[camera]
        self.rates.tick(topic)
        try:
            payload = self._payload[camera](msg)
        except InputRejected as err:
            self._reject(InputRejected(err.reason, f"{topic}: {err.detail}"))
            return
        ns = stamp_ns(msg.header)
        late = self.sync.late[camera]
        refused = self.sync.offer_image(camera, ns, payload)
        if refused is not None:
            self._reject(InputRejected(f"image: {refused}", f"{topic} stamp {ns / NS_PER_S:.9f}"))
            return
        if self.sync.late[camera] > late:
            self._reject(InputRejected(LATE_IMAGE, LATE_IMAGE_HELP.format(topic=topic)))
        self._release()

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.rates.tick(self.settings.node.lidar_topic)
        ns = stamp_ns(msg.header)
        self._note_frame("lidar", str(msg.header.frame_id))
        try:
            points, removed = cloud_points(msg)
        except InputRejected as err:
            self._reject(err)
            return
        if removed:
            self.fixes.add(CLOUD_NAN, removed)
            self.warnings(CLOUD_NAN, f"{removed} of {removed + len(points)} points had NaN/inf x, y or z")
        restarts = self.sync.restarts
        refused = self.sync.offer_cloud(ns, points)
        if refused is not None:
            self._reject(InputRejected(f"cloud: {refused}", f"stamp {ns / NS_PER_S:.9f}"))
            return
        if self.sync.restarts > restarts:
            self.fixes.add(TIME_JUMPED)
            self.warnings(TIME_JUMPED, f"cloud stamp {ns / NS_PER_S:.3f} s is more than sync.jump_back = "
                                       f"{self.settings.node.sync.jump_back} s before the last one (a bag played "
                                       "again or with --loop, a simulator reset): a new session starts in the same "
                                       "map, whose earlier keyframes stay matchable")
        self._release()

    def _on_odom(self, buffer: OdometryBuffer, msg: Odometry) -> None:
        self.rates.tick(self.settings.node.odom_topic)
        self._note_frame("base", str(msg.child_frame_id))
        try:
            offer_odometry(buffer, msg)
        except InputRejected as err:
            self._reject(err)
            return
        self._release()

    def _on_peer(self, topic: str, msg: UInt8MultiArray) -> None:
        """A peer's keyframe: read here, matched and stored by the peer worker (the detector may be busy)."""
        self.rates.tick(topic)
        try:
            kf = peer_keyframe(msg)
        except InputRejected as err:
            self._reject(InputRejected(err.reason, f"{topic}: {err.detail}"))
            return
        if not self._closed:
            self.peer_worker.submit((topic, kf))

    def _release(self) -> None:
        if self._closed:
            return
        before = sum(self.sync.drops.values())
        for frame in self.sync.ready():
            for k in frame.stopped:
                topic = self.settings.node.camera_topics[k]
                timeout = self.settings.node.sync.camera_timeout
                self.warnings(f"camera stopped: {topic}",
                              f"no image for {timeout} s of header time; frames go on without it (degraded)")
            self.worker.submit(frame)
        if sum(self.sync.drops.values()) > before:
            for reason, n in self.sync.drops.items():
                self.warnings(reason, f"{n} frame(s) so far")

    # -- worker thread -------------------------------------------------------------------------
    def _process(self, synced: SyncedFrame) -> None:
        images: list[CameraInput | None] = []
        for k, payload in enumerate(synced.cameras):
            if payload is None:
                images.append(None)
                continue
            try:
                images.append(camera_input(payload))  # compressed bytes stay bytes: the describer decodes them
            except InputRejected as err:
                self._reject(InputRejected(err.reason, f"{self.settings.node.camera_topics[k]}: {err.detail}"))
                images.append(None)
        images += [None] * (self.settings.detector.model.num_cameras - len(images))  # lidar_only: all slots empty
        frame = Frame(stamp=synced.stamp_ns / NS_PER_S, images=images, points=synced.points, pose=synced.pose)
        self.get_logger().debug(f"frame {frame.stamp:.9f}: deciding")
        with self._detector_lock:
            self._take_config()
            if synced.new_session:
                self.detector.start_session()
            result = self.detector.process(frame)
            max_distance = self.detector.max_distance
            own = None if result.keyframe_id is None else self.detector.peer_keyframe(result.keyframe_id)
            peers = self._peer_sessions
        if own is not None:  # for the peers, first: they match it while this node goes on
            self._keyframes_pub.publish(keyframe_msg(encode_peer_keyframe(own)))
        for k, why in result.camera_errors.items():  # undecodable bytes: that camera left out of this frame
            self._reject(InputRejected(IMAGE_DECODE, f"{self.settings.node.camera_topics[k]}: {why}"))
        self.decisions.add(result.reason)
        if result.keyframe_id is None:
            return
        for candidate in result.candidates:
            if candidate.verification != "off":
                self.verdicts.add(candidate.verification)
        for error in result.errors:
            self.warnings("verification failed", f"{error}; the candidate counts as unverified, the node goes on")
        up = up_msg(result, self._frames["lidar"])
        if up is not None:  # before the candidates: the back end holds the keyframe's up when its loops come
            self._up_pub.publish(up)
        if result.candidates:
            self._publish_candidates(result)
            # a peer's keyframe lies in its own odometry frame: no marker joins it to ours
            ours = dataclasses.replace(result, candidates=[c for c in result.candidates
                                                           if c.match_session not in peers])
            if ours.candidates:
                self.markers.publish(ours, synced.pose, self.poses.frame_id, max_distance)
        loop = loop_closure_msg(result, skip_sessions=peers)
        if loop is not None:
            self._loop_pub.publish(loop)
            self.loops += 1
        self.latency.add(time.monotonic() - synced.arrival)
        self.model_time.add(result.timings.get("preprocess", 0.0) + result.timings.get("network", 0.0))
        if result.candidates and "verify" in result.timings:  # a keyframe without candidates verifies nothing
            self.verify_time.add(result.timings["verify"])

    def _take_config(self) -> None:
        """Parameters changed at run time reach the detector between two keyframes (under the detector lock)."""
        if self._next_detector_config is not None:
            self.detector.config, self._next_detector_config = self._next_detector_config, None

    def _publish_candidates(self, result: Result) -> None:
        """``~/candidates``, after ``~/sessions`` when a session is new to the table."""
        with self._publish_lock:
            known = len(self._sessions)
            msg = candidates_msg(result, self._sessions)
            if len(self._sessions) > known:
                self._sessions_pub.publish(sessions_msg(self._sessions.names))
            if msg is not None:
                self._candidates_pub.publish(msg)

    def _process_peer(self, item: tuple[str, PeerKeyframe]) -> None:
        """A peer's keyframe matched against this map, verified and stored (the peer worker's thread)."""
        topic, kf = item
        with self._detector_lock:
            self._take_config()
            result = self.detector.add_peer_keyframe(kf)
            if result.keyframe_id is not None:
                self._peer_sessions = self._peer_sessions | {kf.session}
        if result.keyframe_id is None:  # refused: nothing stored
            self._reject(InputRejected(result.reason, f"{topic}: {'; '.join(result.errors)}"))
            return
        self.decisions.add(result.reason)
        for candidate in result.candidates:
            if candidate.verification != "off":
                self.verdicts.add(candidate.verification)
        for error in result.errors:
            self.warnings("verification failed", f"{error}; the candidate counts as unverified, the node goes on")
        if result.candidates:
            self._publish_candidates(result)
            if "verify" in result.timings:
                self.verify_time.add(result.timings["verify"])

    def _on_peer_dropped(self, item: tuple[str, PeerKeyframe]) -> None:
        self.drops.add(PEER_BUSY)
        self.warnings(PEER_BUSY, f"{PEER_QUEUE} peer keyframes were waiting for the detector; the oldest "
                                 f"({item[0]}, stamp {item[1].stamp:.3f}) was dropped")

    def _on_peer_failed(self, item: tuple[str, PeerKeyframe], err: Exception) -> None:
        self.drops.add(PEER_FAILED)
        self.warnings(f"{PEER_FAILED} ({type(err).__name__})",
                      f"{item[0]} stamp {item[1].stamp:.3f}: {err}; the map is kept, the node goes on")

    def _on_replaced(self, frame: SyncedFrame) -> None:
        self.drops.add(BUSY)
        self.warnings(BUSY, "frames arrive faster than the detector describes them; the newest one waits, "
                            "older ones are dropped")

    def _on_failed(self, frame: SyncedFrame, err: Exception) -> None:
        self.drops.add(FAILED)
        self.warnings(f"{FAILED} ({type(err).__name__})",
                      f"frame {frame.stamp_ns / NS_PER_S:.9f}: {err}; the map is kept, the node goes on")

    # -- parameters, map, diagnostics -----------------------------------------------------
    def _apply(self, settings: Settings) -> None:
        settings = self._with_mount(settings)
        self.settings = settings
        self._next_detector_config = settings.detector  # taken by the worker before its next frame
        self.sync.config = settings.node.frame_sync()
        self.poses.configure(slop=settings.node.sync.slop, max_gap=settings.node.sync.odom_max_gap)

    def save_map(self, *, timeout: float = -1) -> int:
        """Save the map to ``map.path`` between two frames; returns the number of places."""
        return save_under_lock(self._detector_lock, self.settings.node.map.path,
                               lambda path: save_map(self.detector.map, path), timeout=timeout, holder="detector",
                               example="/data/lcpr_map.npz")

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return answer_save_request(response, self.save_map, what="places", path=self.settings.node.map.path,
                                   log=self.get_logger().info)

    def health(self) -> Health:
        topics = self.settings.node.camera_topics
        drops = self.drops.snapshot()
        for reason, n in self.sync.drops.items():
            drops[reason] = n
        return Health(
            rates=self.rates.rates(), totals=dict(self.rates.totals), drops=drops, fixes=self.fixes.snapshot(),
            decisions=self.decisions.snapshot(), stopped=[topics[k] for k in self.sync.stopped_cameras()],
            missing={topics[k]: n for k, n in enumerate(self.sync.missing)}, warnings=self.warnings.causes,
            latency=self.latency.percentiles(50, 90, 99), model=self.model_time.percentiles(50, 90, 99),
            map_size=len(self.detector.map), session_keyframes=self.detector.session_keyframes, loops=self.loops,
            verification=self.verdicts.snapshot(), verify_time=self.verify_time.percentiles(50, 90, 99),
            sync_pending=self.sync.pending, worker_waiting=self.worker.waiting, worker_busy=self.worker.busy,
            inference=self.detector.describer.path,
            runtime=self.detector.describer.runtime,
        )

    def _publish_diagnostics(self) -> None:
        newest = self.sync.newest_stamp
        if newest is None:
            sec, nanosec = self.get_clock().now().seconds_nanoseconds()
        else:
            sec, nanosec = divmod(newest, NS_PER_S)
        self._diagnostics_pub.publish(self._diagnostics.build(self.health(), sec, nanosec))

    def close(self) -> None:
        """Stop taking frames, let the worker finish, then save the map (when configured)."""
        if self._closed:
            return
        self._closed = True
        self.peer_worker.stop(drain=False, timeout=SHUTDOWN_TIMEOUT)  # the keyframe in progress finishes
        finish_and_save(self, self.worker, self.settings.node.map, self.save_map, timeout=SHUTDOWN_TIMEOUT,
                        what="places")
        self.detector.close()  # verification worker processes, if any


# -- executable -------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    return node_parser(prog="lcpr_node", node_name="lcpr", summary="LCPR loop-closure detection node",
                       params_file="config/lcpr.yaml", parameters=describe_all())


def main(args: Sequence[str] | None = None) -> int:
    """``lcpr_node``: 0 after a clean stop (Ctrl-C, SIGTERM), 1 when the node refuses to start."""
    return run_node(LcprNode, parser=_parser(), argv=args, closing="finishing the current frame, then saving the map")

if __name__ == "__main__":
    sys.exit(main())
