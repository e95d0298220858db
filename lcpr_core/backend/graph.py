"""The pose graph: :class:`PoseGraphBackend`, GTSAM iSAM2 fed online with odometry, loops and measured ups.

One ``Pose3`` per graph node (a keyframe of the odometry); every odometry message is kept, so any stamp can
be corrected. Stamps are seconds, poses 4 x 4 ``world_T_base``, covariances 6 x 6 in the ROS order of
:mod:`lcpr_core.posegraph`. How nodes, factors, the check and ``pose(t)`` are built: docs/backend.md,
*How the graph is built*.

Sessions (docs/sessions.md): a graph holds several runs, each with its own odometry frame (:mod:`.session`).
The first one, or a loaded graph's, defines the map frame; a later one is placed in it by inter-session loops
that agree with one another (:mod:`.anchoring`, :class:`~.config.SessionPolicy`) and until then lives in its
own frame. Calls without ``session=`` use the session ``"session"`` (the detector's default name), so one-session code
reads as before.
"""
from __future__ import annotations

import math
import os
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import BackendError, PoseGraphError
from ..geometry import interpolate_poses, invert, nearest_rotation, skew, so3_exp, unit_vector
from ..growable import GrowableArray
from ..loop_report import covariance_lidar_to_body
from ..posegraph import check_covariances, check_poses, lidar_to_body, to_gtsam_covariance
from .config import BackendConfig, is_real, rotation_angle, show
from .consistency import mahalanobis_squared, path_covariances, to_world
from .graph_file import SavedGraph, SavedSession, read_graph_file, write_graph_file
from .placing import INTER_ACCEPTED, INTER_UNPLACED, INTER_WAITING, SessionPlacing
from .session import DEFAULT_SESSION, LOOP_UNKNOWN, MAX_SESSION_NAME, Loop, Session

__all__ = ["DEFAULT_SESSION", "BackendStats", "PoseGraphBackend", "compose_covariance"]

_LINEAR_M, _LINEAR_RAD = 0.02, math.radians(0.1)  # a loop that moved its node less was solved in one update
_CONVERGED_M, _CONVERGED_RAD = 1e-3, math.radians(0.01)  # an extra iSAM2 update that moves less: stop
_UP_CHAR = "u"  # Symbol character of the world's up variable (graph nodes are plain integers: character '\0')

# reasons a refusal is counted under (BackendError.reason)
ODOM_ORDER = "odometry out of order"
ODOM_POSE = "odometry bad pose"
BAD_STAMP = "bad stamp"
BAD_SESSION = "bad session"
LOOP_POSE = "loop bad pose"
LOOP_COVARIANCE = "loop bad covariance"
LOOP_SAME_NODE = "loop within one node"
LOOP_SESSION = "loop session unknown"
PRIOR_MISMATCH = "prior of another map"
UP_VECTOR = "up bad vector"

@dataclass(frozen=True)
class BackendStats:
    """Counts and timings of a back end (what /diagnostics reports)."""

    odometry: int  # odometry messages taken
    nodes: int  # graph nodes
    loops_accepted: int
    loops_rejected: int  # failed the consistency check
    refused: dict[str, int]  # inputs refused (BackendError), by reason
    last_loop_s: float | None  # seconds the last accepted loop took (check + iSAM2 updates)
    last_chi2: float | None  # the consistency statistic of the last loop checked
    loops_redundant: int = 0  # skipped: both ends within loops.min_spacing_m of an accepted loop's
    ups: int = 0  # measured up directions taken (add_up), the warm-up's included
    inter_session: dict[str, int] = field(default_factory=dict)  # inter-session loops by outcome, anchors
    last_anchor_s: float | None = None  # seconds the last anchoring took (the graph rebuilt and solved)


# ============================================================================ the back end
class PoseGraphBackend(SessionPlacing):
    """An iSAM2 pose graph fed online with odometry and loop closures, of one session or several
    (docs/backend.md: how it is built; docs/sessions.md: sessions)."""

    def __init__(self, config: BackendConfig | None = None) -> None:
        if config is None:
            config = BackendConfig()
        if not isinstance(config, BackendConfig):
            raise BackendError(f"config={config!r}; expected a BackendConfig", reason="bad option")
        self.config = config
        self._gtsam = _import_gtsam()
        self._threshold = config.loops.threshold()
        self._agree = config.sessions.threshold()
        self._sessions: dict[str, Session] = {}
        self._key_session: list[Session] = []  # session of each graph key
        self._key_local: list[int] = []  # node index within it
        self._loops: list[Loop] = []
        self._loop_ends = GrowableArray(np.int64, (2,))  # (parent, child) keys of each accepted loop
        self._loop_world_cov = GrowableArray(np.float64, (6, 6))  # their world_cov, stacked for the path search
        self._unplaced: list[tuple[Loop, np.ndarray]] = []  # inter-session loops with neither end placed (+ cov)
        self._rejected = 0
        self._redundant = 0
        self._refused: Counter[str] = Counter()
        self._inter: Counter[str] = Counter()
        self._last_loop_s: float | None = None
        self._last_anchor_s: float | None = None
        self._last_chi2: float | None = None
        self._estimates: np.ndarray | None = None  # (keys, 4, 4) cache, None when stale
        self._qr = config.factorization == "qr"
        self._isam = self._new_isam()
        self._up_world: np.ndarray | None = None  # the world's up in the map frame, once warmed up
        self._up_key = int(self._gtsam.symbol(_UP_CHAR, 0))  # the world's up as a variable (up_world_sigma_deg)
        self._ups: list[tuple[float, int, np.ndarray]] = []  # (stamp, key, up in that node's base frame)
        self._held = np.zeros((0, 4, 4))  # (keys, 4, 4) where a held prior's nodes are held (load(hold=True))

    # -- sessions ------------------------------------------------------------------------------
    @property
    def sessions(self) -> list[str]:
        """The sessions' names, in the order they came."""
        return list(self._sessions)

    def held(self) -> list[str]:
        """The sessions held as a prior map (:meth:`load` with ``hold=True``): closed to odometry."""
        return [name for name, s in self._sessions.items() if s.held]

    def anchored(self, session: str | None = None) -> bool:
        """Whether ``session`` is placed in the map frame (the first session and a loaded graph's always are)."""
        return self._known(session, "session").anchored

    def map_T_odom(self, session: str | None = None) -> np.ndarray | None:
        """4 x 4 correction of ``session``'s newest node: ``map_T_base = map_T_odom @ odom_T_base``; None while
        the session is not anchored (the default session of an empty graph: the identity)."""
        name = DEFAULT_SESSION if session is None else session
        if name not in self._sessions and session is None:
            return np.eye(4)
        s = self._known(session, "session")
        if not s.anchored:
            return None
        return self.correction(s.name)

    def correction(self, session: str | None = None) -> np.ndarray:
        """4 x 4 correction of ``session``'s newest node, ``estimate @ odometry^-1``: ``map_T_odom`` once it is
        anchored, its drift correction within its own frame before (what its poses are published in)."""
        s = self._known(session, "session")
        if not s.node_index:
            return np.eye(4)
        return s.newest @ invert(s.node_odom(len(s.node_index) - 1))

    def check_map(self, sources: list[str], stamps: np.ndarray, *, where: str = "the descriptor map") -> None:
        """Refuse (BackendError, reason ``"prior of another map"``) a descriptor map this graph was not made with:
        ``sources``/``stamps`` are the map's keyframes' session names and stamps. Some of its sessions must be
        sessions of this graph, and each such keyframe's stamp must lie within its session's odometry (a
        peer's session the graph never had is allowed: its odometry went to another back end)."""
        stamps = np.asarray(stamps, np.float64)
        shared = sorted({name for name in sources if name in self._sessions})
        if len(sources) and not shared:
            raise BackendError(f"{where} holds sessions {sorted(set(sources))}, none of them a session of this graph "
                               f"({', '.join(self._sessions) or 'none'}): a graph of another map",
                               reason=PRIOR_MISMATCH)
        tol = self.config.loops.stamp_tolerance
        for name in shared:
            s = self._sessions[name]
            mine = stamps[np.array([src == name for src in sources], bool)]
            span = s.stamps.view()
            outside = mine[(mine < span[0] - tol) | (mine > span[-1] + tol)] if len(span) else mine
            if len(outside):
                raise BackendError(f"{where}: {len(outside)} keyframes of session {name!r} (first at stamp "
                                   f"{float(outside[0])!r}) lie outside its odometry in this graph "
                                   f"({float(span[0]) if len(span) else None!r} to "
                                   f"{float(span[-1]) if len(span) else None!r}): a graph of another map",
                                   reason=PRIOR_MISMATCH)

    # -- inputs ------------------------------------------------------------------------------
    def add_odometry(self, stamp: float, world_T_base: np.ndarray, *, session: str | None = None) -> bool:
        """Take one odometry message of ``session``; True when it became a graph node. Stamps must increase within
        a session. A new name starts a session: the map frame's if the graph has none, else one to be placed."""
        t = self._stamp(stamp, "odometry stamp")
        name = self._session_name(session)
        s = self._sessions.get(name)
        if s is not None and len(s.stamps) and t <= s.stamps.view()[-1]:
            newest = float(s.stamps.view()[-1])
            word = "repeats" if t == newest else "is before"
            self._refuse(ODOM_ORDER, f"odometry stamp {t!r} {word} the newest odometry stamp {newest!r}"
                                     f"{s.suffix()}; expected stamps that increase (a replayed bag or a reset "
                                     "starts a new graph or a new session)")
        if s is not None and s.held:
            self._refuse(BAD_SESSION, f"session={name!r} is a prior map held at its estimates (loaded with "
                                      "hold=True / prior_graph); give this run a session name of its own")
        pose = self._pose(world_T_base, f"odometry world_T_base at stamp {t!r}", ODOM_POSE)
        if s is None:
            s = self._new_session(name)
        n = len(s.stamps)
        s.stamps.extend(np.array([t]))
        s.odom.extend(pose[None])
        if not s.node_index:
            self._add_first_node(s, n)
            return True
        step = invert(s.node_odom(-1)) @ pose
        if not self.config.keyframes.due(float(np.linalg.norm(step[:3, 3])), rotation_angle(step[:3, :3]),
                                         t - s.node_stamps[-1]):
            return False
        self._add_node(s, n)
        return True

    def add_loop(self, query_stamp: float, match_stamp: float, match_T_query: np.ndarray,
                 covariance: np.ndarray | None = None, *, query_session: str | None = None,
                 match_session: str | None = None) -> bool:
        """Add a verified loop closure; True when it entered the graph.

        ``match_T_query``: the query keyframe's LiDAR frame in the match keyframe's LiDAR frame;
        ``covariance``: its 6 x 6 (x, y, z, roll, pitch, yaw), None = ``loops.default_sigmas``.
        False: rejected by the consistency check, skipped as redundant, or (between sessions) kept waiting
        until it can place a session (``stats().inter_session``). Raises BackendError (the graph unchanged)
        for inputs that cannot be used, a session the graph does not know among them.
        """
        q = self._stamp(query_stamp, "query_stamp")
        m = self._stamp(match_stamp, "match_stamp")
        qs = self._loop_session(query_session, "query_session")
        ms = self._loop_session(match_session, "match_session")
        rel = self._pose(match_T_query, f"match_T_query of the loop {q!r} -> {m!r}", LOOP_POSE)
        if covariance is None:
            cov = self.config.loops.default_covariance()
        else:
            try:
                cov = check_covariances(covariance, f"covariance of the loop {q!r} -> {m!r}", single=True)
            except PoseGraphError as err:
                self._refuse(LOOP_COVARIANCE, f"{err} (got {show(covariance)})")
        child, odom_q = self._attach(qs, q, "query_stamp")
        parent, odom_m = self._attach(ms, m, "match_stamp")
        if child == parent:
            self._refuse(LOOP_SAME_NODE, f"query_stamp {q!r} and match_stamp {m!r} attach to the same graph node "
                                         f"(stamp {self._node_stamp(child)!r}); a loop needs two places")
        if self._is_redundant(parent, child):
            self._redundant += 1
            return False
        cov = cov * self.config.loops.covariance_scale
        tic = time.perf_counter()
        ext = self.config.base_T_lidar
        body = lidar_to_body(rel, ext)  # base(match)_T_base(query)
        body_cov = covariance_lidar_to_body(cov, rel, ext)
        before = invert(self._node_odom(parent)) @ odom_m  # node -> match stamp
        after = invert(odom_q) @ self._node_odom(child)  # query stamp -> node
        measured = before @ body @ after
        measured[:3, :3] = nearest_rotation(measured[:3, :3])
        measured_cov = compose_covariance(body_cov, before, body, after)
        gtsam_cov = to_gtsam_covariance(measured_cov, measured[:3, :3])
        loop = Loop(parent, child, measured, measured_cov, (q, m), math.nan, np.zeros((6, 6)), (qs.name, ms.name))
        if qs is not ms and not (qs.anchored and ms.anchored):
            return self._wait(loop, gtsam_cov)
        chi2 = self._chi2(parent, child, measured, gtsam_cov)
        self._last_chi2 = loop.chi2 = chi2
        if not chi2 <= self._threshold:
            self._rejected += 1
            if qs is not ms:
                self._contradict(loop, gtsam_cov)
            return False
        self._insert(loop, gtsam_cov)
        if qs is not ms:
            self._inter[INTER_ACCEPTED] += 1
        self._last_loop_s = time.perf_counter() - tic
        return True

    def add_up(self, stamp: float, up: np.ndarray, *, session: str | None = None) -> bool:
        """Take the up direction measured in the loops' LiDAR frame at ``stamp`` (:func:`lcpr_core.up.estimate_up`).

        The node nearest in time gets an attitude factor holding its up axis to the world's up (std dev
        ``up_sigma_deg``, Huber kernel). The world's up in the map frame is the mean of the map session's
        measurements within ``up_warmup_m`` of travel from its first node, carried by the odometry, so an
        odometry frame that is not level (a handheld start, a LIO's first IMU frame) is fine. A session not yet
        placed keeps its ups until it is. False when ``up_sigma_deg`` is 0 (ignored). Raises BackendError (the
        graph unchanged) for a vector that is not finite and non-zero or a stamp outside the odometry.
        """
        t = self._stamp(stamp, "up stamp")
        s = self._loop_session(session, "session")
        vec = unit_vector(up)
        if vec is None:
            self._refuse(UP_VECTOR, f"up at stamp {t!r} is {show(up)}; expected a finite non-zero 3-vector")
        if self.config.up_sigma_deg <= 0:
            return False
        key, odom_t = self._attach(s, t, "up stamp", tolerance=math.inf)  # a tilt carried a few s drifts little
        body_t = self.config.base_T_lidar[:3, :3] @ vec  # base frame at t
        body = self._node_odom(key)[:3, :3].T @ odom_t[:3, :3] @ body_t  # the node's base frame
        self._ups.append((t, key, body))
        world_up, warm_up_ends = self._up_world, self._up_world is None
        if world_up is None:
            warmup = self.config.up_warmup_m
            if not s.root or s.travel[self._key_local[key]] <= warmup:
                return True  # kept for the world's up; its factor comes when the warm-up ends
            warm = [(k, b) for _, k, b in self._ups
                    if self._key_session[k].root and self._travel(k) <= warmup] or [(key, body)]
            world = sum(self._node_odom(k)[:3, :3] @ b for k, b in warm)
            world_up = self._up_world = world / np.linalg.norm(world)
        if not s.anchored:
            return True  # its factor comes when the session is placed
        graph, values = self._gtsam.NonlinearFactorGraph(), self._gtsam.Values()
        if warm_up_ends:  # the variable (up_world_sigma_deg > 0) and every up kept so far
            self._add_world_up(graph, values, world_up)
        for _, k, b in self._ups if warm_up_ends else self._ups[-1:]:
            if self._key_session[k].anchored:
                self._add_up_factor(graph, k, b, world_up)
        self._update(graph, values)
        self._refresh()
        return True

    # -- outputs ---------------------------------------------------------------------------
    def pose(self, stamp: float, *, session: str | None = None) -> np.ndarray:
        """Corrected 4 x 4 world_T_base at ``stamp``, within the session's odometry span (``pose(t)`` in
        docs/backend.md); the map frame's once the session is anchored, its own before."""
        if not is_real(stamp) or not math.isfinite(float(stamp)):
            raise BackendError(f"stamp={stamp!r}; expected a finite number of seconds", reason=BAD_STAMP)
        t = float(stamp)
        s = self._sessions.get(self._session_name(session))
        if s is None or not s.node_index:
            raise BackendError(f"stamp={t!r}: the graph holds no odometry yet"
                               + ("" if s is None or session is None else s.suffix()), reason=LOOP_UNKNOWN)
        odom = s.odom_at(t, "stamp", self.config.loops.stamp_tolerance)  # a question: not counted as refused
        return self._corrections(s, np.array([t]))[0] @ odom

    def trajectory(self, session: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,), corrected poses (N, 4, 4)) of every odometry message of ``session`` taken (in the map
        frame once it is anchored, its own before)."""
        s = self._sessions.get(self._session_name(session))
        if s is None:
            if session is not None:
                self._known(session, "session")
            return np.zeros(0), np.zeros((0, 4, 4))
        stamps = s.stamps.view().copy()
        if not len(stamps):
            return stamps, np.zeros((0, 4, 4))
        return stamps, self._corrections(s, stamps) @ s.odom.view()

    def nodes(self, session: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (K,), estimates (K, 4, 4)) of the session's graph nodes (the keyframes of ``~/path``)."""
        s = self._sessions.get(self._session_name(session))
        if s is None:
            return np.zeros(0), np.zeros((0, 4, 4))
        return np.array(s.node_stamps), self._session_estimates(s).copy()

    def stats(self) -> BackendStats:
        sessions = self._sessions.values()
        inter = dict(self._inter)
        inter[INTER_WAITING] = sum(len(s.waiting) for s in sessions)
        inter[INTER_UNPLACED] = len(self._unplaced)
        return BackendStats(odometry=sum(len(s.stamps) for s in sessions), nodes=len(self._key_session),
                            loops_accepted=len(self._loops), loops_rejected=self._rejected,
                            refused=dict(self._refused), last_loop_s=self._last_loop_s, last_chi2=self._last_chi2,
                            loops_redundant=self._redundant, ups=len(self._ups), inter_session=inter,
                            last_anchor_s=self._last_anchor_s)

    @property
    def loops(self) -> list[tuple[float, float, float]]:
        """(query_stamp, match_stamp, chi2) of every accepted loop, in order."""
        return [(lp.stamps[0], lp.stamps[1], lp.chi2) for lp in self._loops]

    def session_loops(self) -> list[tuple[str, float, str, float]]:
        """(query_session, query_stamp, match_session, match_stamp) of every accepted loop, in order."""
        return [(lp.sessions[0], lp.stamps[0], lp.sessions[1], lp.stamps[1]) for lp in self._loops]

    # -- file ------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the graph as .npz (atomically; no pickled objects): sessions, odometry, nodes, factors,
        estimates, and the inter-session loops still waiting (taken up again by :meth:`load`)."""
        order = list(self._sessions.values())
        position = self._positions(order)
        est = self._node_estimates()
        keys = np.array([k for s in order for k in s.keys], np.int64)
        step = [np.concatenate([np.zeros((1, 6, 6)), s.step_cov.view()]) if s.keys else np.zeros((0, 6, 6))
                for s in order]
        pending = [w.loop for s in order for w in (*s.waiting, *s.contradicting)] + [lp for lp, _ in self._unplaced]
        write_graph_file(path, SavedGraph(
            base_T_lidar=np.array(self.config.base_T_lidar),
            stamps=_cat([s.stamps.view() for s in order], (0,)),
            odometry=_cat([s.odom.view() for s in order], (0, 4, 4)),
            node_index=np.array([i for s in order for i in s.node_index], np.int64),
            node_estimate=est[keys] if len(keys) else np.zeros((0, 4, 4)),
            step_covariance=_cat(step, (0, 6, 6)),
            loop_nodes=np.array([(position[lp.parent], position[lp.child]) for lp in self._loops],
                                np.int64).reshape(-1, 2),
            loop_measured=np.array([lp.measured for lp in self._loops], np.float64).reshape(-1, 4, 4),
            loop_covariance=np.array([lp.covariance for lp in self._loops], np.float64).reshape(-1, 6, 6),
            loop_stamps=np.array([lp.stamps for lp in self._loops], np.float64).reshape(-1, 2),
            loop_chi2=np.array([lp.chi2 for lp in self._loops], np.float64),
            up_stamps=np.array([u[0] for u in self._ups], np.float64),
            up_nodes=np.array([position[u[1]] for u in self._ups], np.int64),
            up_body=np.array([u[2] for u in self._ups], np.float64).reshape(-1, 3),
            up_world=np.full(3, np.nan) if self._up_world is None else self._up_world,
            rejected=self._rejected, redundant=self._redundant, refused=dict(self._refused),
            waiting_nodes=np.array([(position[lp.parent], position[lp.child]) for lp in pending],
                                   np.int64).reshape(-1, 2),
            waiting_measured=np.array([lp.measured for lp in pending], np.float64).reshape(-1, 4, 4),
            waiting_covariance=np.array([lp.covariance for lp in pending], np.float64).reshape(-1, 6, 6),
            waiting_stamps=np.array([lp.stamps for lp in pending], np.float64).reshape(-1, 2),
            sessions=[SavedSession(name=s.name, rows=len(s.stamps), nodes=len(s.keys), root=s.root,
                                   anchored=s.anchored, frame=s.frame, anchors=s.anchors, held=s.held)
                      for s in order],
            inter_session=dict(self._inter)))

    @classmethod
    def load(cls, path: str | os.PathLike[str], config: BackendConfig | None = None, *,
             hold: bool = False) -> PoseGraphBackend:
        """A back end holding the graph saved at ``path``; a new ``session=`` name is a new session to be placed
        in its map. ``hold``: a prior map, every node held at its saved estimate (``sessions.hold_sigma``) and
        its sessions closed to odometry; otherwise its sessions continue. BackendError names what is wrong
        with the file."""
        data = read_graph_file(path)
        backend = cls(config)
        backend._restore(SavedGraph.from_arrays(data, os.fspath(path), base_T_lidar=backend.config.base_T_lidar),
                         hold=hold)
        return backend

    # -- internals: sessions ------------------------------------------------------------------
    def _session_name(self, session: str | None) -> str:
        if session is None:
            return DEFAULT_SESSION
        if not isinstance(session, str) or not session or len(session) > MAX_SESSION_NAME:
            self._refuse(BAD_SESSION, f"session={session!r}; expected a non-empty name (str, at most "
                                      f"{MAX_SESSION_NAME} characters)")
        return session

    def _known(self, session: str | None, what: str) -> Session:
        """The session called ``session`` (None: the default one), or a BackendError naming those held."""
        name = self._session_name(session)
        s = self._sessions.get(name)
        if s is None:
            held = ", ".join(repr(n) for n in self._sessions) or "none yet"
            raise BackendError(f"{what}={name!r} is not a session of this graph (it holds {held})",
                               reason=LOOP_SESSION)
        return s

    def _loop_session(self, session: str | None, what: str) -> Session:
        """Like :meth:`_known`, the refusal counted (an input, not a question)."""
        try:
            return self._known(session, what)
        except BackendError as err:
            return self._refuse(err.reason, str(err))

    def _new_session(self, name: str) -> Session:
        first = not self._sessions
        s = Session(name=name, code=len(self._sessions), root=first, anchored=first)
        self._sessions[name] = s
        return s

    def _node_odom(self, key: int) -> np.ndarray:
        return self._key_session[key].node_odom(self._key_local[key])

    def _node_stamp(self, key: int) -> float:
        return self._key_session[key].node_stamps[self._key_local[key]]

    def _travel(self, key: int) -> float:
        return self._key_session[key].travel[self._key_local[key]]

    def _positions(self, order: list[Session]) -> np.ndarray:
        """(keys,) position of every graph key when ``order``'s sessions' nodes follow one another (-1: none)."""
        position = np.full(len(self._key_session), -1, np.int64)
        offset = 0
        for s in order:
            position[s.keys] = offset + np.arange(len(s.keys))
            offset += len(s.keys)
        return position

    # -- internals: graph ------------------------------------------------------------------
    def _new_isam(self) -> Any:
        gt, cfg = self._gtsam, self.config
        params = gt.ISAM2Params()
        # per tangent component (Pose3: rotation, then translation) of every key: our keys are plain integers,
        # whose Symbol character is '\0'
        limits = gt.ISAM2ThresholdMap()
        threshold = np.array([cfg.relinearize_threshold] * 3 + [cfg.relinearize_translation] * 3)
        for char in ("\0", _UP_CHAR):  # the nodes, and the world's up variable
            limits.insert((char, threshold))
        params.setRelinearizeThreshold(limits)
        params.setOptimizationParams(gt.ISAM2GaussNewtonParams(float(cfg.wildfire_threshold)))
        params.relinearizeSkip = 1
        params.enablePartialRelinearizationCheck = True  # check only the cliques an update touched
        # Cholesky is a quarter to a half faster per update than QR, but standing still while turning (a
        # handheld sensor, a robot turning in place) gives node steps known to a fraction of a millimetre in
        # position but only to tenths of a degree in rotation; after a few dozen such nodes Cholesky of the
        # normal equations declares the system indeterminate (docs/backend.md, "Optimiser"), while QR of the
        # Jacobian solves it: "auto" starts with Cholesky and moves to QR when that happens (_update)
        params.setFactorization("QR" if self._qr else "CHOLESKY")
        return self._gtsam.ISAM2(params)

    def _update(self, graph: Any = None, values: Any = None) -> None:
        """One iSAM2 update; under ``factorization: auto``, a Cholesky failure rebuilds the graph with QR."""
        try:
            if graph is None:
                self._isam.update()
            else:
                self._isam.update(graph, values)
        except RuntimeError as err:
            if self._qr or self.config.factorization != "auto" or "ndetermina" not in str(err):
                raise
            # the failed update had already taken its factors and values: rebuild from them with QR
            factors, theta = self._isam.getFactorsUnsafe(), self._isam.getLinearizationPoint()
            self._qr = True
            self._isam = self._new_isam()
            self._isam.update(factors, theta)

    def _new_key(self, s: Session, row: int) -> int:
        key = len(self._key_session)
        self._key_session.append(s)
        self._key_local.append(len(s.keys))
        s.keys.append(key)
        s.node_index.append(row)
        s.node_stamps.append(float(s.stamps.view()[row]))
        return key

    def _add_first_node(self, s: Session, row: int) -> None:
        """A session's first node, held by the gauge prior at its odometry (the map frame's session, or a session
        not yet placed, in its own frame)."""
        gt = self._gtsam
        pose = s.odom.view()[row]
        key = self._new_key(s, row)
        graph, values = gt.NonlinearFactorGraph(), gt.Values()
        graph.add(self._gauge(key, pose))
        values.insert(key, _pose3(gt, pose))
        self._add_level(graph, key, pose)
        self._update(graph, values)
        s.cum.extend(np.zeros((1, 6, 6)))
        s.travel.append(0.0)
        self._refresh()

    def _add_node(self, s: Session, row: int) -> None:
        gt = self._gtsam
        odom = s.odom.view()
        step = invert(s.node_odom(-1)) @ odom[row]
        step[:3, :3] = nearest_rotation(step[:3, :3])
        cov = self.config.odometry.covariance(step)
        gtsam_cov = to_gtsam_covariance(cov, step[:3, :3])
        previous = s.keys[-1]
        key = self._new_key(s, row)
        graph, values = gt.NonlinearFactorGraph(), gt.Values()
        graph.add(gt.BetweenFactorPose3(previous, key, _pose3(gt, step), gt.noiseModel.Gaussian.Covariance(gtsam_cov)))
        values.insert(key, _pose3(gt, s.newest @ step))
        self._add_level(graph, key, odom[row])
        self._update(graph, values)
        self._extend_chain(s, row, cov, gtsam_cov, step)
        self._refresh()

    def _extend_chain(self, s: Session, row: int, cov: np.ndarray, gtsam_cov: np.ndarray, step: np.ndarray) -> None:
        """A node step's covariance, its world-frame prefix sum and the travel."""
        s.step_cov.extend(cov[None])
        s.cum.extend((s.cum.view()[-1] + to_world(gtsam_cov, s.frame @ s.odom.view()[row]))[None])
        s.travel.append(s.travel[-1] + float(np.linalg.norm(step[:3, 3])))

    def _gauge(self, key: int, pose: np.ndarray) -> Any:
        gt = self._gtsam
        return gt.PriorFactorPose3(key, _pose3(gt, pose), gt.noiseModel.Isotropic.Sigma(6, self.config.prior_sigma))

    def _insert(self, loop: Loop, gtsam_cov: np.ndarray) -> None:
        """Add an accepted loop's factor and solve (a few updates while its node still moves)."""
        gt = self._gtsam
        graph = gt.NonlinearFactorGraph()
        graph.add(gt.BetweenFactorPose3(loop.parent, loop.child, _pose3(gt, loop.measured),
                                        self._loop_noise(gtsam_cov)))
        moved_from = self._isam.calculateEstimatePose3(loop.child).matrix()
        self._update(graph, gt.Values())
        self._converge(loop.child, moved_from)
        loop.world_cov = self._world_cov(loop.child, gtsam_cov)
        self._remember(loop)
        self._refresh()

    def _world_cov(self, child: int, gtsam_cov: np.ndarray) -> np.ndarray:
        """A loop's covariance moved into the map frame (through its query session's anchoring frame)."""
        return to_world(gtsam_cov, self._key_session[child].frame @ self._node_odom(child))

    def _converge(self, node: int, before: np.ndarray) -> None:
        """Extra iSAM2 updates (at most ``loops.iterations``) while ``node`` still moves 1 mm / 0.01 deg or more.

        An update is one Gauss-Newton step from the old linearisation point: a loop that moved ``node``
        (from ``before``) by less than 2 cm / 0.1 deg was solved in the linear regime and needs no more (an
        extra update would relinearise hundreds of nodes for sub-millimetre changes); one that moved the
        graph by metres needs a few.
        """
        limits = (_LINEAR_M, _LINEAR_RAD)
        for _ in range(self.config.loops.iterations):
            now = self._isam.calculateEstimatePose3(node).matrix()
            step = invert(before) @ now
            if np.linalg.norm(step[:3, 3]) < limits[0] and rotation_angle(step[:3, :3]) < limits[1]:
                return
            self._update()
            before, limits = now, (_CONVERGED_M, _CONVERGED_RAD)
    def _add_level(self, graph: Any, node: int, odometry: np.ndarray) -> None:
        """Attitude factors on ``node`` (odometry pose ``odometry``): its up axis to the world's up
        (``level_sigma_deg`` > 0) and its tilt to the odometry's (``gravity_sigma_deg`` > 0)."""
        gt = self._gtsam
        up = np.array([0.0, 0.0, 1.0])
        for sigma_deg, body_up in ((self.config.level_sigma_deg, up),
                                   (self.config.gravity_sigma_deg, odometry[:3, :3].T @ up)):
            if sigma_deg > 0:  # AttitudeFactorPose3: the node's rotation takes body_up (body frame) to up
                noise = gt.noiseModel.Isotropic.Sigma(2, math.radians(sigma_deg))
                graph.add(gt.AttitudeFactorPose3(node, gt.Unit3(up), noise, gt.Unit3(body_up)))

    def _add_world_up(self, graph: Any, values: Any, world_up: np.ndarray) -> None:
        """The world's up as a graph variable (a Pose3 whose z axis it is), held to ``world_up`` with
        ``up_world_sigma_deg`` in tilt and fixed in heading and position (which nothing observes)."""
        sigma = self.config.up_world_sigma_deg
        if sigma <= 0:
            return
        gt = self._gtsam
        pose = np.eye(4)
        pose[:3, :3] = _rotation_to(world_up)
        noise = gt.noiseModel.Diagonal.Sigmas(np.array([math.radians(sigma)] * 2 + [1e-4] * 4))
        values.insert(self._up_key, _pose3(gt, pose))
        graph.add(gt.PriorFactorPose3(self._up_key, _pose3(gt, pose), noise))

    def _add_up_factor(self, graph: Any, node: int, body_up: np.ndarray, world_up: np.ndarray) -> None:
        """The measured up of ``node`` (its base frame) held to the world's up (add_up): to ``world_up``, or with
        ``up_world_sigma_deg`` > 0 to the world's up variable, the error then being the x, y of the node's up in
        the variable's frame, ``R_u^T R_n b`` (0 when they agree)."""
        gt = self._gtsam
        noise = gt.noiseModel.Robust.Create(gt.noiseModel.mEstimator.Huber.Create(1.345),
                                            gt.noiseModel.Isotropic.Sigma(2, math.radians(self.config.up_sigma_deg)))
        if self.config.up_world_sigma_deg <= 0:
            graph.add(gt.AttitudeFactorPose3(node, gt.Unit3(world_up), noise, gt.Unit3(body_up)))
            return
        body = np.array(body_up, np.float64)

        def error(factor: Any, values: Any, jacobians: Any) -> np.ndarray:
            up_key, node_key = factor.keys()
            r_up = values.atPose3(up_key).rotation().matrix()
            r_node = values.atPose3(node_key).rotation().matrix()
            w = r_up.T @ r_node @ body
            if jacobians is not None:  # right perturbations, Pose3 tangent (rotation, translation)
                j_up, j_node = np.zeros((2, 6)), np.zeros((2, 6))
                j_up[:, :3] = skew(w)[:2]
                j_node[:, :3] = -(r_up.T @ r_node @ skew(body))[:2]
                jacobians[0], jacobians[1] = j_up, j_node
            return np.asarray(w[:2])

        graph.add(gt.CustomFactor(noise, [self._up_key, node], error))

    def _loop_noise(self, gtsam_cov: np.ndarray) -> Any:
        gt = self._gtsam
        noise = gt.noiseModel.Gaussian.Covariance(gtsam_cov)
        policy = self.config.loops
        make = {"huber": gt.noiseModel.mEstimator.Huber.Create,
                "cauchy": gt.noiseModel.mEstimator.Cauchy.Create}.get(policy.robust)
        return noise if make is None else gt.noiseModel.Robust.Create(make(policy.robust_param), noise)


    def _refresh(self) -> None:
        """After an iSAM2 update: each session's newest estimate now, the full one when asked for."""
        for s in self._sessions.values():
            if s.keys:
                s.newest = self._isam.calculateEstimatePose3(s.keys[-1]).matrix()
        self._estimates = None

    def _node_estimates(self) -> np.ndarray:
        """(keys, 4, 4) every node's estimate, by key."""
        if self._estimates is None:
            k = len(self._key_session)
            # a full back-substitution: the online reads (the newest node, the check's two ends) stop at
            # wildfire_threshold, the trajectory and the saved graph do not
            values = self._isam.calculateBestEstimate()
            self._estimates = np.stack([values.atPose3(i).matrix() for i in range(k)]) if k else np.zeros((0, 4, 4))
        return self._estimates

    def _session_estimates(self, s: Session) -> np.ndarray:
        return self._node_estimates()[s.keys] if s.keys else np.zeros((0, 4, 4))

    def _remember(self, loop: Loop) -> None:
        """Keep an accepted loop (and its ends and world covariance for the consistency check's path search)."""
        self._loops.append(loop)
        self._loop_ends.extend(np.array([[loop.parent, loop.child]], np.int64))
        self._loop_world_cov.extend(loop.world_cov[None])

    def _is_redundant(self, parent: int, child: int) -> bool:
        """Whether an accepted loop between the same sessions joins places within ``loops.min_spacing_m`` of
        travel of both ends."""
        spacing = self.config.loops.min_spacing_m
        if spacing <= 0 or not self._loops:
            return False
        sp, sc = self._key_session[parent], self._key_session[child]
        tp, tc = self._travel(parent), self._travel(child)
        return any(self._key_session[lp.parent] is sp and self._key_session[lp.child] is sc
                   and abs(self._travel(lp.parent) - tp) < spacing and abs(self._travel(lp.child) - tc) < spacing
                   for lp in self._loops)

    # -- internals: the consistency check ----------------------------------------------------
    def _chi2(self, parent: int, child: int, measured: np.ndarray, gtsam_cov: np.ndarray) -> float:
        """Squared Mahalanobis distance of the loop from the current estimate (:mod:`.consistency`)."""
        if math.isinf(self._threshold):
            return 0.0
        gt = self._gtsam
        a = self._isam.calculateEstimatePose3(parent)
        b = self._isam.calculateEstimatePose3(child)
        residual = gt.Pose3.Logmap(_pose3(gt, measured).between(a.between(b)))
        relative = self._relative_covariance(parent, child)
        if relative is None:
            return math.inf
        return mahalanobis_squared(residual, gtsam_cov, relative)

    def _relative_covariance(self, a: int, b: int) -> np.ndarray | None:
        """GTSAM-order covariance of ``X_a^-1 X_b`` (in b's tangent) along the least uncertain path."""
        return self._path_covariances(a, [b])[0]

    def _path_covariances(self, a: int, targets: list[int], *,
                          sessions: list[Session] | None = None) -> list[np.ndarray | None]:
        """:func:`.consistency.path_covariances` over the graph, or over ``sessions`` only (their nodes, and the
        accepted loops between them): keys in, covariances in each target's tangent (map frame) out."""
        order = list(self._sessions.values()) if sessions is None else sessions
        ends, world = self._loop_ends.view(), self._loop_world_cov.view()
        if len(order) == 1 and len(self._sessions) == 1:  # one session: keys are its node indices
            s = order[0]
            return path_covariances(a, np.array(targets), cumulative=s.cum.view(), loop_ends=ends,
                                    loop_world_cov=world, poses=np.stack([s.node_odom(k) for k in targets]))
        position = self._positions(order)
        if len(ends):
            keep = (position[ends] >= 0).all(axis=1)
            ends, world = position[ends[keep]], world[keep]
        cumulative = np.concatenate([s.cum.view() for s in order])  # each in the map frame already
        counts = np.cumsum([len(s.keys) for s in order])
        poses = np.stack([self._key_session[k].frame @ self._node_odom(k) for k in targets])
        return path_covariances(int(position[a]), position[targets], cumulative=cumulative, loop_ends=ends,
                                loop_world_cov=world, poses=poses, breaks=counts[:-1])

    def _rebuild(self, values: np.ndarray) -> None:
        """A fresh iSAM2 holding every session's chain, gauge priors (the map frame's session and those not
        placed), the accepted loops and the ups of placed sessions, started from ``values`` (keys, 4, 4)."""
        gt = self._gtsam
        self._unanchor_cut_off()
        self._isam = self._new_isam()
        graph, init = gt.NonlinearFactorGraph(), gt.Values()
        hold = gt.noiseModel.Isotropic.Sigma(6, self.config.sessions.hold_sigma)
        for s in self._sessions.values():
            for local, key in enumerate(s.keys):
                init.insert(key, _pose3(gt, values[key]))
                odom = s.node_odom(local)
                if local == 0:
                    if s.root:
                        graph.add(self._gauge(key, odom))
                    elif not s.anchored:  # held where it is: its own frame, or where an anchor it lost left it
                        graph.add(self._gauge(key, values[key]))
                else:
                    step = invert(s.node_odom(local - 1)) @ odom
                    step[:3, :3] = nearest_rotation(step[:3, :3])
                    cov = to_gtsam_covariance(s.step_cov.view()[local - 1], step[:3, :3])
                    graph.add(gt.BetweenFactorPose3(s.keys[local - 1], key, _pose3(gt, step),
                                                    gt.noiseModel.Gaussian.Covariance(cov)))
                self._add_level(graph, key, odom)
                if s.held:
                    graph.add(gt.PriorFactorPose3(key, _pose3(gt, self._held[key]), hold))
        for lp in self._loops:
            cov = to_gtsam_covariance(lp.covariance, lp.measured[:3, :3])
            graph.add(gt.BetweenFactorPose3(lp.parent, lp.child, _pose3(gt, lp.measured), self._loop_noise(cov)))
        if self._up_world is not None and self.config.up_sigma_deg > 0:
            self._add_world_up(graph, init, self._up_world)
            for _, key, body in self._ups:
                if self._key_session[key].anchored:
                    self._add_up_factor(graph, key, body, self._up_world)
        self._update(graph, init)
        for _ in range(max(self.config.loops.iterations, 1)):
            self._update()
        self._refresh()

    def _rebuild_chain(self, s: Session) -> None:
        """``s``'s prefix sums of step covariances again, in the map frame through its new anchoring frame."""
        steps, travel = s.step_cov.view().copy(), s.travel
        s.cum, s.step_cov, s.travel = GrowableArray(np.float64, (6, 6)), GrowableArray(np.float64, (6, 6)), [0.0]
        s.cum.extend(np.zeros((1, 6, 6)))
        for local in range(1, len(s.keys)):
            step = invert(s.node_odom(local - 1)) @ s.node_odom(local)
            step[:3, :3] = nearest_rotation(step[:3, :3])
            cov = steps[local - 1]
            self._extend_chain(s, s.node_index[local], cov, to_gtsam_covariance(cov, step[:3, :3]), step)
        assert len(s.travel) == len(travel)

    def _rebuild_loop_covariances(self) -> None:
        """The accepted loops' map-frame covariances again (a session's anchoring frame changed)."""
        self._loop_ends = GrowableArray(np.int64, (2,))
        self._loop_world_cov = GrowableArray(np.float64, (6, 6))
        loops, self._loops = self._loops, []
        for lp in loops:
            lp.world_cov = self._world_cov(lp.child, to_gtsam_covariance(lp.covariance, lp.measured[:3, :3]))
            self._remember(lp)

    # -- internals: stamps and checks ------------------------------------------------------
    def _refuse(self, reason: str, message: str) -> Any:
        self._refused[reason] += 1
        raise BackendError(message, reason=reason)

    def _stamp(self, value: Any, name: str) -> float:
        if not is_real(value) or not math.isfinite(float(value)):
            self._refuse(BAD_STAMP, f"{name}={value!r}; expected a finite number of seconds")
        return float(value)

    def _pose(self, value: Any, name: str, reason: str) -> np.ndarray:
        try:
            pose = check_poses(value, name, single=True)
        except PoseGraphError as err:
            return self._refuse(reason, f"{err} (got {show(value)})")
        pose[:3, :3] = nearest_rotation(pose[:3, :3])
        return pose

    def _attach(self, s: Session, t: float, name: str, *, tolerance: float | None = None) -> tuple[int, np.ndarray]:
        """(graph key of ``s``'s node nearest to stamp ``t``, the odometry pose at ``t``) or a refusal naming the
        stamp. ``tolerance``: s the node may be from ``t`` (default ``loops.attach_tolerance``)."""
        if not s.node_index:
            self._refuse(LOOP_UNKNOWN, f"{name}={t!r}: the graph holds no odometry yet{s.suffix()}")
        try:
            odom = s.odom_at(t, name, self.config.loops.stamp_tolerance)
        except BackendError as err:
            return self._refuse(err.reason, str(err))
        node, gap = s.nearest_node(t)
        if gap > (self.config.loops.attach_tolerance if tolerance is None else tolerance):
            self._refuse(LOOP_UNKNOWN, f"{name}={t!r} is {gap:.3f} s from the nearest graph node (stamp "
                                       f"{s.node_stamps[node]!r}{s.suffix()}); loops.attach_tolerance = "
                                       f"{self.config.loops.attach_tolerance} s")
        return s.keys[node], odom

    def _corrections(self, s: Session, stamps: np.ndarray) -> np.ndarray:
        """(M, 4, 4) map_T_odom at each stamp: node corrections blended in time (``pose(t)`` in docs/backend.md)."""
        est = self._session_estimates(s)
        node_t = np.array(s.node_stamps)
        odom = s.odom.view()[np.array(s.node_index)]
        corr = est @ invert(odom)  # (K, 4, 4)
        hi = np.clip(np.searchsorted(node_t, stamps, side="left"), 0, len(node_t) - 1)
        lo = np.clip(hi - 1, 0, None)
        span = node_t[hi] - node_t[lo]
        w = np.where(span > 0, (stamps - node_t[lo]) / np.where(span > 0, span, 1.0), 1.0)
        w = np.clip(w, 0.0, 1.0)
        return interpolate_poses(corr[lo], corr[hi], w)

    def _restore(self, saved: SavedGraph, *, hold: bool) -> None:
        """Rebuild the graph from a saved file's arrays (checked by :meth:`SavedGraph.from_arrays` first); ``hold``:
        every session held (:meth:`load`)."""
        gt_cov = to_gtsam_covariance
        row0 = node0 = 0
        for info in saved.sessions:
            s = Session(name=info.name, code=len(self._sessions), root=info.root, anchored=info.anchored,
                        frame=np.array(info.frame, np.float64), anchors=info.anchors, held=info.held or hold)
            self._sessions[s.name] = s
            s.stamps.extend(saved.stamps[row0:row0 + info.rows].astype(np.float64))
            s.odom.extend(saved.odometry[row0:row0 + info.rows].astype(np.float64))
            for n in range(info.nodes):
                row = int(saved.node_index[node0 + n])
                self._new_key(s, row)
                if n == 0:
                    s.cum.extend(np.zeros((1, 6, 6)))
                    s.travel.append(0.0)
                    continue
                step = invert(s.node_odom(n - 1)) @ s.odom.view()[row]
                step[:3, :3] = nearest_rotation(step[:3, :3])
                cov = saved.step_covariance[node0 + n].astype(np.float64)
                self._extend_chain(s, row, cov, gt_cov(cov, step[:3, :3]), step)
            row0, node0 = row0 + info.rows, node0 + info.nodes
        for (parent, child), measured, cov, stamps, chi2 in zip(
                saved.loop_nodes, saved.loop_measured, saved.loop_covariance, saved.loop_stamps,
                saved.loop_chi2, strict=True):
            p, c = int(parent), int(child)  # file positions: the keys, as sessions were restored in order
            self._loops.append(Loop(p, c, measured.copy(), cov.copy(), (float(stamps[0]), float(stamps[1])),
                                     float(chi2), np.zeros((6, 6)),
                                     (self._key_session[c].name, self._key_session[p].name)))
        self._ups = [(float(t), int(n), b.copy()) for t, n, b in zip(saved.up_stamps, saved.up_nodes, saved.up_body,
                                                                       strict=True)]
        if np.isfinite(saved.up_world).all():
            self._up_world = saved.up_world / np.linalg.norm(saved.up_world)
        self._held = saved.node_estimate.astype(np.float64)  # where held nodes are held
        if self._key_session:
            self._rebuild(self._held)
        self._rebuild_loop_covariances()
        for (parent, child), measured, cov, stamps in zip(saved.waiting_nodes, saved.waiting_measured,
                                                          saved.waiting_covariance, saved.waiting_stamps, strict=True):
            p, c = int(parent), int(child)  # waiting again: judged as when they came (their counts are saved)
            loop = Loop(p, c, measured.copy(), cov.copy(), (float(stamps[0]), float(stamps[1])), math.nan,
                        np.zeros((6, 6)), (self._key_session[c].name, self._key_session[p].name))
            self._resubmit(loop, to_gtsam_covariance(loop.covariance, loop.measured[:3, :3]))
        self._rejected, self._redundant, self._refused = saved.rejected, saved.redundant, Counter(saved.refused)
        self._inter = Counter(saved.inter_session)
# ============================================================================ helpers
def _import_gtsam() -> Any:
    try:
        import gtsam
    except ImportError as exc:
        raise BackendError(f"gtsam is not installed ({exc}); the back end needs it: pip install gtsam",
                           reason="no gtsam") from exc
    return gtsam


def _pose3(gt: Any, matrix: np.ndarray) -> Any:
    return gt.Pose3(np.ascontiguousarray(matrix, np.float64))


def _rotation_to(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the z axis to the unit vector ``up``."""
    axis = np.cross([0.0, 0.0, 1.0], up)
    s, c = float(np.linalg.norm(axis)), float(up[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(axis / s * math.atan2(s, c))


def compose_covariance(cov: np.ndarray, before: np.ndarray, rel: np.ndarray, after: np.ndarray) -> np.ndarray:
    """ROS-order covariance of ``before @ rel @ after`` given that of ``rel`` (``before``, ``after`` exact).

    Parent-frame errors ``(dt, dtheta)`` of ``rel`` become ``dtheta' = R_b dtheta`` and
    ``dt' = R_b dt - R_b [R t_a]_x dtheta`` (``R_b``: before's rotation, ``R``: rel's, ``t_a``: after's
    translation): :func:`~lcpr_core.loop_report.covariance_lidar_to_body` generalised to any two sides.
    """
    rb = before[:3, :3]
    j = np.zeros((6, 6))
    j[:3, :3] = j[3:, 3:] = rb
    j[:3, 3:] = -rb @ skew(rel[:3, :3] @ after[:3, 3])
    out = j @ cov @ j.T
    return 0.5 * (out + out.T)


def _cat(parts: list[np.ndarray], empty: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty)
