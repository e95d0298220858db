"""The pose graph: :class:`PoseGraphBackend`, GTSAM iSAM2 fed online with odometry, loops and measured ups.

One ``Pose3`` per graph node (a keyframe of the odometry); every odometry message is kept, so any stamp can
be corrected. Stamps are seconds, poses 4 x 4 ``world_T_base``, covariances 6 x 6 in the ROS order of
:mod:`lcpr_core.posegraph`. How nodes, factors, the check and ``pose(t)`` are built: docs/backend.md,
*How the graph is built*.
"""
from __future__ import annotations

import bisect
import math
import os
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import BackendError, PoseGraphError
from ..geometry import interpolate_poses, invert, nearest_rotation, skew, so3_exp, unit_vector
from ..growable import GrowableArray
from ..loop_report import covariance_lidar_to_body
from ..posegraph import check_covariances, check_poses, lidar_to_body, to_gtsam_covariance
from .config import BackendConfig, is_real, rotation_angle, show
from .consistency import mahalanobis_squared, relative_covariance, to_world
from .graph_file import SavedGraph, read_graph_file, write_graph_file

__all__ = ["BackendStats", "PoseGraphBackend", "compose_covariance"]

_LINEAR_M, _LINEAR_RAD = 0.02, math.radians(0.1)  # a loop that moved its node less was solved in one update
_CONVERGED_M, _CONVERGED_RAD = 1e-3, math.radians(0.01)  # an extra iSAM2 update that moves less: stop
_UP_CHAR = "u"  # Symbol character of the world's up variable (graph nodes are plain integers: character '\0')

# reasons a refusal is counted under (BackendError.reason)
ODOM_ORDER = "odometry out of order"
ODOM_POSE = "odometry bad pose"
BAD_STAMP = "bad stamp"
LOOP_POSE = "loop bad pose"
LOOP_COVARIANCE = "loop bad covariance"
LOOP_UNKNOWN = "loop stamp never seen"
LOOP_OLD = "loop stamp older than the graph"
LOOP_AHEAD = "loop stamp ahead of odometry"
LOOP_SAME_NODE = "loop within one node"
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


# ============================================================================ the back end
@dataclass
class _Loop:
    parent: int  # graph node of the match
    child: int  # graph node of the query
    measured: np.ndarray  # (4, 4) parent_T_child
    covariance: np.ndarray  # (6, 6) ROS order, in the parent node's frame
    stamps: tuple[float, float]  # (query, match) as given
    chi2: float
    world_cov: np.ndarray  # (6, 6) GTSAM order, moved into the odometry's world frame (path search)


class PoseGraphBackend:
    """An iSAM2 pose graph fed online with odometry and loop closures (docs/backend.md: how it is built)."""

    def __init__(self, config: BackendConfig | None = None) -> None:
        if config is None:
            config = BackendConfig()
        if not isinstance(config, BackendConfig):
            raise BackendError(f"config={config!r}; expected a BackendConfig", reason="bad option")
        self.config = config
        self._gtsam = _import_gtsam()
        self._threshold = config.loops.threshold()
        self._stamps = GrowableArray(np.float64)
        self._odom = GrowableArray(np.float64, (4, 4))
        self._node_stamps: list[float] = []
        self._node_index: list[int] = []  # odometry row of each node
        self._cum = GrowableArray(np.float64, (6, 6))  # prefix sums of world-frame odometry covariances
        self._step_cov = GrowableArray(np.float64, (6, 6))  # ROS-order covariance of each node step
        self._loops: list[_Loop] = []
        self._loop_ends = GrowableArray(np.int64, (2,))  # (parent, child) of each accepted loop
        self._loop_world_cov = GrowableArray(np.float64, (6, 6))  # their world_cov, stacked for the path search
        self._rejected = 0
        self._redundant = 0
        self._travel: list[float] = []  # m along the odometry at each node
        self._refused: Counter[str] = Counter()
        self._last_loop_s: float | None = None
        self._last_chi2: float | None = None
        self._newest = np.eye(4)  # estimate of the newest node
        self._estimates: np.ndarray | None = None  # (K, 4, 4) cache, None when stale
        self._qr = config.factorization == "qr"
        self._isam = self._new_isam()
        self._up_world: np.ndarray | None = None  # the world's up in the odometry frame, once warmed up
        self._up_key = int(self._gtsam.symbol(_UP_CHAR, 0))  # the world's up as a variable (up_world_sigma_deg)
        self._ups: list[tuple[float, int, np.ndarray]] = []  # (stamp, node, up in that node's base frame)

    # -- inputs ------------------------------------------------------------------------------
    def add_odometry(self, stamp: float, world_T_base: np.ndarray) -> bool:
        """Take one odometry message; True when it became a graph node. Stamps must increase."""
        t = self._stamp(stamp, "odometry stamp")
        n = len(self._stamps)
        if n and t <= self._stamps.view()[-1]:
            newest = float(self._stamps.view()[-1])
            word = "repeats" if t == newest else "is before"
            self._refuse(ODOM_ORDER, f"odometry stamp {t!r} {word} the newest odometry stamp {newest!r}; "
                                     "expected stamps that increase (a replayed bag or a reset starts a new graph)")
        pose = self._pose(world_T_base, f"odometry world_T_base at stamp {t!r}", ODOM_POSE)
        self._stamps.extend(np.array([t]))
        self._odom.extend(pose[None])
        if not self._node_index:
            self._add_first_node(n)
            return True
        last = self._node_index[-1]
        step = invert(self._odom.view()[last]) @ pose
        if not self.config.keyframes.due(float(np.linalg.norm(step[:3, 3])), rotation_angle(step[:3, :3]),
                                         t - self._node_stamps[-1]):
            return False
        self._add_node(n)
        return True

    def add_loop(self, query_stamp: float, match_stamp: float, match_T_query: np.ndarray,
                 covariance: np.ndarray | None = None) -> bool:
        """Add a verified loop closure; False when the consistency check rejects it.

        ``match_T_query``: the query keyframe's LiDAR frame in the match keyframe's LiDAR frame;
        ``covariance``: its 6 x 6 (x, y, z, roll, pitch, yaw), None = ``loops.default_sigmas``.
        Raises BackendError (the graph unchanged) for inputs that cannot be used.
        """
        q = self._stamp(query_stamp, "query_stamp")
        m = self._stamp(match_stamp, "match_stamp")
        rel = self._pose(match_T_query, f"match_T_query of the loop {q!r} -> {m!r}", LOOP_POSE)
        if covariance is None:
            cov = self.config.loops.default_covariance()
        else:
            try:
                cov = check_covariances(covariance, f"covariance of the loop {q!r} -> {m!r}", single=True)
            except PoseGraphError as err:
                self._refuse(LOOP_COVARIANCE, f"{err} (got {show(covariance)})")
        child, odom_q = self._attach(q, "query_stamp")
        parent, odom_m = self._attach(m, "match_stamp")
        if child == parent:
            self._refuse(LOOP_SAME_NODE, f"query_stamp {q!r} and match_stamp {m!r} attach to the same graph node "
                                         f"(stamp {self._node_stamps[child]!r}); a loop needs two places")
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
        chi2 = self._chi2(parent, child, measured, gtsam_cov)
        self._last_chi2 = chi2
        if not chi2 <= self._threshold:
            self._rejected += 1
            return False
        gt = self._gtsam
        graph = gt.NonlinearFactorGraph()
        graph.add(gt.BetweenFactorPose3(parent, child, _pose3(gt, measured), self._loop_noise(gtsam_cov)))
        moved_from = self._isam.calculateEstimatePose3(child).matrix()
        self._update(graph, gt.Values())
        self._converge(child, moved_from)
        self._remember(_Loop(parent, child, measured, measured_cov, (q, m), chi2,
                             to_world(gtsam_cov, self._node_odom(child))))
        self._refresh()
        self._last_loop_s = time.perf_counter() - tic
        return True

    def add_up(self, stamp: float, up: np.ndarray) -> bool:
        """Take the up direction measured in the loops' LiDAR frame at ``stamp`` (:func:`lcpr_core.up.estimate_up`).

        The node nearest in time gets an attitude factor holding its up axis to the world's up (std dev
        ``up_sigma_deg``, Huber kernel). The world's up in the odometry frame is the mean of the measurements
        within ``up_warmup_m`` of travel from the first node, carried by the odometry, so an odometry frame
        that is not level (a handheld start, a LIO's first IMU frame) is fine. False when ``up_sigma_deg``
        is 0 (ignored). Raises BackendError (the graph unchanged) for a vector that is not finite and
        non-zero or a stamp outside the odometry.
        """
        t = self._stamp(stamp, "up stamp")
        vec = unit_vector(up)
        if vec is None:
            self._refuse(UP_VECTOR, f"up at stamp {t!r} is {show(up)}; expected a finite non-zero 3-vector")
        if self.config.up_sigma_deg <= 0:
            return False
        node, odom_t = self._attach(t, "up stamp", tolerance=math.inf)  # a tilt carried a few s drifts little
        body_t = self.config.base_T_lidar[:3, :3] @ vec  # base frame at t
        body = self._node_odom(node)[:3, :3].T @ odom_t[:3, :3] @ body_t  # the node's base frame
        self._ups.append((t, node, body))
        world_up, warm_up_ends = self._up_world, self._up_world is None
        if world_up is None:
            warmup = self.config.up_warmup_m
            if self._travel[node] <= warmup:
                return True  # kept for the world's up; its factor comes when the warm-up ends
            warm = [(n, b) for _, n, b in self._ups if self._travel[n] <= warmup] or [(node, body)]
            world = sum(self._node_odom(n)[:3, :3] @ b for n, b in warm)
            world_up = self._up_world = world / np.linalg.norm(world)
        graph, values = self._gtsam.NonlinearFactorGraph(), self._gtsam.Values()
        if warm_up_ends:  # the variable (up_world_sigma_deg > 0) and every up kept so far
            self._add_world_up(graph, values, world_up)
        for _, n, b in self._ups if warm_up_ends else self._ups[-1:]:
            self._add_up_factor(graph, n, b, world_up)
        self._update(graph, values)
        self._refresh()
        return True

    # -- outputs ---------------------------------------------------------------------------
    def pose(self, stamp: float) -> np.ndarray:
        """Corrected 4 x 4 world_T_base at ``stamp``, within the odometry's span (``pose(t)`` in docs/backend.md)."""
        if not is_real(stamp) or not math.isfinite(float(stamp)):
            raise BackendError(f"stamp={stamp!r}; expected a finite number of seconds", reason=BAD_STAMP)
        t = float(stamp)
        if not self._node_index:
            raise BackendError(f"stamp={t!r}: the graph holds no odometry yet", reason=LOOP_UNKNOWN)
        odom = self._odom_at(t, "stamp", count=False)  # a question, not an input: not counted as refused
        return self._corrections(np.array([t]))[0] @ odom

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,), corrected poses (N, 4, 4)) of every odometry message taken."""
        stamps = self._stamps.view().copy()
        if not len(stamps):
            return stamps, np.zeros((0, 4, 4))
        return stamps, self._corrections(stamps) @ self._odom.view()

    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (K,), estimates (K, 4, 4)) of the graph nodes (the keyframes of ``~/path``)."""
        return np.array(self._node_stamps), self._node_estimates().copy()

    def map_T_odom(self) -> np.ndarray:
        """4 x 4 correction of the newest node: ``map_T_base = map_T_odom @ odom_T_base``."""
        if not self._node_index:
            return np.eye(4)
        return self._newest @ invert(self._node_odom(len(self._node_index) - 1))

    def stats(self) -> BackendStats:
        return BackendStats(odometry=len(self._stamps), nodes=len(self._node_index),
                            loops_accepted=len(self._loops), loops_rejected=self._rejected,
                            refused=dict(self._refused), last_loop_s=self._last_loop_s, last_chi2=self._last_chi2,
                            loops_redundant=self._redundant, ups=len(self._ups))

    @property
    def loops(self) -> list[tuple[float, float, float]]:
        """(query_stamp, match_stamp, chi2) of every accepted loop, in order."""
        return [(lp.stamps[0], lp.stamps[1], lp.chi2) for lp in self._loops]

    # -- file ------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the graph as .npz (atomically; no pickled objects): odometry, nodes, factors, estimates."""
        k = len(self._node_index)
        write_graph_file(path, SavedGraph(
            base_T_lidar=np.array(self.config.base_T_lidar),
            stamps=self._stamps.view(), odometry=self._odom.view(),
            node_index=np.array(self._node_index, np.int64).reshape(k),
            node_estimate=self._node_estimates(), step_covariance=self._step_cov.view(),
            loop_nodes=np.array([(lp.parent, lp.child) for lp in self._loops], np.int64).reshape(-1, 2),
            loop_measured=np.array([lp.measured for lp in self._loops], np.float64).reshape(-1, 4, 4),
            loop_covariance=np.array([lp.covariance for lp in self._loops], np.float64).reshape(-1, 6, 6),
            loop_stamps=np.array([lp.stamps for lp in self._loops], np.float64).reshape(-1, 2),
            loop_chi2=np.array([lp.chi2 for lp in self._loops], np.float64),
            up_stamps=np.array([u[0] for u in self._ups], np.float64),
            up_nodes=np.array([u[1] for u in self._ups], np.int64),
            up_body=np.array([u[2] for u in self._ups], np.float64).reshape(-1, 3),
            up_world=np.full(3, np.nan) if self._up_world is None else self._up_world,
            rejected=self._rejected, redundant=self._redundant, refused=dict(self._refused)))

    @classmethod
    def load(cls, path: str | os.PathLike[str], config: BackendConfig | None = None) -> PoseGraphBackend:
        """A back end continuing the graph saved at ``path`` (BackendError names what is wrong with the file)."""
        data = read_graph_file(path)
        backend = cls(config)
        backend._restore(SavedGraph.from_arrays(data, os.fspath(path), base_T_lidar=backend.config.base_T_lidar))
        return backend

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

    def _add_first_node(self, row: int) -> None:
        gt = self._gtsam
        pose = self._odom.view()[row]
        graph, values = gt.NonlinearFactorGraph(), gt.Values()
        graph.add(gt.PriorFactorPose3(0, _pose3(gt, pose), gt.noiseModel.Isotropic.Sigma(6, self.config.prior_sigma)))
        values.insert(0, _pose3(gt, pose))
        self._add_level(graph, 0, pose)
        self._update(graph, values)
        self._node_index.append(row)
        self._node_stamps.append(float(self._stamps.view()[row]))
        self._cum.extend(np.zeros((1, 6, 6)))
        self._travel.append(0.0)
        self._refresh()

    def _add_node(self, row: int, *, step_cov: np.ndarray | None = None, initial: np.ndarray | None = None) -> None:
        gt = self._gtsam
        k = len(self._node_index)
        odom = self._odom.view()
        step = invert(odom[self._node_index[-1]]) @ odom[row]
        step[:3, :3] = nearest_rotation(step[:3, :3])
        cov = self.config.odometry.covariance(step) if step_cov is None else step_cov
        gtsam_cov = to_gtsam_covariance(cov, step[:3, :3])
        graph, values = gt.NonlinearFactorGraph(), gt.Values()
        graph.add(gt.BetweenFactorPose3(k - 1, k, _pose3(gt, step),
                                        gt.noiseModel.Gaussian.Covariance(gtsam_cov)))
        values.insert(k, _pose3(gt, self._newest @ step if initial is None else initial))
        self._add_level(graph, k, odom[row])
        self._update(graph, values)
        self._node_index.append(row)
        self._node_stamps.append(float(self._stamps.view()[row]))
        self._step_cov.extend(cov[None])
        self._cum.extend((self._cum.view()[-1] + to_world(gtsam_cov, odom[row]))[None])
        self._travel.append(self._travel[-1] + float(np.linalg.norm(step[:3, 3])))
        self._refresh()

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
        """After an iSAM2 update: the newest estimate now, the full one when asked for."""
        self._newest = self._isam.calculateEstimatePose3(len(self._node_index) - 1).matrix()
        self._estimates = None

    def _node_estimates(self) -> np.ndarray:
        if self._estimates is None:
            k = len(self._node_index)
            # a full back-substitution: the online reads (the newest node, the check's two ends) stop at
            # wildfire_threshold, the trajectory and the saved graph do not
            values = self._isam.calculateBestEstimate()
            self._estimates = np.stack([values.atPose3(i).matrix() for i in range(k)]) if k else np.zeros((0, 4, 4))
        return self._estimates

    def _node_odom(self, node: int) -> np.ndarray:
        return self._odom.view()[self._node_index[node]]

    def _remember(self, loop: _Loop) -> None:
        """Keep an accepted loop (and its ends and world covariance for the consistency check's path search)."""
        self._loops.append(loop)
        self._loop_ends.extend(np.array([[loop.parent, loop.child]], np.int64))
        self._loop_world_cov.extend(loop.world_cov[None])

    def _is_redundant(self, parent: int, child: int) -> bool:
        """Whether an accepted loop joins places within ``loops.min_spacing_m`` of travel of both ends."""
        spacing = self.config.loops.min_spacing_m
        if spacing <= 0 or not self._loops:
            return False
        tp, tc = self._travel[parent], self._travel[child]
        return any(abs(self._travel[lp.parent] - tp) < spacing and abs(self._travel[lp.child] - tc) < spacing
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
        return mahalanobis_squared(residual, gtsam_cov, self._relative_covariance(parent, child))

    def _relative_covariance(self, a: int, b: int) -> np.ndarray:
        """GTSAM-order covariance of ``X_a^-1 X_b`` (in b's tangent) along the least uncertain path."""
        return relative_covariance(a, b, cumulative=self._cum.view(), loop_ends=self._loop_ends.view(),
                                   loop_world_cov=self._loop_world_cov.view(), odom_b=self._node_odom(b))

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

    def _attach(self, t: float, name: str, *, tolerance: float | None = None) -> tuple[int, np.ndarray]:
        """(graph node nearest to stamp ``t``, the odometry pose at ``t``) or a refusal naming the stamp.

        ``tolerance``: s the node may be from ``t`` (default ``loops.attach_tolerance``)."""
        if not self._node_index:
            self._refuse(LOOP_UNKNOWN, f"{name}={t!r}: the graph holds no odometry yet")
        odom = self._odom_at(t, name)
        i = bisect.bisect_left(self._node_stamps, t)
        near = [j for j in (i - 1, i) if 0 <= j < len(self._node_stamps)]
        node = min(near, key=lambda j: abs(self._node_stamps[j] - t))
        gap = abs(self._node_stamps[node] - t)
        if gap > (self.config.loops.attach_tolerance if tolerance is None else tolerance):
            self._refuse(LOOP_UNKNOWN, f"{name}={t!r} is {gap:.3f} s from the nearest graph node (stamp "
                                       f"{self._node_stamps[node]!r}); loops.attach_tolerance = "
                                       f"{self.config.loops.attach_tolerance} s")
        return node, odom

    def _odom_at(self, t: float, name: str, *, count: bool = True) -> np.ndarray:
        """The odometry pose at ``t``: interpolated between its two messages, or the nearest within tolerance."""
        stamps, odom = self._stamps.view(), self._odom.view()
        tol = self.config.loops.stamp_tolerance

        def refuse(reason: str, message: str) -> None:
            if count:
                self._refuse(reason, message)
            raise BackendError(message, reason=reason)

        if t < stamps[0] - tol:
            refuse(LOOP_OLD, f"{name}={t!r} is older than the graph (its first odometry stamp is "
                             f"{float(stamps[0])!r})")
        if t > stamps[-1] + tol:
            refuse(LOOP_AHEAD, f"{name}={t!r} is after the newest odometry stamp {float(stamps[-1])!r}; "
                               "add the odometry up to that stamp first")
        i = int(np.searchsorted(stamps, t))
        if i < len(stamps) and stamps[i] == t:
            return odom[i].copy()
        if i == 0 or i == len(stamps):
            return odom[min(i, len(stamps) - 1)].copy()
        lo, hi = float(stamps[i - 1]), float(stamps[i])
        if min(t - lo, hi - t) > tol:
            refuse(LOOP_UNKNOWN, f"{name}={t!r} was never seen: the odometry around it is at {lo!r} and "
                                 f"{hi!r}, both more than loops.stamp_tolerance = {tol} s away")
        w = (t - lo) / (hi - lo)
        return interpolate_poses(odom[i - 1:i], odom[i:i + 1], np.array([w]))[0]

    def _corrections(self, stamps: np.ndarray) -> np.ndarray:
        """(M, 4, 4) map_T_odom at each stamp: node corrections blended in time (``pose(t)`` in docs/backend.md)."""
        est = self._node_estimates()
        node_t = np.array(self._node_stamps)
        odom = self._odom.view()[np.array(self._node_index)]
        corr = est @ invert(odom)  # (K, 4, 4)
        hi = np.clip(np.searchsorted(node_t, stamps, side="left"), 0, len(node_t) - 1)
        lo = np.clip(hi - 1, 0, None)
        span = node_t[hi] - node_t[lo]
        w = np.where(span > 0, (stamps - node_t[lo]) / np.where(span > 0, span, 1.0), 1.0)
        w = np.clip(w, 0.0, 1.0)
        return interpolate_poses(corr[lo], corr[hi], w)

    def _restore(self, saved: SavedGraph) -> None:
        """Rebuild the graph from a saved file's arrays (checked by :meth:`SavedGraph.from_arrays` first)."""
        k, idx = len(saved.node_index), saved.node_index
        gt = self._gtsam
        self._stamps.extend(saved.stamps.astype(np.float64))
        self._odom.extend(saved.odometry.astype(np.float64))
        if k == 0:
            return
        self._add_first_node(0)
        for row, cov, estimate in zip(idx[1:], saved.step_covariance, saved.node_estimate[1:], strict=True):
            self._add_node(int(row), step_cov=cov, initial=estimate)
        graph, values = gt.NonlinearFactorGraph(), gt.Values()
        for (parent, child), measured, cov, stamps, chi2 in zip(
                saved.loop_nodes, saved.loop_measured, saved.loop_covariance, saved.loop_stamps,
                saved.loop_chi2, strict=True):
            gtsam_cov = to_gtsam_covariance(cov, measured[:3, :3])
            graph.add(gt.BetweenFactorPose3(int(parent), int(child), _pose3(gt, measured), self._loop_noise(gtsam_cov)))
            self._remember(_Loop(int(parent), int(child), measured.copy(), cov.copy(),
                                 (float(stamps[0]), float(stamps[1])), float(chi2),
                                 to_world(gtsam_cov, self._node_odom(int(child)))))
        self._ups = [(float(t), int(n), b.copy()) for t, n, b in zip(saved.up_stamps, saved.up_nodes, saved.up_body,
                                                                       strict=True)]
        if np.isfinite(saved.up_world).all():
            self._up_world = saved.up_world / np.linalg.norm(saved.up_world)
            if self.config.up_sigma_deg > 0:
                self._add_world_up(graph, values, self._up_world)
                for _, n, b in self._ups:
                    self._add_up_factor(graph, n, b, self._up_world)
        self._update(graph, values)
        for _ in range(max(self.config.loops.iterations, 1)):
            self._update()
        self._rejected, self._redundant, self._refused = saved.rejected, saved.redundant, Counter(saved.refused)
        self._refresh()


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
