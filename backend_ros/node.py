"""``lcpr_backend``: any odometry + the detector's verified loops in, a corrected trajectory out.

Subscribes nav_msgs/Odometry (``odom_topic``), the detector's ``~/candidates``
(``candidates_topic``; rows with verified = 1, read by the column names of
:mod:`ros_common.tables`), its ``~/sessions`` (``sessions_topic``: the names of the rows' session
codes) and its ``~/up`` (``up_topic``: each keyframe's up from its walls) and feeds
:class:`lcpr_core.backend.PoseGraphBackend` (GTSAM iSAM2). The odometry is this run's session
(``session``); a prior map (``prior_graph``) is loaded held at its estimates, and loops between the
two place this run in it (docs/nodes/lcpr_backend.md). Other robots' odometry (``peers``: each
namespace's odometry topic) goes in as one session per robot (``peer_sessions``), placed by the
inter-robot loops; a peer's odometry that comes before this run's first waits for it, so that this
run's frame, not a peer's, becomes the map of a new graph.
Publishes ``~/odometry`` (every odometry message, corrected: ``map_T_odom @ odom_T_base``) and
``~/path`` (this session's graph nodes), in the map frame once the session is placed in the map and in
its own odometry frame before; map -> odom on /tf (geometry_msgs/TransformStamped on ``~/map_to_odom``
where tf2_msgs is not installed) only once it is placed; ``~/localized`` (std_msgs/Bool, latched:
whether it is), /diagnostics; service ``~/save_graph``.

Threads: the callbacks only check messages, publish the corrected odometry with the newest
correction and queue the work; one worker thread applies odometry and loops to the graph in
arrival order (an optimisation never holds the callbacks up). A loop that arrives before the
odometry of its stamps (or an up before its odometry) waits (``pending_s`` of header time)
and is retried as odometry comes in (an end in a peer's session waits for that peer's odometry); a row
naming a session code before the ``~/sessions`` table that names it waits as well (``pending_s`` of
odometry header time).
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
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
from std_msgs.msg import Bool, Float64MultiArray, String
from std_srvs.srv import Trigger

from lcpr_core.backend import BackendConfig, BackendStats, PoseGraphBackend
from lcpr_core.errors import BackendError, MapError
from msg_tools.build import build_message
from msg_tools.geometry import pose_to_parts
from msg_tools.transforms import transforms_message
from ros_common.diagnostics import HARDWARE_ID
from ros_common.errors import ConfigError, InputRejected, MapLoadError
from ros_common.inputs import odometry_pose
from ros_common.mapstore import answer_save_request, load_map_file, save_under_lock
from ros_common.process import finish_and_save, node_parser, run_node
from ros_common.qos import CANDIDATE_QOS, LATCHED_QOS, QOS_ADAPTED, SensorSubscription
from ros_common.ros_params import declare
from ros_common.stamps import NS_PER_S, StampOrder, stamp_ns
from ros_common.static_tf import tf_message_type
from ros_common.stats import NodeStats
from ros_common.tables import SESSION_COLUMNS, parse_candidates, parse_sessions, row_covariance, row_pose
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
CANDIDATES_BAD_SESSION = "candidates: bad session code"
SESSIONS_BAD = "sessions: bad table"
LOOP_EXPIRED = "loop: its odometry never came"
LOOP_NO_TABLE = "loop: its session names never came"
UP_EXPIRED = "up: its odometry never came"
PEER_EARLY = "peer odometry: dropped waiting for this run's first odometry"


@dataclass(frozen=True)
class _Odom:
    stamp: float
    pose: np.ndarray  # odom_T_base
    session: str | None = None  # a peer's session; None: this run's


@dataclass(frozen=True)
class _Up:
    stamp: float
    up: np.ndarray  # (3,) in the LiDAR frame
    expired: ClassVar[str] = UP_EXPIRED  # the drop reason when its odometry never comes

    def newest(self, session: str) -> float:
        """The newest stamp of ``session`` it needs odometry for (ups are always this run's)."""
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
    codes: tuple[int | None, int | None] = (None, None)  # the row's session codes; None: this run's session
    sessions: tuple[str, str] | None = None  # (query, match) names, once the codes are looked up
    since: float = -np.inf  # the newest odometry stamp when it began to wait for the session names
    expired: ClassVar[str] = LOOP_EXPIRED  # the drop reason when its odometry never comes

    def newest(self, session: str) -> float:
        """The newest stamp of ``session`` among its ends (-inf: none; another session's odometry is never
        waited for: its graph holds all it will get)."""
        ends = [t for t, name in zip((self.query_stamp, self.match_stamp), self.sessions or (session, session),
                                     strict=True) if name == session]
        return max(ends, default=-np.inf)

    @property
    def what(self) -> str:
        if self.sessions is None:
            return f"loop {self.query_stamp!r} -> {self.match_stamp!r} (session codes {self.codes})"
        return (f"loop {self.query_stamp!r} ({self.sessions[0]}) -> {self.match_stamp!r} "
                f"({self.sessions[1]})")


@dataclass(frozen=True)
class _Sessions:
    names: tuple[str, ...]  # the detector's session table: code = index


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
        self.backend, self._graph_source = _start_graph(cfg)
        self._stats: BackendStats = self.backend.stats()
        self._session_names: tuple[str, ...] | None = None  # the detector's ~/sessions table, once it came
        self._graph_sessions = tuple(self.backend.sessions)
        self._localized = self._is_localized()
        self._map_T_odom = self._correction()
        self._frames = (cfg.odom_frame, cfg.base_frame)  # filled from the first odometry message when empty
        self._order = StampOrder()
        self._pending: list[_Loop | _Up] = []
        self._newest_odom = -np.inf
        self._peers = cfg.peer_odometry()  # (session, odometry topic) of each peer robot
        self._newest: dict[str, float] = {name: -np.inf for name in (cfg.session, *(n for n, _ in self._peers))}
        self._early: list[_Odom] = []  # peers' odometry that came before this run's first (see _add_odometry)
        self._peers_anchored: tuple[str, ...] = ()
        self._path_sent = 0.0
        self._path_nodes = -1
        self._path_due = False
        self._reported_refused = 0

        self._odom_pub = self.create_publisher(Odometry, "~/odometry", 10)
        self._path_pub = self.create_publisher(PathMsg, "~/path", CANDIDATE_QOS)
        self._localized_pub = self.create_publisher(Bool, "~/localized", LATCHED_QOS)
        self._localized_pub.publish(Bool(data=self._localized))
        if TFMessage is not None:
            self._tf_pub = self.create_publisher(TFMessage, "/tf", 100)
        else:
            self._tf_pub = self.create_publisher(TransformStamped, "~/map_to_odom", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._odom_sub = SensorSubscription(self, Odometry, cfg.odom_topic, self._on_odom, cfg.input_qos,
                                            warn=lambda text: self.warnings(QOS_ADAPTED, text))
        self._peer_subs = [
            SensorSubscription(self, Odometry, topic, partial(self._on_peer_odom, name, topic, StampOrder()),
                               cfg.input_qos, warn=lambda text: self.warnings(QOS_ADAPTED, text))
            for name, topic in self._peers]
        self.create_subscription(Float64MultiArray, cfg.candidates_topic, self._on_candidates, CANDIDATE_QOS)
        if cfg.sessions_topic:
            self.create_subscription(String, cfg.sessions_topic, self._on_sessions, LATCHED_QOS)
        if cfg.up_topic:
            self.create_subscription(Vector3Stamped, cfg.up_topic, self._on_up, CANDIDATE_QOS)
        self.create_service(Trigger, "~/save_graph", self._on_save_graph)
        self.create_timer(cfg.diagnostics.period, self._publish_diagnostics)

        self.worker: Worker[_Odom | _Loop | _Up | _Sessions] = Worker(
            self._process, max_waiting=MAX_WAITING, name="backend-worker", on_dropped=self._on_dropped,
            on_error=self._on_failed)
        self.worker.start()
        ups = f", ups from {cfg.up_topic}" if cfg.up_topic else ""
        ups += "".join(f", session {name!r} from {topic}" for name, topic in self._peers)
        place = "localized" if self._localized else "not localized until inter-session loops place it"
        log.info(f"ready: odometry {cfg.odom_topic} as session {cfg.session!r} ({place}), loops from "
                 f"{cfg.candidates_topic}{ups}; {self._graph_source}; "
                 f"map -> odom on {'/tf' if TFMessage is not None else '~/map_to_odom'}")

    # -- inputs (callback thread) -------------------------------------------------------------
    def _reject(self, err: InputRejected) -> None:
        self.drops.add(err.reason)
        self.warnings(err.reason, err.detail)

    def _odometry_in(self, msg: Odometry, topic: str, order: StampOrder, where: str) -> tuple[int, np.ndarray] | None:
        """(stamp ns, odom_T_base) of an odometry message on ``topic`` (counted), or None with the refusal counted:
        a pose that is not one, or a stamp out of ``order`` (``where`` names it in the warning)."""
        self.rates.tick(topic)
        ns = stamp_ns(msg.header)
        try:
            pose = odometry_pose(msg)
        except InputRejected as err:
            self._reject(err)
            return None
        refused = order.check(ns)
        if refused is not None:
            self._reject(InputRejected(f"odometry: {refused}", f"{where}stamp {ns / NS_PER_S:.9f}"))
            return None
        return ns, pose

    def _on_odom(self, msg: Odometry) -> None:
        taken = self._odometry_in(msg, self.settings.odom_topic, self._order, "")
        if taken is None:
            return
        ns, pose = taken
        if not self._frames[0] or not self._frames[1]:
            self._frames = (self._frames[0] or msg.header.frame_id or "odom",
                            self._frames[1] or msg.child_frame_id or "base_link")
        correction = self._map_T_odom  # the worker swaps in a new array; this one stays whole
        placed = self._localized  # not placed in the map yet: corrected within its own odometry frame
        out = build_message("nav_msgs/msg/Odometry", {
            "header": {"stamp": {"sec": msg.header.stamp.sec, "nanosec": msg.header.stamp.nanosec},
                       "frame_id": self.settings.map_frame if placed else self._frames[0]},
            "child_frame_id": self._frames[1]}, msg_type=Odometry)
        _set_pose(out.pose.pose, correction @ pose)
        out.pose.covariance = msg.pose.covariance
        out.twist = msg.twist  # in the child frame: the correction does not change it
        self._odom_pub.publish(out)
        if placed:
            self._publish_tf(msg.header.stamp, correction)
        self.worker.submit(_Odom(ns / NS_PER_S, pose))

    def _on_peer_odom(self, session: str, topic: str, order: StampOrder, msg: Odometry) -> None:
        """A peer robot's odometry: checked as this run's is, queued as its session (nothing is published)."""
        taken = self._odometry_in(msg, topic, order, f"{topic} ")
        if taken is not None:
            self.worker.submit(_Odom(taken[0] / NS_PER_S, taken[1], session))

    def _parsed(self, msg: Any, topic: str, parse: Any, reason: str) -> Any:
        """``parse(msg)`` of a message on ``topic`` (counted), or None with the refusal counted under ``reason``."""
        self.rates.tick(topic)
        try:
            return parse(msg)
        except ValueError as err:
            self._reject(InputRejected(reason, str(err)))
            return None

    def _on_candidates(self, msg: Float64MultiArray) -> None:
        rows = self._parsed(msg, self.settings.candidates_topic, parse_candidates, CANDIDATES_BAD)
        for row in rows or ():
            if row.get("verified", 0.0) != 1.0:
                continue
            rel = row_pose(row)
            if rel is None:
                self._reject(InputRejected(CANDIDATES_NO_POSE, f"query {row.get('query_stamp')!r}, match "
                                                               f"{row.get('match_stamp')!r}: tx..qw are not finite"))
                continue
            try:
                codes = _session_codes(row)
            except ValueError as err:
                self._reject(InputRejected(CANDIDATES_BAD_SESSION, f"query {row.get('query_stamp')!r}, match "
                                                                   f"{row.get('match_stamp')!r}: {err}"))
                continue
            self.worker.submit(_Loop(float(row["query_stamp"]), float(row["match_stamp"]), rel, row_covariance(row),
                                     codes))

    def _on_sessions(self, msg: String) -> None:
        names = self._parsed(msg, self.settings.sessions_topic, parse_sessions, SESSIONS_BAD)
        if names is not None:
            self.worker.submit(_Sessions(tuple(names)))

    def _on_up(self, msg: Vector3Stamped) -> None:
        self.rates.tick(self.settings.up_topic)
        v = msg.vector
        self.worker.submit(_Up(stamp_ns(msg.header) / NS_PER_S, np.array([v.x, v.y, v.z], np.float64)))

    # -- worker thread ------------------------------------------------------------------------
    def _process(self, item: _Odom | _Loop | _Up | _Sessions) -> None:
        with self._lock:
            if isinstance(item, _Odom):
                self._add_odometry(item)
            elif isinstance(item, _Sessions):
                self._session_names = item.names
                self._retry_pending()
            else:
                self._add_stamped(item)
            self._stats = self.backend.stats()
            self._graph_sessions = tuple(self.backend.sessions)
            localized = self._is_localized()
            self._map_T_odom = self._correction()
            anchored = tuple(name for name, _ in self._peers
                             if name in self.backend.sessions and self.backend.anchored(name))
        for name in sorted(set(anchored) ^ set(self._peers_anchored)):
            self.get_logger().info(f"peer session {name!r} "
                                   f"{'placed in the map' if name in anchored else 'no longer placed in the map'}")
        self._peers_anchored = anchored
        if localized != self._localized:
            self._localized = localized
            self._localized_pub.publish(Bool(data=localized))
            self._path_due = localized
            self.get_logger().info(f"session {self.settings.session!r} "
                                   f"{'placed in the map' if localized else 'no longer placed in the map'}")
        self._maybe_publish_path()

    def _is_localized(self) -> bool:
        """Whether this run's session is placed in the map frame (a graph without sessions: it will be the map)."""
        name = self.settings.session
        if name in self.backend.sessions:
            return self.backend.anchored(name)
        return not self.backend.sessions

    def _correction(self) -> np.ndarray:
        """This run's session's correction: map_T_odom once it is placed in the map, its correction within its
        own odometry frame before (its poses are then published in that frame)."""
        name = self.settings.session
        return self.backend.correction(name) if name in self.backend.sessions else np.eye(4)

    def _add_odometry(self, item: _Odom) -> None:
        """Add one odometry message to its session's graph. A peer's that comes while the graph is still empty
        waits for this run's first (``MAX_WAITING`` at most): the first session of a graph is its map frame."""
        own = self.settings.session
        session = item.session or own
        if session != own and not self.backend.sessions:
            if len(self._early) >= MAX_WAITING:
                self.drops.add(PEER_EARLY)
                self.warnings(PEER_EARLY, f"{MAX_WAITING} messages of the peers' odometry waited for this run's "
                                          f"first on {self.settings.odom_topic}; the oldest was dropped")
                self._early.pop(0)
            self._early.append(item)
            return
        try:
            self.backend.add_odometry(item.stamp, item.pose, session=session)
        except BackendError as err:
            self._refused(err)
            return
        self._newest[session] = item.stamp
        if session == own:
            self._newest_odom = item.stamp
        if self._early and self.backend.sessions:
            early, self._early = self._early, []
            for waited in early:
                self._add_odometry(waited)
        self._retry_pending()

    def _retry_pending(self) -> None:
        waiting, self._pending = self._pending, []
        for stamped in waiting:
            self._add_stamped(stamped)

    def _names(self, codes: tuple[int | None, int | None]) -> tuple[str, str] | None:
        """The session names of a row's codes (None: this run's); None while the table does not hold them."""
        own, table = self.settings.session, self._session_names or ()
        if any(c is not None and c >= len(table) for c in codes):
            return None
        query, match = (own if c is None else table[c] for c in codes)
        return query, match

    def _wait_for_names(self, item: _Loop) -> None:
        """Keep a loop whose session codes the table does not name yet, ``pending_s`` of odometry time at most."""
        since = self._newest_odom if item.since == -np.inf else item.since
        waited = self._newest_odom - since
        if waited > self.settings.pending_s or len(self._pending) >= MAX_WAITING:
            known = "no table yet" if self._session_names is None else f"table {list(self._session_names)}"
            self.drops.add(LOOP_NO_TABLE)
            self.warnings(LOOP_NO_TABLE, f"{item.what}: {known} from {self.settings.sessions_topic or '(none)'} "
                                         f"after {waited:.3f} s of odometry (pending_s = {self.settings.pending_s} s)")
            return
        self._pending.append(replace(item, since=since))

    def _add_stamped(self, item: _Loop | _Up) -> None:
        """Add a loop or an up, or keep it until the odometry reaches its stamps (``pending_s`` ahead at most)
        and, for a loop, until the session table names its codes."""
        if isinstance(item, _Loop) and item.sessions is None:
            names = self._names(item.codes)
            if names is None:
                self._wait_for_names(item)
                return
            item = replace(item, sessions=names)
        # the end furthest ahead of its own session's odometry (an end in a held or unknown session waits for none)
        ahead, newest = max(((item.newest(name) - t, t) for name, t in self._newest.items()
                             if (isinstance(item, _Loop) or name == self.settings.session)
                             and item.newest(name) > -np.inf), default=(-np.inf, 0.0))
        if ahead > self.settings.loops.stamp_tolerance:
            if ahead <= self.settings.pending_s or newest == -np.inf:
                if len(self._pending) < MAX_WAITING:
                    self._pending.append(item)
                    return
            self.drops.add(item.expired)
            self.warnings(item.expired, f"{item.what} is {ahead:.3f} s ahead of the newest odometry "
                                             f"(pending_s = {self.settings.pending_s} s)")
            return
        try:
            if isinstance(item, _Up):
                self.backend.add_up(item.stamp, item.up, session=self.settings.session)
                return
            query, match = item.sessions or (self.settings.session, self.settings.session)
            tic = time.perf_counter()
            accepted = self.backend.add_loop(item.query_stamp, item.match_stamp, item.match_T_query, item.covariance,
                                             query_session=query, match_session=match)
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
        nodes = self._stats.nodes
        self._path_due, self._path_sent, self._path_nodes = False, now, nodes
        frame = self.settings.map_frame if self._localized else self._frames[0]  # its own until placed
        with self._lock:
            stamps, poses = self.backend.nodes(self.settings.session)
        if not len(stamps) or not frame:
            return
        msg = PathMsg()
        msg.header.frame_id = frame
        msg.header.stamp = _stamp_msg(float(stamps[-1]))
        for t, pose in zip(stamps, poses, strict=True):
            item = PoseStamped()
            item.header.frame_id = frame
            item.header.stamp = _stamp_msg(float(t))
            _set_pose(item.pose, pose)
            msg.poses.append(item)
        self._path_pub.publish(msg)

    def _on_dropped(self, item: _Odom | _Loop | _Up | _Sessions) -> None:
        self.drops.add(BUSY)
        self.warnings(BUSY, f"more than {MAX_WAITING} items waited for the graph; the oldest was dropped")

    def _on_failed(self, item: _Odom | _Loop | _Up | _Sessions, err: Exception) -> None:
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
        pending = list(self._pending)
        for_names = sum(1 for item in pending if isinstance(item, _Loop) and item.sessions is None)
        values = {
            "session": self.settings.session, "localized": str(self._localized).lower(),
            **({"peer sessions anchored": ", ".join(self._peers_anchored) or "none yet",
                "peer sessions not anchored": ", ".join(n for n, _ in self._peers if n not in self._peers_anchored)
                or "none"} if self._peers else {}),
            "sessions in graph": ", ".join(self._graph_sessions) or "none yet", "graph from": self._graph_source,
            "odometry messages": stats.odometry, "graph nodes": stats.nodes,
            "loops accepted": stats.loops_accepted, "loops rejected": stats.loops_rejected,
            "loops skipped as redundant": stats.loops_redundant,
            "ups taken": stats.ups,
            "loops waiting for odometry": len(pending) - for_names,
            "loops waiting for session names": for_names,
            **{f"inter-session {what}": n for what, n in sorted(stats.inter_session.items())},
            "last anchoring (ms)": "n/a" if stats.last_anchor_s is None else f"{stats.last_anchor_s * 1e3:.1f}",
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
            f"{stats.nodes} nodes, {stats.loops_accepted} loops"
            + ("" if self._localized else f"; session {self.settings.session!r} not placed in the map yet"),
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


def _start_graph(cfg: BackendNodeConfig) -> tuple[PoseGraphBackend, str]:
    """The graph the node starts with and where it came from: ``graph.path``'s file when it exists (the
    continuation: it already holds any prior), else ``prior_graph`` held at its estimates, else a new one.
    MapLoadError for a file that cannot be used, ConfigError for a prior that holds this run's session."""
    config = cfg.backend()

    def load(path: Path) -> PoseGraphBackend:
        try:
            return PoseGraphBackend.load(path, config)
        except BackendError as err:
            raise MapError(str(err)) from err

    try:
        backend = load_map_file(cfg.graph.path, load)
        if backend is not None:
            source = f"continuing {cfg.graph.path}"
            if cfg.prior_graph:
                source += f" (prior_graph {cfg.prior_graph} not read: graph.path holds it)"
        elif cfg.prior_graph:
            backend = _load_prior(Path(cfg.prior_graph), config)
            source = f"prior map {cfg.prior_graph}" + (f", saved to {cfg.graph.path}" if cfg.graph.path else "")
        else:
            backend, source = PoseGraphBackend(config), "a new graph"
    except BackendError as err:  # gtsam missing
        raise ConfigError(str(err)) from err
    if cfg.prior_map:
        _check_prior_map(backend, Path(cfg.prior_map))
    held = backend.held()
    if cfg.session in held:
        where = f"prior_graph {cfg.prior_graph}" if source.startswith("prior") else f"graph.path {cfg.graph.path}"
        raise ConfigError(f"session={cfg.session!r} is a session of the prior map in {where} (its held sessions: "
                          f"{', '.join(repr(n) for n in held)}); this run needs a session name of its own: set "
                          "session (and the detector's session) to a new name")
    return backend, f"{source}, {len(backend.sessions)} sessions, {backend.stats().nodes} nodes"


def _check_prior_map(backend: PoseGraphBackend, file: Path) -> None:
    """``prior_map``: the graph must be the one saved beside that descriptor map (MapLoadError otherwise: the
    node refuses to start, naming both)."""
    from lcpr_core.descriptor_map import DescriptorMap

    try:
        sources, stamps = DescriptorMap.keyframe_sessions(file)
        backend.check_map(sources, stamps, where=f"prior_map {file}")
    except (MapError, BackendError, OSError) as err:
        raise MapLoadError(f"refusing to start: {err}; give the map file the prior graph was saved beside, or "
                           "leave prior_map empty") from err


def _load_prior(file: Path, config: BackendConfig) -> PoseGraphBackend:
    """``prior_graph``: a saved graph held at its estimates; MapLoadError naming the file when it cannot be used
    (the node refuses to start, as for graph.path)."""
    if not file.is_file():
        state = "is not a file" if file.exists() else "does not exist"
        raise MapLoadError(f"prior_graph {file} {state}; give a graph file saved by lcpr_backend (graph.path, "
                           "~/save_graph) or PoseGraphBackend.save, or leave prior_graph empty")
    try:
        return PoseGraphBackend.load(file, config, hold=True)
    except BackendError as err:
        if err.reason == "no gtsam":
            raise
        raise MapLoadError(f"refusing to start: prior_graph {file} cannot be used: {err}. Point prior_graph at a "
                           "graph saved by lcpr_backend, or leave it empty") from err


def _session_codes(row: dict[str, float]) -> tuple[int | None, int | None]:
    """A row's (query, match) session codes: None where the column is absent (a detector without sessions) or
    NaN (it kept no table), both meaning this run's session; ValueError for a code that is no index."""
    def code(column: str) -> int | None:
        value = row.get(column, math.nan)
        if math.isnan(value):
            return None
        if not math.isfinite(value) or value != int(value) or value < 0:
            raise ValueError(f"{column}={value!r}; expected an index into the ~/sessions table (0, 1, ...) or NaN")
        return int(value)
    return code(SESSION_COLUMNS[0]), code(SESSION_COLUMNS[1])


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
