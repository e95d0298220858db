"""Online pose-graph back end: any odometry plus verified loop closures -> a corrected trajectory.

    g = PoseGraphBackend(BackendConfig(base_T_lidar=T))   # T: base frame -> the loops' LiDAR frame
    g.add_odometry(stamp, world_T_base)                     # every odometry message, in stamp order
    g.add_loop(query_stamp, match_stamp, match_T_query, covariance)   # False: rejected as inconsistent
    g.pose(stamp), g.trajectory(), g.map_T_odom(), g.stats(), g.save(path), PoseGraphBackend.load(path)

GTSAM iSAM2 (an optional extra: ``pip install gtsam``; Cholesky, QR where that fails, see ``_new_isam``) holds one
``Pose3`` per graph node; every stamp is in seconds, every pose a 4 x 4 ``world_T_base``, every
covariance 6 x 6 in the ROS order and meaning of :mod:`lcpr_core.posegraph` ((x, y, z, roll, pitch,
yaw), errors in the parent frame), turned into GTSAM's with :func:`~lcpr_core.posegraph.to_gtsam_covariance`.

Nodes (keyframing). A 10 Hz odometry does not get a node per message: a message becomes a node when
the vehicle moved ``keyframes.distance`` m or turned ``keyframes.angle_deg`` since the last node, or
``keyframes.interval`` s passed (LIO-SAM's 1 m / 0.2 rad rule, plus a slow clock so that standing
still keeps nodes near every stamp). Every message is kept (stamp and pose), so that any stamp can be
corrected and loops can be attached exactly.

Odometry factors. Between two nodes, a ``BetweenFactorPose3`` with the odometry's relative pose and
:class:`OdometryNoise`: :class:`~lcpr_core.posegraph.DriftModel`'s form for a step of length ``d`` m
(std dev 2 % of ``d`` in x and y, 1 % in z, ``0.1 deg * sqrt(d)`` of yaw, ``0.2 deg * sqrt(d)`` of
roll and pitch), plus 2 % of the angle turned on each rotation axis. The consistency check below
trusts this model, so it must not be tighter than the odometry's real drift: KISS-ICP on the
synthetic nuScenes-like rig (validation city seed 3, 600 m at 1 m steps) drifted ``0.01-0.02 deg *
sqrt(m)`` in yaw, ``0.15 deg * sqrt(m)`` in roll and pitch (a 32-beam LiDAR's weak axes) and about
1 % of the distance in position; the defaults are 1.3 times (roll, pitch) to 8 times (yaw) looser,
room for wheel or visual odometry.

Level prior (``level_sigma_deg``, off by default). Loops fix the shape between the places they join,
not a tilt the odometry picked up before them: the 2-3 deg of roll/pitch KISS-ICP gathers in its
first 100 m put the rest of a drive on a tilted plane, metres off in z, and loops within that plane
agree with it. For a ground vehicle whose roll and pitch are level on average (or with an IMU's
gravity), an attitude factor per node (GTSAM's ``AttitudeFactorPose3``: the node's up axis to the
world's up, std dev ``level_sigma_deg``; a few degrees leaves roads their slopes) removes it. Not
for hilly drives: a long climb is pulled toward level.

Measured ups (``add_up``, on by default: ``up_sigma_deg``). The detector measures each 360-degree
keyframe's up from its walls (:mod:`lcpr_core.up`); the same attitude factor then holds the node nearest
in time to the world's up, which slopes do not move. The world's up in the odometry frame is the mean
of the ups of the first ``up_warmup_m`` of travel, fixed (or, ``up_world_sigma_deg`` > 0, a graph
variable every later up refines: steadier under noisy ups, several times dearer per update).

Loops. ``match_T_query`` (LiDAR frames) becomes a body-frame constraint
(:func:`~lcpr_core.posegraph.lidar_to_body`, :func:`~lcpr_core.loop_report.covariance_lidar_to_body`)
and is attached to the graph node nearest in time to each stamp, within ``loops.attach_tolerance``
s: the odometry between the stamp and its node is composed into the constraint (and its covariance
moved accordingly), so attaching costs no accuracy. Loop factors carry their covariance (``None`` ->
``loops.default_sigmas``) inside a robust kernel (``loops.robust``: huber by default, convex, so a
long-drift loop still pulls the graph all the way; cauchy for a harder cut-off). ``loops.covariance_scale``
multiplies every loop covariance (1 by default: a detector whose covariances are known to be too tight
or too loose). ``loops.min_spacing_m`` (0 = off, the default) skips a loop whose both ends lie within that
much travel (along the odometry, between graph nodes) of an accepted loop's ends, counted as redundant:
a place closed again and again then costs one iSAM2 update, not hundreds. Neither helped the validation
city (benchmarks/studies/backend_loop_redundancy.py), so both are off.

Consistency check (before a loop enters the graph): a chi-square test of the loop against the
current estimate. The residual ``r = Log(measured^-1 * X_match^-1 X_query)`` is weighed by
``S = C_loop + C_rel``, ``C_rel`` the covariance of the relative pose of the two nodes along the
least uncertain path through the graph: odometry stretches and loops already accepted, each
moved into the world frame (their sums are precomputed per node, so the check costs a small
Dijkstra over the loops' end nodes, not a solve of the graph). A single path ignores the information
parallel paths add (and the level prior), so ``C_rel`` bounds the true marginal from above (to
within its linearisation at the odometry poses): as long as the odometry model is not tighter than the
real drift, the check does not reject a true loop by being over-confident about the graph, and it
stays cheap at thousands of nodes (iSAM2's exact joint marginals cost 25-45 ms at 2,000 nodes on the
2-core EPYC measured). A loop whose
``r^T S^-1 r`` exceeds the chi-square quantile of ``loops.gate`` (6 degrees of freedom) is rejected
and counted. Pairwise consistency between loops (PCM) is not used: it needs several loops of one
place before it can judge, while the test against the estimate judges the first one.

pose(t). ``C(t) @ O(t)``: ``O(t)`` the odometry at ``t`` (interpolated between its two messages around
``t``: translation linearly, rotation by slerp) and ``C(t)`` the graph's correction ``X_n O_n^-1`` of
the two nodes around ``t``, blended in time the same way (after the newest node: that node's). At a
node it is the node's estimate; between nodes, the odometry's own shape, moved smoothly.
``map_T_odom()`` is the newest node's correction.
"""
from __future__ import annotations

import bisect
import heapq
import json
import math
import numbers
import os
import time
import zipfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .atomic import atomic_path
from .errors import BackendError, PoseGraphError
from .geometry import interpolate_poses, invert, nearest_rotation, rotation_angle_deg, skew, so3_exp, unit_vector
from .growable import GrowableArray
from .loop_report import DEFAULT_LOOP_COVARIANCE, covariance_lidar_to_body
from .posegraph import (
    ROBUST_KERNELS,
    DriftModel,
    check_covariances,
    check_poses,
    lidar_to_body,
    to_gtsam_covariance,
)

__all__ = [
    "BackendConfig", "BackendStats", "GRAPH_SCHEMA", "GRAPH_VERSION", "KeyframeRule", "LoopPolicy", "OdometryNoise",
    "PoseGraphBackend", "chi2_quantile_6dof", "config_dict",
]

GRAPH_SCHEMA = "lcpr_backend_graph"
GRAPH_VERSION = 2  # 2 added the measured ups; version 1 files (none) still load
_LINEAR_M, _LINEAR_RAD = 0.02, math.radians(0.1)  # a loop that moved its node less was solved in one update
_CONVERGED_M, _CONVERGED_RAD = 1e-3, math.radians(0.01)  # an extra iSAM2 update that moves less: stop
_PATH_LENGTH_M = 10.0  # a radian of relative-pose uncertainty weighs as much as 10 m when choosing the path
FACTORIZATIONS = ("auto", "cholesky", "qr")
_SLACK = 1e-6  # m, rad and s: round-off allowed when a keyframe criterion is compared
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


def _default_sigmas() -> tuple[float, ...]:
    sigma = np.sqrt(np.diag(DEFAULT_LOOP_COVARIANCE))
    return tuple(round(float(v), 9) for v in (*sigma[:3], *np.degrees(sigma[3:])))


def _is_real(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise BackendError(message, reason="bad option")


def _finite_non_negative(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _require(_is_real(value) and math.isfinite(value) and value >= 0,
                 f"{type(obj).__name__}.{name}={value!r}; expected a finite number >= 0")


# ============================================================================ configuration
@dataclass(frozen=True, kw_only=True)
class KeyframeRule:
    """When an odometry message becomes a graph node (any criterion that is due; 0 turns one off)."""

    distance: float = 1.0  # m moved (3-D) since the last node
    angle_deg: float = 11.5  # deg turned since the last node (0.2 rad, as LIO-SAM)
    interval: float = 5.0  # s since the last node (standing still)

    def __post_init__(self) -> None:
        _finite_non_negative(self, "distance", "angle_deg", "interval")

    def due(self, moved: float, turned_rad: float, elapsed: float) -> bool:
        """Whether a message ``moved`` m, ``turned_rad`` and ``elapsed`` s after the last node is a node."""
        if self.distance == 0 and self.angle_deg == 0 and self.interval == 0:
            return True  # every message
        return ((self.distance > 0 and moved >= self.distance - _SLACK)  # slack: a 1 m step computed as 0.9999999
                or (self.angle_deg > 0 and turned_rad >= math.radians(self.angle_deg) - _SLACK)
                or (self.interval > 0 and elapsed >= self.interval - _SLACK))


@dataclass(frozen=True, kw_only=True)
class OdometryNoise:
    """Std dev of the odometry between two nodes, grown with its length ``d`` (m) and turn ``a`` (rad).

    x, y: ``translation_frac * d``; z: ``z_frac * d``; yaw: ``yaw_deg_per_m * sqrt(d)`` deg; roll,
    pitch: ``roll_pitch_deg_per_m * sqrt(d)`` deg (:class:`~lcpr_core.posegraph.DriftModel`'s form,
    a heading random walk); plus ``rotation_frac * a`` on each rotation axis, in quadrature. Steps
    shorter than 1 cm count as 1 cm (a still vehicle keeps an invertible covariance).
    """

    translation_frac: float = 0.02
    z_frac: float = 0.01
    yaw_deg_per_m: float = 0.1
    roll_pitch_deg_per_m: float = 0.2
    rotation_frac: float = 0.02

    def __post_init__(self) -> None:
        _finite_non_negative(self, "rotation_frac")
        try:
            drift = DriftModel(translation_frac=self.translation_frac, z_frac=self.z_frac,
                               yaw_deg_per_m=self.yaw_deg_per_m, roll_pitch_deg_per_m=self.roll_pitch_deg_per_m)
        except PoseGraphError as err:
            raise BackendError(f"OdometryNoise: {err}", reason="bad option") from err
        object.__setattr__(self, "_drift", drift)

    def covariance(self, step: np.ndarray) -> np.ndarray:
        """(6, 6) diagonal covariance (x, y, z, roll, pitch, yaw) of a (4, 4) odometry step."""
        sigmas = self._drift.step_sigmas(float(np.linalg.norm(step[:3, 3])))  # type: ignore[attr-defined]
        turned = self.rotation_frac * _rotation_angle(step[:3, :3])
        sigmas[3:] = np.sqrt(sigmas[3:] ** 2 + turned**2)
        return np.diag(sigmas**2)


@dataclass(frozen=True, kw_only=True)
class LoopPolicy:
    """How loops are attached, checked and weighed."""

    robust: str = "huber"  # m-estimator of loop factors: none | huber | cauchy
    robust_param: float = 3.0  # the kernel's k, in units of the loop's whitened (Mahalanobis) residual
    default_sigmas: tuple[float, ...] = field(default_factory=_default_sigmas)  # x, y, z (m), roll, pitch, yaw (deg)
    stamp_tolerance: float = 0.5  # s: a loop stamp this far from every odometry message was never seen
    attach_tolerance: float = 2.5  # s: the graph node nearest to a loop stamp must be this close
    gate: float = 0.999  # chi-square probability of the consistency check (6 dof); 1 = no check
    iterations: int = 3  # extra iSAM2 updates after a loop at most (relinearise and converge)
    min_spacing_m: float = 0.0  # m of travel: a loop whose both ends lie this close to an accepted loop's is skipped
    covariance_scale: float = 1.0  # every loop covariance (given or default) is multiplied by this

    def __post_init__(self) -> None:
        _require(self.robust in ROBUST_KERNELS,
                 f"LoopPolicy.robust={self.robust!r}; expected one of {', '.join(ROBUST_KERNELS)}")
        _require(_is_real(self.robust_param) and math.isfinite(self.robust_param) and self.robust_param > 0,
                 f"LoopPolicy.robust_param={self.robust_param!r}; expected a finite number > 0")
        sig = tuple(self.default_sigmas)
        _require(len(sig) == 6 and all(_is_real(v) and math.isfinite(v) and v > 0 for v in sig),
                 f"LoopPolicy.default_sigmas={sig!r}; expected 6 finite numbers > 0: x, y, z (m), roll, pitch, "
                 "yaw (deg)")
        object.__setattr__(self, "default_sigmas", tuple(float(v) for v in sig))
        _finite_non_negative(self, "stamp_tolerance", "attach_tolerance", "min_spacing_m")
        _require(_is_real(self.covariance_scale) and math.isfinite(self.covariance_scale) and self.covariance_scale > 0,
                 f"LoopPolicy.covariance_scale={self.covariance_scale!r}; expected a finite number > 0")
        _require(_is_real(self.gate) and 0 < self.gate <= 1,
                 f"LoopPolicy.gate={self.gate!r}; expected a probability in (0, 1] (1 = no check)")
        _require(isinstance(self.iterations, int) and not isinstance(self.iterations, bool)
                 and 0 <= self.iterations <= 100,
                 f"LoopPolicy.iterations={self.iterations!r}; expected an integer in 0..100")

    def default_covariance(self) -> np.ndarray:
        s = np.array(self.default_sigmas)
        s[3:] = np.radians(s[3:])
        return np.diag(s**2)

    def threshold(self) -> float:
        """The squared Mahalanobis distance above which a loop is rejected (inf: no check)."""
        return math.inf if self.gate >= 1 else chi2_quantile_6dof(self.gate)


@dataclass(frozen=True, kw_only=True)
class BackendConfig:
    """Everything :class:`PoseGraphBackend` is configured with."""

    base_T_lidar: np.ndarray = field(default_factory=lambda: np.eye(4), compare=False)  # (4, 4)
    keyframes: KeyframeRule = field(default_factory=KeyframeRule)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    loops: LoopPolicy = field(default_factory=LoopPolicy)
    prior_sigma: float = 1e-3  # std dev (m and rad) of the prior holding the first node at its odometry
    relinearize_threshold: float = 0.1  # rad: iSAM2 relinearises a node whose rotation update exceeds this
    # m: ... or whose translation update exceeds this (looser cuts the cost of a loop by half but cost 3-20 % of
    # ATE on validation city seed 3: the translation's linearisation point matters on a drifting odometry)
    relinearize_translation: float = 0.1
    # m, rad: the online reads (newest node, the check's ends) stop back-substituting below a clique whose update
    # is under this (GTSAM's wildfire; 0.001 its default); trajectory(), nodes() and save() solve fully.
    # 0.01: validation city seed 3 ATE within 0.02 % of 0.001's, with and without the level prior
    wildfire_threshold: float = 0.01
    # iSAM2's factorisation: cholesky (faster), qr (robust), or auto: Cholesky until it declares the graph
    # indeterminate, then QR for good (the graph rebuilt once from its factors; see _new_isam)
    factorization: str = "auto"
    level_sigma_deg: float = 0.0  # > 0: every node's up axis is pulled to the world's up with this std dev; 0 = off
    gravity_sigma_deg: float = 0.0  # > 0: every node's tilt is held to the odometry's with this std dev; 0 = off
    # std dev (deg) of an up direction measured from a scan's walls (add_up), inside a Huber kernel; 0 = ignore them
    up_sigma_deg: float = 2.0
    # m of travel from the first node: the ups measured within it, carried by the odometry, are averaged into the
    # world's up (fixed at the first measurement beyond it); short, so that the odometry's drift stays out of it
    up_warmup_m: float = 10.0
    # deg, > 0: the world's up is a graph variable held to the warm-up's mean with this std dev, refined by every
    # measured up, so a few noisy scans cannot tilt the map; but a variable joined to every node makes add_loop's
    # p95 3-4 times dearer at 2,000 nodes. 0 (the default): the warm-up's mean is fixed
    up_world_sigma_deg: float = 0.0

    def __post_init__(self) -> None:
        try:
            ext = check_poses(self.base_T_lidar, "BackendConfig.base_T_lidar", single=True)
        except PoseGraphError as err:
            raise BackendError(f"{err} (got {_show(self.base_T_lidar)})", reason="bad option") from err
        ext.flags.writeable = False
        object.__setattr__(self, "base_T_lidar", ext)
        for name, kind in (("keyframes", KeyframeRule), ("odometry", OdometryNoise), ("loops", LoopPolicy)):
            _require(isinstance(getattr(self, name), kind),
                     f"BackendConfig.{name}={getattr(self, name)!r}; expected a {kind.__name__}")
        for name in ("prior_sigma", "relinearize_threshold", "relinearize_translation"):
            value = getattr(self, name)
            _require(_is_real(value) and math.isfinite(value) and value > 0,
                     f"BackendConfig.{name}={value!r}; expected a finite number > 0")
        _finite_non_negative(self, "level_sigma_deg")
        _finite_non_negative(self, "gravity_sigma_deg")
        _finite_non_negative(self, "up_sigma_deg")
        _finite_non_negative(self, "up_warmup_m")
        _finite_non_negative(self, "up_world_sigma_deg")
        _finite_non_negative(self, "wildfire_threshold")
        _require(self.factorization in FACTORIZATIONS,
                 f"BackendConfig.factorization={self.factorization!r}; expected one of {', '.join(FACTORIZATIONS)}")


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
    """An iSAM2 pose graph fed online with odometry and loop closures (see the module docstring)."""

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
        if not self.config.keyframes.due(float(np.linalg.norm(step[:3, 3])), _rotation_angle(step[:3, :3]),
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
                self._refuse(LOOP_COVARIANCE, f"{err} (got {_show(covariance)})")
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
        measured_cov = _compose_covariance(body_cov, before, body, after)
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
                             _to_world(gtsam_cov, self._node_odom(child))))
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
            self._refuse(UP_VECTOR, f"up at stamp {t!r} is {_show(up)}; expected a finite non-zero 3-vector")
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
        """Corrected 4 x 4 world_T_base at ``stamp`` (within the odometry's span; see the module docstring)."""
        if not _is_real(stamp) or not math.isfinite(float(stamp)):
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
        counters = {"rejected": self._rejected, "redundant": self._redundant, "refused": dict(self._refused)}
        arrays: dict[str, Any] = {
            "schema": np.array(GRAPH_SCHEMA), "version": np.array(GRAPH_VERSION, np.int64),
            "base_T_lidar": np.array(self.config.base_T_lidar),
            "stamps": self._stamps.view(), "odometry": self._odom.view(),
            "node_index": np.array(self._node_index, np.int64).reshape(k),
            "node_estimate": self._node_estimates(), "step_covariance": self._step_cov.view(),
            "loop_nodes": np.array([(lp.parent, lp.child) for lp in self._loops], np.int64).reshape(-1, 2),
            "loop_measured": np.array([lp.measured for lp in self._loops], np.float64).reshape(-1, 4, 4),
            "loop_covariance": np.array([lp.covariance for lp in self._loops], np.float64).reshape(-1, 6, 6),
            "loop_stamps": np.array([lp.stamps for lp in self._loops], np.float64).reshape(-1, 2),
            "loop_chi2": np.array([lp.chi2 for lp in self._loops], np.float64),
            "up_stamps": np.array([u[0] for u in self._ups], np.float64),
            "up_nodes": np.array([u[1] for u in self._ups], np.int64),
            "up_body": np.array([u[2] for u in self._ups], np.float64).reshape(-1, 3),
            "up_world": np.full(3, np.nan) if self._up_world is None else self._up_world,

            "counters": np.array(json.dumps(counters)),
        }
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike[str], config: BackendConfig | None = None) -> PoseGraphBackend:
        """A back end continuing the graph saved at ``path`` (BackendError names what is wrong with the file)."""
        where = os.fspath(path)
        try:
            with np.load(where, allow_pickle=False) as npz:
                data = {name: npz[name] for name in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise BackendError(f"graph file {where} cannot be read ({err}); expected an .npz written by "
                               "PoseGraphBackend.save", reason="bad graph file") from err
        backend = cls(config)
        backend._restore(data, where)
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
        # normal equations declared the system indeterminate (livox_hku/campus, 144 nodes), while QR of the
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
        self._cum.extend((self._cum.view()[-1] + _to_world(gtsam_cov, odom[row]))[None])
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
            if np.linalg.norm(step[:3, 3]) < limits[0] and _rotation_angle(step[:3, :3]) < limits[1]:
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
        """Squared Mahalanobis distance of the loop from the current estimate (see the module docstring)."""
        if math.isinf(self._threshold):
            return 0.0
        gt = self._gtsam
        a = self._isam.calculateEstimatePose3(parent)
        b = self._isam.calculateEstimatePose3(child)
        residual = gt.Pose3.Logmap(_pose3(gt, measured).between(a.between(b)))
        s = gtsam_cov + self._relative_covariance(parent, child)
        return float(residual @ np.linalg.solve(s, residual))

    def _relative_covariance(self, a: int, b: int) -> np.ndarray:
        """GTSAM-order covariance of ``X_a^-1 X_b`` (in b's tangent) along the least uncertain path."""
        cum = self._cum.view()
        to_b = _adjoint(invert(self._node_odom(b)))
        if not self._loops:
            return to_b @ (cum[max(a, b)] - cum[min(a, b)]) @ to_b.T
        loop_ends = self._loop_ends.view()  # L x 2
        ends = np.unique(np.concatenate([[a, b], loop_ends.ravel()]))  # E sorted nodes
        # edges: the odometry stretches between consecutive ends, then the loops; their covariances E' x 6 x 6
        tail = np.searchsorted(ends, loop_ends)  # L x 2 slots
        first = np.concatenate([np.arange(len(ends) - 1), tail[:, 0]])
        second = np.concatenate([np.arange(1, len(ends)), tail[:, 1]])
        covs = np.concatenate([cum[ends[1:]] - cum[ends[:-1]], self._loop_world_cov.view()])
        weight = to_b.T @ np.diag([_PATH_LENGTH_M**2] * 3 + [1.0] * 3) @ to_b
        costs = np.maximum(np.einsum("eij,ij->e", covs, weight), 0.0).tolist()
        adjacency: list[list[tuple[int, int]]] = [[] for _ in ends]
        for e, (i, j) in enumerate(zip(first.tolist(), second.tolist(), strict=True)):
            adjacency[i].append((j, e))
            adjacency[j].append((i, e))
        start, goal = int(np.searchsorted(ends, a)), int(np.searchsorted(ends, b))
        best = [math.inf] * len(ends)
        via: list[int] = [-1] * len(ends)
        best[start] = 0.0
        heap = [(0.0, start)]
        while heap:
            d, i = heapq.heappop(heap)
            if i == goal:
                break
            if d > best[i]:
                continue
            for j, e in adjacency[i]:
                nd = d + costs[e]
                if nd < best[j]:
                    best[j], via[j] = nd, e
                    heapq.heappush(heap, (nd, j))
        path: list[int] = []
        i = goal
        while i != start:
            e = via[i]
            path.append(e)
            i = int(first[e]) if int(second[e]) == i else int(second[e])
        total = covs[path].sum(axis=0)  # 6 x 6
        return to_b @ total @ to_b.T

    # -- internals: stamps and checks ------------------------------------------------------
    def _refuse(self, reason: str, message: str) -> Any:
        self._refused[reason] += 1
        raise BackendError(message, reason=reason)

    def _stamp(self, value: Any, name: str) -> float:
        if not _is_real(value) or not math.isfinite(float(value)):
            self._refuse(BAD_STAMP, f"{name}={value!r}; expected a finite number of seconds")
        return float(value)

    def _pose(self, value: Any, name: str, reason: str) -> np.ndarray:
        try:
            pose = check_poses(value, name, single=True)
        except PoseGraphError as err:
            return self._refuse(reason, f"{err} (got {_show(value)})")
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
        """(M, 4, 4) map_T_odom at each stamp: node corrections blended in time (module docstring)."""
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

    def _restore(self, data: dict[str, np.ndarray], where: str) -> None:
        """Rebuild the graph from a saved file's arrays (checked first: nothing is half-restored)."""
        def bad(what: str) -> BackendError:
            return BackendError(f"graph file {where}: {what}", reason="bad graph file")

        schema = str(data["schema"]) if "schema" in data else None
        if schema != GRAPH_SCHEMA:
            raise bad(f"schema {schema!r}; expected {GRAPH_SCHEMA!r} (a file written by PoseGraphBackend.save)")
        version = int(data["version"]) if "version" in data else None
        if version not in (1, GRAPH_VERSION):
            raise bad(f"version {version!r}; this back end reads versions 1 to {GRAPH_VERSION}")
        if version == 1:  # before measured ups
            data = {**data, "up_stamps": np.zeros(0), "up_nodes": np.zeros(0, np.int64), "up_body": np.zeros((0, 3)),
                    "up_world": np.full(3, np.nan)}
        shapes = {"base_T_lidar": (4, 4), "stamps": (None,), "odometry": (None, 4, 4), "node_index": (None,),
                  "node_estimate": (None, 4, 4), "step_covariance": (None, 6, 6), "loop_nodes": (None, 2),
                  "loop_measured": (None, 4, 4), "loop_covariance": (None, 6, 6), "loop_stamps": (None, 2),
                  "loop_chi2": (None,), "up_stamps": (None,), "up_nodes": (None,), "up_body": (None, 3),
                  "up_world": (3,)}
        for name, shape in shapes.items():
            arr = data.get(name)
            if arr is None or arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape,
                                                                                                    strict=True)):
                raise bad(f"{name} of shape {None if arr is None else arr.shape}; expected {shape} (None: any)")
            if arr.dtype.kind not in "fi" or not (np.isfinite(arr).all() or name == "up_world"):
                raise bad(f"{name} holds non-numbers or NaN/inf")
        if not np.allclose(data["base_T_lidar"], self.config.base_T_lidar, atol=1e-9):
            raise bad(f"saved with base_T_lidar {_show(data['base_T_lidar'])}, but this back end has "
                      f"{_show(self.config.base_T_lidar)}; loops from another extrinsic would not fit its graph")
        n, k, nl = len(data["stamps"]), len(data["node_index"]), len(data["loop_nodes"])
        idx = data["node_index"]
        if (len(data["odometry"]) != n or len(data["node_estimate"]) != k
                or len(data["step_covariance"]) != max(k - 1, 0)
                or (k and (idx[0] != 0 or np.any(np.diff(idx) <= 0) or idx[-1] >= n))
                or np.any(np.diff(data["stamps"]) <= 0) or (n and not k)
                or any(len(data[f"loop_{s}"]) != nl for s in ("measured", "covariance", "stamps", "chi2"))
                or (nl and (data["loop_nodes"].min() < 0 or data["loop_nodes"].max() >= k))
                or len(data["up_nodes"]) != len(data["up_stamps"]) or len(data["up_body"]) != len(data["up_stamps"])
                or (len(data["up_nodes"]) and (data["up_nodes"].min() < 0 or data["up_nodes"].max() >= k))
                or not (np.isfinite(data["up_world"]).all() or np.isnan(data["up_world"]).all())):
            raise bad(f"inconsistent arrays ({n} odometry stamps, {k} nodes, {nl} loops); the file is damaged")
        try:
            counters = json.loads(str(data["counters"]))
            rejected, refused = int(counters["rejected"]), {str(a): int(b) for a, b in counters["refused"].items()}
            redundant = int(counters.get("redundant", 0))
        except (KeyError, ValueError, TypeError, AttributeError) as err:
            raise bad(f"counters cannot be read ({err})") from err
        gt = self._gtsam
        self._stamps.extend(data["stamps"].astype(np.float64))
        self._odom.extend(data["odometry"].astype(np.float64))
        if k == 0:
            return
        self._add_first_node(0)
        for row, cov, estimate in zip(idx[1:], data["step_covariance"], data["node_estimate"][1:], strict=True):
            self._add_node(int(row), step_cov=cov, initial=estimate)
        graph, values = gt.NonlinearFactorGraph(), gt.Values()
        for (parent, child), measured, cov, stamps, chi2 in zip(
                data["loop_nodes"], data["loop_measured"], data["loop_covariance"], data["loop_stamps"],
                data["loop_chi2"], strict=True):
            gtsam_cov = to_gtsam_covariance(cov, measured[:3, :3])
            graph.add(gt.BetweenFactorPose3(int(parent), int(child), _pose3(gt, measured), self._loop_noise(gtsam_cov)))
            self._remember(_Loop(int(parent), int(child), measured.copy(), cov.copy(),
                                 (float(stamps[0]), float(stamps[1])), float(chi2),
                                 _to_world(gtsam_cov, self._node_odom(int(child)))))
        self._ups = [(float(t), int(n), b.copy()) for t, n, b in zip(data["up_stamps"], data["up_nodes"],
                                                                       data["up_body"], strict=True)]
        if np.isfinite(data["up_world"]).all():
            self._up_world = data["up_world"] / np.linalg.norm(data["up_world"])
            if self.config.up_sigma_deg > 0:
                self._add_world_up(graph, values, self._up_world)
                for _, n, b in self._ups:
                    self._add_up_factor(graph, n, b, self._up_world)
        self._update(graph, values)
        for _ in range(max(self.config.loops.iterations, 1)):
            self._update()
        self._rejected, self._redundant, self._refused = rejected, redundant, Counter(refused)
        self._refresh()


# ============================================================================ helpers
def chi2_quantile_6dof(probability: float) -> float:
    """The chi-square quantile of 6 degrees of freedom: ``x`` with ``P(chi2_6 <= x) = probability``.

    Its CDF has a closed form for an even number of degrees of freedom,
    ``1 - exp(-x/2) (1 + x/2 + (x/2)^2 / 2)``, inverted here by bisection (no scipy needed).
    """
    if not 0 < probability < 1:
        raise BackendError(f"probability={probability!r}; expected a number in (0, 1)", reason="bad option")

    def cdf(x: float) -> float:
        h = x / 2.0
        return 1.0 - math.exp(-h) * (1.0 + h + h * h / 2.0)

    lo, hi = 0.0, 1.0
    while cdf(hi) < probability:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < probability else (lo, mid)
    return 0.5 * (lo + hi)


def _import_gtsam() -> Any:
    try:
        import gtsam
    except ImportError as exc:
        raise BackendError(f"gtsam is not installed ({exc}); the back end needs it: pip install gtsam",
                           reason="no gtsam") from exc
    return gtsam


def _pose3(gt: Any, matrix: np.ndarray) -> Any:
    return gt.Pose3(np.ascontiguousarray(matrix, np.float64))


def _show(value: Any) -> str:
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return repr(value)
    return np.array2string(arr, precision=4, max_line_width=200, threshold=64).replace("\n", "")


def _rotation_angle(r: np.ndarray) -> float:
    return math.radians(float(rotation_angle_deg(r)))


def _rotation_to(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the z axis to the unit vector ``up``."""
    axis = np.cross([0.0, 0.0, 1.0], up)
    s, c = float(np.linalg.norm(axis)), float(up[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(axis / s * math.atan2(s, c))


def _adjoint(pose: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 adjoint in its (rot, trans) tangent order: [[R, 0], [[t]x R, R]]."""
    r, t = pose[:3, :3], pose[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = r
    out[3:, :3] = skew(t) @ r
    return out


def _to_world(gtsam_cov: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """A covariance in ``pose``'s right tangent (GTSAM) as a left, world-frame one: Ad C Ad^T."""
    ad = _adjoint(pose)
    return ad @ gtsam_cov @ ad.T


def _compose_covariance(cov: np.ndarray, before: np.ndarray, rel: np.ndarray, after: np.ndarray) -> np.ndarray:
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


def config_dict(config: BackendConfig) -> dict[str, Any]:
    """A JSON-ready summary of a config (reports, benchmarks)."""
    out: dict[str, Any] = {name: asdict(getattr(config, name)) for name in ("keyframes", "odometry", "loops")}
    out.update(base_T_lidar=np.asarray(config.base_T_lidar).tolist(), prior_sigma=config.prior_sigma,
               relinearize_threshold=config.relinearize_threshold,
               relinearize_translation=config.relinearize_translation, wildfire_threshold=config.wildfire_threshold,
               factorization=config.factorization,
               level_sigma_deg=config.level_sigma_deg,
               gravity_sigma_deg=config.gravity_sigma_deg, up_sigma_deg=config.up_sigma_deg,
               up_warmup_m=config.up_warmup_m, up_world_sigma_deg=config.up_world_sigma_deg)
    return out

