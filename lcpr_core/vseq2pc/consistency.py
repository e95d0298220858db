"""Temporal consistency of verified VSeq2PC loops: a loop is published only when earlier queries agree with it.

A look-alike street of a grid city can register as well as the true place for one query, but it rarely stays
consistent as the camera moves on; the true place does. :class:`ConsistencyGate` keeps the recent queries'
verified camera poses in the map (``world_T_scan @ match_T_query``, before this gate) with their odometry;
a verified candidate of query q keeps ``verified`` only when each of the ``count - 1`` earlier chain members
(the latest query at least ``spacing_m`` of odometry travel before the previous member) has a verified pose
that, chained with the odometry from that query to q, lands within ``max_m`` / ``max_deg`` of the candidate's.
``count`` 1 turns the gate off.

With ``backfill`` (default), the loop a query publishes also confirms its chain members' agreeing poses: an earlier
query that was held back for want of a chain gets its loop then (:meth:`ConsistencyGate.confirm`), late but with the
same evidence, so every query of a consistent stretch has a loop, not only those after its first ``count - 1``.
"""
from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Hashable
from dataclasses import dataclass
from typing import cast

import numpy as np

from ..errors import InvalidValueError
from ..geometry import invert, is_rigid, rotation_angle_deg
from ..verification import ACCEPTED
from .retrieval import ScanMatch

__all__ = ["INCONSISTENT", "ConsistencyConfig", "ConsistencyGate", "map_camera_pose"]

INCONSISTENT = "inconsistent"  # earlier queries did not verify a camera pose that agrees with this one
MAX_GAP_SLACK_M = 10.0  # a chain member more than spacing_m + this before the next one: the chain is broken
MAX_HISTORY = 512  # queries kept at most


@dataclass(frozen=True)
class ConsistencyConfig:
    """count: queries in the chain, this one included (1 = off). max_m / max_deg: how far an earlier query's
    verified camera pose, moved on by odometry, may land from this query's. spacing_m: odometry travel between
    chain members at least (0 = consecutive queries). backfill: a confirmed query confirms its chain members too."""

    # vseq2pc_eval --verify on the validation drive (citysim seed 43, exact depth): the most recall that keeps precision
    # 1.0 with a margin (see lcpr_core.vseq2pc.verify_eval.choose and docs/vseq2pc_verification.md)
    count: int = 4
    max_m: float = 0.5
    max_deg: float = 2.0
    spacing_m: float = 5.0  # the evaluation's queries (every 4th 1.5 m frame) are 6 m apart
    backfill: bool = True  # a published loop also confirms its chain members' agreeing poses (late loops)

    def __post_init__(self) -> None:
        if isinstance(self.count, bool) or not isinstance(self.count, int) or not 1 <= self.count <= 16:
            raise InvalidValueError(f"verify.consistency={self.count!r} (queries in the chain); accepted: an "
                                    "integer in 1..16 (1 = off)")
        if not isinstance(self.backfill, bool):
            raise InvalidValueError(f"verify.consistency_backfill={self.backfill!r}; accepted: true or false")
        if not (np.isfinite(self.max_m) and self.max_m > 0 and np.isfinite(self.max_deg) and self.max_deg > 0):
            raise InvalidValueError(f"verify.consistency_m={self.max_m!r}, verify.consistency_deg={self.max_deg!r}; "
                                    "both must be finite and > 0")
        if not (np.isfinite(self.spacing_m) and self.spacing_m >= 0):
            raise InvalidValueError(f"verify.consistency_spacing={self.spacing_m!r} (m); accepted: a finite value >= 0")


def map_camera_pose(candidate: ScanMatch) -> np.ndarray | None:
    """The query camera's pose in the map (4 x 4: world_T_scan @ match_T_query), None without both."""
    if candidate.pose is None or candidate.match_T_query is None:
        return None
    T = np.asarray(candidate.pose, np.float64) @ np.asarray(candidate.match_T_query, np.float64)
    return T if np.isfinite(T).all() else None


@dataclass
class _Record:
    travel: float  # m of odometry travel (straight lines between successive queries) up to this query
    odom_T_base: np.ndarray  # 4 x 4
    placed: tuple[np.ndarray, ...]  # verified camera poses in the map, 4 x 4 each
    indices: tuple[int, ...] = ()  # each placed pose's index in the caller's list
    scores: tuple[float, ...] = ()  # each placed pose's score (fitness): the best agreeing one is confirmed late
    key: Hashable = None  # the caller's name for the query (returned by confirm)
    payload: object = None  # what admit_all keeps of the query: its candidates as admitted, the verified ones' indices
    confirmed: bool = False  # a loop of this query was confirmed (at its own time or later)


class ConsistencyGate:
    """Keeps the recent queries' verified camera poses; admits a query's candidates that earlier queries confirm.

    Feed every query in stream order (those without candidates too: a gap breaks the chain). Not thread-safe.
    """

    def __init__(self, config: ConsistencyConfig | None = None, *, lidar_T_cam: np.ndarray | None = None) -> None:
        self.config = config if config is not None else ConsistencyConfig()
        L = np.eye(4) if lidar_T_cam is None else np.asarray(lidar_T_cam, np.float64).reshape(4, 4)
        self.lidar_T_cam, self._L_inv = L, invert(L)  # 4 x 4
        self.usable = is_rigid(L)  # extrinsics that are not a rigid transform confirm nothing (never raise in a worker)
        self._history: deque[_Record] = deque(maxlen=MAX_HISTORY)
        # the latest query's chain (newest first) and, per pose of its list, the position in each member's placed
        # poses of the one that agreed (None where the pose was not confirmed): what confirm reads
        self._chain_of_latest: tuple[_Record, ...] = ()
        self._agreed: list[tuple[int, ...] | None] = []

    def reset(self) -> None:
        """Forget the history (a new session: odometry does not chain across it)."""
        self._history.clear()
        self._chain_of_latest, self._agreed = (), []

    def _chain(self, travel: float) -> list[_Record] | None:
        """The count - 1 earlier chain members, newest first; None when the history has no such chain."""
        cfg = self.config
        members: list[_Record] = []
        ref = travel
        records = list(self._history)
        i = len(records) - 1
        while len(members) < cfg.count - 1:
            while i >= 0 and records[i].travel > ref - cfg.spacing_m:
                i -= 1
            if i < 0 or ref - records[i].travel > cfg.spacing_m + MAX_GAP_SLACK_M:
                return None
            members.append(records[i])
            ref = records[i].travel
            i -= 1
        return members

    def admit_poses(self, odom_T_base: np.ndarray | None, placed: list[np.ndarray | None], *,
                    key: Hashable = None, scores: list[float] | None = None) -> list[bool]:
        """Per verified camera pose of this query (4 x 4 in the map, None if unknown): does the chain confirm it?
        Records the query (as ``key``, with each pose's score, e.g. its fitness: of an earlier query's poses that
        agree with a later loop, the best scored is the one confirmed late). A query without odometry resets the
        history (nothing chains across it)."""
        cfg = self.config
        odom = None if odom_T_base is None else np.asarray(odom_T_base, np.float64)
        if odom is None or odom.size != 16 or not is_rigid(odom.reshape(4, 4)) or not self.usable:
            self.reset()
            return [cfg.count <= 1] * len(placed)
        odom = odom.reshape(4, 4)
        placed = [p if p is not None and is_rigid(np.asarray(p, np.float64)) else None for p in placed]
        last = self._history[-1] if self._history else None
        travel = 0.0 if last is None else last.travel + float(np.linalg.norm(odom[:3, 3] - last.odom_T_base[:3, 3]))
        verdicts = [True] * len(placed)
        agreed: list[tuple[int, ...] | None] = [None] * len(placed)
        chain = self._chain(travel) if cfg.count > 1 else []
        if cfg.count > 1:
            for n, pose in enumerate(placed):
                found = None if chain is None or pose is None else [self._agrees(m, odom, pose) for m in chain]
                verdicts[n] = found is not None and all(f is not None for f in found)
                agreed[n] = tuple(f for f in found if f is not None) if verdicts[n] and found else None
        kept = [n for n, p in enumerate(placed) if p is not None]
        poses = tuple(p for p in placed if p is not None)
        score = [0.0] * len(placed) if scores is None else [float(v) for v in scores]
        self._history.append(_Record(travel, odom, poses, tuple(kept), tuple(score[n] for n in kept), key))
        self._chain_of_latest, self._agreed = tuple(chain or ()), agreed
        return verdicts

    def confirm(self, index: int) -> list[tuple[Hashable, int]]:
        """The latest query publishes its pose ``index`` (one that :meth:`admit_poses` admitted): returns, oldest
        first, the chain members it confirms that had no loop yet, as (their key, index in their pose list); with
        ``backfill`` off, none. Each query is returned at most once."""
        return [(member.key, i) for member, i in self._confirm(index)]

    def _confirm(self, index: int) -> list[tuple[_Record, int]]:
        if not self._history:
            return []
        self._history[-1].confirmed = True
        agreed = self._agreed[index] if 0 <= index < len(self._agreed) else None
        if not self.config.backfill or agreed is None:
            return []
        late = []
        for member, position in zip(self._chain_of_latest, agreed, strict=True):
            if not member.confirmed:
                member.confirmed = True
                late.append((member, member.indices[position]))
        return late[::-1]

    def _agrees(self, member: _Record, odom: np.ndarray, pose: np.ndarray) -> int | None:
        """The position of a verified pose of ``member`` that, moved on by the odometry to this query, lands near
        ``pose`` (the best scored such, then the nearest), or None."""
        # the member's camera -> this query's camera, by odometry
        cam_T_cam = self._L_inv @ invert(member.odom_T_base) @ odom @ self.lidar_T_cam
        inv = invert(pose)
        best, best_key = None, (-np.inf, -np.inf)
        for position, earlier in enumerate(member.placed):
            d = inv @ earlier @ cam_T_cam
            m = float(np.linalg.norm(d[:3, 3]))
            rank = (member.scores[position], -m)
            if m <= self.config.max_m and rotation_angle_deg(d[:3, :3]) <= self.config.max_deg and rank > best_key:
                best, best_key = position, rank
        return best

    def admit(self, odom_T_base: np.ndarray | None, candidates: list[ScanMatch]) -> list[ScanMatch]:
        """The query's candidates with those verified but unconfirmed by the chain turned ``INCONSISTENT``."""
        return self.admit_all(odom_T_base, candidates)[0]

    def admit_all(self, odom_T_base: np.ndarray | None, candidates: list[ScanMatch], *, key: Hashable = None
                  ) -> tuple[list[ScanMatch], list[tuple[Hashable, list[ScanMatch]]]]:
        """:meth:`admit`, and the earlier queries whose loop this query's loop (its best confirmed candidate: best
        fitness, then rank) confirms late: (their key, their candidates as admitted then with the confirmed one
        verified again), oldest first."""
        idx = [i for i, c in enumerate(candidates) if c.verified]
        verdicts = self.admit_poses(odom_T_base, [map_camera_pose(candidates[i]) for i in idx], key=key,
                                    scores=[candidates[i].fitness for i in idx])
        out = list(candidates)
        for i, ok in zip(idx, verdicts, strict=True):
            if not ok:
                out[i] = dataclasses.replace(candidates[i], verified=False, verification=INCONSISTENT)
        if self._history:
            self._history[-1].payload = (out, idx)  # what a later confirmation turns verified
        passed = [n for n, ok in enumerate(verdicts) if ok and out[idx[n]].verified]
        if not passed:
            return out, []
        best = max(passed, key=lambda n: (out[idx[n]].fitness, -out[idx[n]].rank))
        late = []
        for member, n in self._confirm(best):
            their, their_idx = cast(tuple[list[ScanMatch], list[int]], member.payload)
            i = their_idx[n]
            again = list(their)
            again[i] = dataclasses.replace(their[i], verified=True, verification=ACCEPTED)
            late.append((member.key, again))
        return out, late
