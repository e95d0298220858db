"""One session of the graph: a run of one odometry in its own frame, its nodes and where it sits in the map.

A session keeps every odometry message it was given (stamps increasing within it), the rows that became
graph nodes and their graph keys, the prefix sums of its odometry steps' world-frame covariances (for the
consistency check's path search) and its travel. ``frame`` is ``map_T_odom`` as fixed when it was anchored
(the identity for the session that defines the map frame and for one not yet placed): it moves the session's
covariances into the map frame. Stamp lookups refuse with the reasons :mod:`.graph` counts.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from ..errors import BackendError
from ..geometry import interpolate_poses
from ..growable import GrowableArray

__all__ = ["DEFAULT_SESSION", "LOOP_AHEAD", "LOOP_OLD", "LOOP_UNKNOWN", "MAX_SESSION_NAME", "Loop", "Session",
           "Waiting"]

DEFAULT_SESSION = "session"  # calls without session=, files from before sessions; the detector's default name
MAX_SESSION_NAME = 256  # characters a session name may have

LOOP_UNKNOWN = "loop stamp never seen"
LOOP_OLD = "loop stamp older than the graph"
LOOP_AHEAD = "loop stamp ahead of odometry"


@dataclass
class Loop:
    """A loop as the graph holds it: between two graph nodes, in their base frames."""

    parent: int  # graph key of the match's node
    child: int  # graph key of the query's node
    measured: np.ndarray  # (4, 4) parent_T_child
    covariance: np.ndarray  # (6, 6) ROS order, in the parent node's frame
    stamps: tuple[float, float]  # (query, match) as given
    chi2: float
    world_cov: np.ndarray  # (6, 6) GTSAM order, moved into the map frame (path search)
    sessions: tuple[str, str] = (DEFAULT_SESSION, DEFAULT_SESSION)  # (query, match)


@dataclass
class Waiting:
    """An inter-session loop not (or no longer) in the graph, normalised to ``Z = X_fixed^-1 X_free``."""

    loop: Loop  # as it would enter the graph
    fixed: int  # key of its end in a placed session
    free: int  # key of its end in the session it would place
    measured: np.ndarray  # (4, 4) Z
    cov: np.ndarray  # (6, 6) GTSAM order, the free end's tangent


@dataclass
class Session:
    """Per-session state of :class:`~lcpr_core.backend.PoseGraphBackend` (see the module docstring)."""

    name: str
    code: int
    root: bool = False  # defines the map frame (its first node holds the gauge prior)
    anchored: bool = False
    held: bool = False  # a loaded prior map: every node held at its saved estimate, no new odometry
    frame: np.ndarray = field(default_factory=lambda: np.eye(4))
    stamps: GrowableArray = field(default_factory=lambda: GrowableArray(np.float64))
    odom: GrowableArray = field(default_factory=lambda: GrowableArray(np.float64, (4, 4)))
    keys: list[int] = field(default_factory=list)  # graph key of each node
    node_stamps: list[float] = field(default_factory=list)
    node_index: list[int] = field(default_factory=list)  # odometry row of each node
    cum: GrowableArray = field(default_factory=lambda: GrowableArray(np.float64, (6, 6)))
    step_cov: GrowableArray = field(default_factory=lambda: GrowableArray(np.float64, (6, 6)))  # node k-1 -> k
    travel: list[float] = field(default_factory=list)  # m along the odometry at each node
    newest: np.ndarray = field(default_factory=lambda: np.eye(4))  # estimate of the newest node
    waiting: list[Waiting] = field(default_factory=list)  # loops to a placed session, before it is anchored
    waiting_agree: list[list[bool]] = field(default_factory=list)  # which waiting loops agree pairwise
    contradicting: list[Waiting] = field(default_factory=list)  # loops refused against its anchor
    contradicting_agree: list[list[bool]] = field(default_factory=list)
    anchors: int = 0  # times it was placed (the first anchoring and every move)
    anchored_stamp: float | None = None  # its newest odometry stamp when last anchored

    def pool(self, *, contradicting: bool) -> tuple[list[Waiting], list[list[bool]]]:
        """Its waiting (or contradicting) loops and which of them agree pairwise."""
        if contradicting:
            return self.contradicting, self.contradicting_agree
        return self.waiting, self.waiting_agree

    def node_odom(self, local: int) -> np.ndarray:
        return self.odom.view()[self.node_index[local]]

    def nearest_node(self, t: float) -> tuple[int, float]:
        """(local index of the node nearest in time to ``t``, its distance in s)."""
        i = bisect.bisect_left(self.node_stamps, t)
        near = [j for j in (i - 1, i) if 0 <= j < len(self.node_stamps)]
        node = min(near, key=lambda j: abs(self.node_stamps[j] - t))
        return node, abs(self.node_stamps[node] - t)

    def odom_at(self, t: float, name: str, tolerance: float) -> np.ndarray:
        """The odometry pose at ``t``: interpolated between two messages, or the nearest within ``tolerance``;
        BackendError (reason ``LOOP_OLD`` / ``LOOP_AHEAD`` / ``LOOP_UNKNOWN``) naming the stamp otherwise."""
        stamps, odom = self.stamps.view(), self.odom.view()
        where, suffix = self.where(), self.suffix()
        if t < stamps[0] - tolerance:
            raise BackendError(f"{name}={t!r} is older than {where} (its first odometry stamp is "
                               f"{float(stamps[0])!r})", reason=LOOP_OLD)
        if t > stamps[-1] + tolerance:
            raise BackendError(f"{name}={t!r} is after the newest odometry stamp {float(stamps[-1])!r}{suffix}; "
                               "add the odometry up to that stamp first", reason=LOOP_AHEAD)
        i = int(np.searchsorted(stamps, t))
        if i < len(stamps) and stamps[i] == t:
            return odom[i].copy()
        if i == 0 or i == len(stamps):
            return odom[min(i, len(stamps) - 1)].copy()
        lo, hi = float(stamps[i - 1]), float(stamps[i])
        if min(t - lo, hi - t) > tolerance:
            raise BackendError(f"{name}={t!r} was never seen{suffix}: the odometry around it is at {lo!r} and "
                               f"{hi!r}, both more than loops.stamp_tolerance = {tolerance} s away",
                               reason=LOOP_UNKNOWN)
        w = (t - lo) / (hi - lo)
        return interpolate_poses(odom[i - 1:i], odom[i:i + 1], np.array([w]))[0]

    def where(self) -> str:
        """How messages name the session: "the graph" for a single default session."""
        return "the graph" if self.name == DEFAULT_SESSION else f"session {self.name!r}"

    def suffix(self) -> str:
        return "" if self.name == DEFAULT_SESSION else f" of session {self.name!r}"
