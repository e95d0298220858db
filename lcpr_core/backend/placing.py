"""Placing sessions in the map frame: the part of :class:`~lcpr_core.backend.PoseGraphBackend` that keeps
inter-session loops waiting, finds which agree (:mod:`.anchoring`), anchors, re-anchors and un-anchors.

A mixin of the graph, apart because it is a job of its own: it reads the graph's sessions, loops and
estimates and asks the graph to rebuild itself (docs/sessions.md, *How a session is anchored*).
"""
from __future__ import annotations

import time
from collections import Counter
from typing import TYPE_CHECKING, Any

import numpy as np

from ..geometry import invert
from .anchoring import implied_transform, invert_measurement, max_clique, pair_statistic
from .session import Loop, Session, Waiting

if TYPE_CHECKING:
    from .config import BackendConfig

__all__ = ["ANCHORS", "INTER_ACCEPTED", "INTER_CONTRADICTING", "INTER_DROPPED", "INTER_UNPLACED", "INTER_WAITING",
           "INTER_WITHDRAWN", "REANCHORS", "UNANCHORS", "SessionPlacing"]

# what became of inter-session loops (BackendStats.inter_session)
INTER_ACCEPTED = "accepted"  # in the graph
INTER_WAITING = "waiting"  # kept as evidence until their session is placed
INTER_CONTRADICTING = "contradicting the anchor"  # refused against their session's anchor (kept a while)
INTER_UNPLACED = "between unplaced sessions"  # neither end placed yet: kept until one is
INTER_DROPPED = "dropped"  # the oldest waiting loop once max_waiting is reached
INTER_WITHDRAWN = "withdrawn"  # in the graph once, taken out when their session's anchor moved
ANCHORS = "anchors"  # a session placed in the map frame
REANCHORS = "re-anchors"  # an anchor moved by a larger agreeing set of loops
UNANCHORS = "un-anchors"  # a session that lost every loop to the map with another session's anchor


class SessionPlacing:
    """Inter-session loops before and against an anchor (mixed into PoseGraphBackend)."""

    if TYPE_CHECKING:  # what it uses of the graph
        config: BackendConfig
        _sessions: dict[str, Session]
        _key_session: list[Session]
        _loops: list[Loop]
        _unplaced: list[tuple[Loop, np.ndarray]]
        _inter: Counter[str]
        _isam: Any
        _agree: float
        _threshold: float
        _rejected: int
        _last_anchor_s: float | None

        def _travel(self, key: int) -> float: ...
        def _node_estimates(self) -> np.ndarray: ...
        def _path_covariances(self, a: int, targets: list[int], *,
                              sessions: list[Session] | None = None) -> list[np.ndarray | None]: ...
        def _chi2(self, parent: int, child: int, measured: np.ndarray, gtsam_cov: np.ndarray) -> float: ...
        def _insert(self, loop: Loop, gtsam_cov: np.ndarray) -> None: ...
        def _rebuild(self, values: np.ndarray) -> None: ...
        def _rebuild_chain(self, s: Session) -> None: ...
        def _rebuild_loop_covariances(self) -> None: ...

    def _waiting_of(self, loop: Loop, gtsam_cov: np.ndarray, *, free_is_child: bool) -> Waiting:
        if free_is_child:
            return Waiting(loop, fixed=loop.parent, free=loop.child, measured=loop.measured, cov=gtsam_cov)
        z, cov = invert_measurement(loop.measured, gtsam_cov)
        return Waiting(loop, fixed=loop.child, free=loop.parent, measured=z, cov=cov)

    def _wait(self, loop: Loop, gtsam_cov: np.ndarray) -> bool:
        """An inter-session loop with an end in a session not yet placed: evidence for placing it."""
        qs, ms = self._key_session[loop.child], self._key_session[loop.parent]
        if not qs.anchored and not ms.anchored:
            self._unplaced.append((loop, gtsam_cov))
            excess = len(self._unplaced) - self.config.sessions.max_waiting
            if excess > 0:
                del self._unplaced[:excess]
                self._inter[INTER_DROPPED] += excess
            return False
        free = ms if qs.anchored else qs
        self._push(free, self._waiting_of(loop, gtsam_cov, free_is_child=free is qs), contradicting=False)
        return self._try_anchor(free, contradicting=False)

    def _contradict(self, loop: Loop, gtsam_cov: np.ndarray) -> None:
        """An inter-session loop the consistency check refused: evidence against its session's anchor."""
        qs, ms = self._key_session[loop.child], self._key_session[loop.parent]
        free = ms if qs.root or (not ms.root and ms.code > qs.code) else qs
        self._inter[INTER_CONTRADICTING] += 1
        self._push(free, self._waiting_of(loop, gtsam_cov, free_is_child=free is qs), contradicting=True)
        self._try_anchor(free, contradicting=True)

    def _push(self, s: Session, item: Waiting, *, contradicting: bool) -> None:
        """Add ``item`` to ``s``'s waiting (or contradicting) loops with its agreement with every one of them (the
        oldest dropped first, counted, beyond ``sessions.max_waiting``)."""
        pool, agree = s.pool(contradicting=contradicting)
        if len(pool) >= self.config.sessions.max_waiting:
            pool.pop(0)
            agree.pop(0)
            for row in agree:
                row.pop(0)
            self._inter[INTER_DROPPED] += 1
        row = self._agreement(s, pool, item)
        for r, ok in zip(agree, row, strict=True):
            r.append(ok)
        agree.append([*row, True])
        pool.append(item)

    def _agreement(self, s: Session, pool: list[Waiting], item: Waiting) -> list[bool]:
        """Whether ``item`` agrees with each member of ``pool`` (:func:`.anchoring.pair_statistic`)."""
        if not pool:
            return []
        placed = [o for o in self._sessions.values() if o.anchored and o is not s]
        a_covs = self._path_covariances(item.fixed, [w.fixed for w in pool], sessions=placed)
        b_covs = self._path_covariances(item.free, [w.free for w in pool], sessions=[s])
        est = self._isam.calculateEstimatePose3
        x_a, e_b = est(item.fixed).matrix(), est(item.free).matrix()
        out = []
        for w, a_cov, b_cov in zip(pool, a_covs, b_covs, strict=True):
            if a_cov is None or b_cov is None or w.fixed == item.fixed and w.free == item.free:
                out.append(w.fixed == item.fixed and w.free == item.free)
                continue
            # pair (w, item): i = w, j = item; covariances in the item's tangents
            stat = pair_statistic(z_i=w.measured, cov_i=w.cov, z_j=item.measured, cov_j=item.cov,
                                  a_rel=invert(est(w.fixed).matrix()) @ x_a, a_cov=a_cov,
                                  b_rel=invert(est(w.free).matrix()) @ e_b, b_cov=b_cov)
            out.append(stat <= self._agree)
        return out

    def _try_anchor(self, s: Session, *, contradicting: bool) -> bool:
        """Place (or move) ``s`` on the largest agreeing set of its waiting (contradicting) loops once it is large
        and spread enough (and, to move an anchor, larger than the loops holding it); True when the newest
        loop is among those placing it."""
        policy = self.config.sessions
        pool, agree = s.pool(contradicting=contradicting)
        if len(pool) < policy.min_loops:
            return False
        support = sum(1 for lp in self._loops if self._is_between(lp, s)) if contradicting else 0
        clique = max_clique(np.array(agree, bool))
        if len(clique) < policy.min_loops or len(clique) <= support:
            return False
        travel = [self._travel(pool[i].free) for i in clique]
        if max(travel) - min(travel) < policy.min_spread_m:
            return False
        newest = len(pool) - 1 in clique
        self._anchor(s, [pool[i] for i in clique], contradicting=contradicting)
        return newest

    def _is_between(self, loop: Loop, s: Session) -> bool:
        """Whether ``loop`` joins ``s`` to another session."""
        a, b = self._key_session[loop.parent], self._key_session[loop.child]
        return a is not b and s in (a, b)

    def _anchor(self, s: Session, members: list[Waiting], *, contradicting: bool) -> None:
        """Place ``s`` in the map frame on ``members`` (loops that agree): the graph rebuilt with ``s``'s nodes
        moved by the transform the members imply and their factors in; the other loops of the pool left to
        contradict it. When ``s`` was placed already its loops to other sessions are withdrawn first."""
        tic = time.perf_counter()
        est = self._node_estimates()
        moves = [implied_transform(est[w.fixed], w.measured, est[w.free]) for w in members]
        spread = [sum(float(np.linalg.norm(m[:3, 3] - o[:3, 3])) for o in moves) for m in moves]
        move = moves[int(np.argmin(spread))]  # the medoid
        if s.anchored:
            kept = [lp for lp in self._loops if not self._is_between(lp, s)]
            self._inter[INTER_WITHDRAWN] += len(self._loops) - len(kept)
            self._inter[REANCHORS] += 1
            self._loops = kept
        else:
            self._inter[ANCHORS] += 1
        chosen = {id(w) for w in members}
        rest = [w for w in s.pool(contradicting=contradicting)[0] if id(w) not in chosen]
        if not contradicting:  # the waiting loops that disagree with the anchor: kept as evidence against it
            self._inter[INTER_CONTRADICTING] += len(rest)
            rest = s.contradicting + rest
        s.waiting, s.waiting_agree, s.contradicting, s.contradicting_agree = [], [], [], []
        s.anchored = True
        for w in rest:  # their agreement judged again, against one another only
            self._push(s, w, contradicting=True)
        values = est.copy()
        values[s.keys] = move @ est[s.keys]
        for w in members:
            w.loop.chi2 = 0.0
            self._loops.append(w.loop)
        self._inter[INTER_ACCEPTED] += len(members)
        s.anchors += 1
        s.anchored_stamp = float(s.stamps.view()[-1])
        self._rebuild(values)
        s.frame = s.newest @ invert(s.node_odom(-1))
        self._rebuild_chain(s)
        self._rebuild_loop_covariances()
        self._last_anchor_s = time.perf_counter() - tic
        unplaced, self._unplaced = self._unplaced, []
        for loop, gtsam_cov in unplaced:  # loops waiting for either end to be placed
            self._resubmit(loop, gtsam_cov)

    def _resubmit(self, loop: Loop, gtsam_cov: np.ndarray) -> None:
        qs, ms = self._key_session[loop.child], self._key_session[loop.parent]
        if not (qs.anchored and ms.anchored):
            self._wait(loop, gtsam_cov)
            return
        chi2 = self._chi2(loop.parent, loop.child, loop.measured, gtsam_cov)
        loop.chi2 = chi2
        if chi2 <= self._threshold:
            self._insert(loop, gtsam_cov)
            self._inter[INTER_ACCEPTED] += 1
        else:
            self._rejected += 1
            self._contradict(loop, gtsam_cov)

    def _unanchor_cut_off(self) -> None:
        """Sessions anchored only through loops that were withdrawn no longer reach the map: each goes back to
        unanchored (counted), held where it is, so that no part of the graph floats free."""
        group = {s.name: s.name for s in self._sessions.values()}

        def find(name: str) -> str:
            while group[name] != name:
                group[name] = group[group[name]]
                name = group[name]
            return name

        for lp in self._loops:
            a, b = find(self._key_session[lp.parent].name), find(self._key_session[lp.child].name)
            group[a] = b
        mapped = {find(s.name) for s in self._sessions.values() if s.root or s.held}
        for s in self._sessions.values():
            if s.anchored and not (s.root or s.held) and find(s.name) not in mapped:
                s.anchored = False
                self._inter[UNANCHORS] += 1
