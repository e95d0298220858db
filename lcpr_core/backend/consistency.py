"""The consistency check a loop passes before it enters the graph: a chi-square test against the estimate.

The loop's residual ``r`` against the current estimate of its two nodes is weighed by ``S = C_loop + C_rel``,
``C_rel`` the covariance of the two nodes' relative pose along the least uncertain path through the graph
(odometry stretches and loops already accepted, each moved into the world frame). A single path bounds the
true marginal from above, so a true loop is not rejected for an over-confident graph, and the check costs a
small Dijkstra over the loops' end nodes instead of a solve. docs/backend.md, *How the graph is built*, says
why this test and not pairwise consistency between loops.
"""
from __future__ import annotations

import heapq
import math

import numpy as np

from ..errors import BackendError
from ..geometry import invert, skew

__all__ = ["adjoint", "chi2_quantile_6dof", "mahalanobis_squared", "path_covariances", "relative_covariance",
           "to_world"]

PATH_LENGTH_M = 10.0  # a radian of relative-pose uncertainty weighs as much as 10 m when choosing the path


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


def mahalanobis_squared(residual: np.ndarray, loop_cov: np.ndarray, relative_cov: np.ndarray) -> float:
    """``r^T S^-1 r`` with ``S = loop_cov + relative_cov`` (GTSAM order): the statistic the gate compares."""
    return float(residual @ np.linalg.solve(loop_cov + relative_cov, residual))


def adjoint(pose: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 adjoint in its (rot, trans) tangent order: [[R, 0], [[t]x R, R]]."""
    r, t = pose[:3, :3], pose[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = r
    out[3:, :3] = skew(t) @ r
    return out


def to_world(gtsam_cov: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """A covariance in ``pose``'s right tangent (GTSAM) as a left, world-frame one: Ad C Ad^T."""
    ad = adjoint(pose)
    return ad @ gtsam_cov @ ad.T


def relative_covariance(a: int, b: int, *, cumulative: np.ndarray, loop_ends: np.ndarray,
                        loop_world_cov: np.ndarray, odom_b: np.ndarray,
                        breaks: np.ndarray | None = None) -> np.ndarray | None:
    """GTSAM-order covariance of ``X_a^-1 X_b`` (in b's tangent) along the least uncertain path.

    ``cumulative``: (K, 6, 6) prefix sums of the world-frame covariances of the odometry steps between nodes;
    ``loop_ends``: (L, 2) nodes of the accepted loops and ``loop_world_cov`` their (L, 6, 6) world-frame
    covariances; ``odom_b``: node ``b``'s pose in that world frame, into whose tangent the result is moved.
    Several sessions: their nodes follow one another in ``cumulative`` and ``breaks`` (sorted) holds the
    position of each session's first node but the first session's; no odometry stretch crosses one, so
    sessions join only through loops. None when no path joins ``a`` and ``b``.
    """
    return path_covariances(a, np.array([b]), cumulative=cumulative, loop_ends=loop_ends,
                            loop_world_cov=loop_world_cov, poses=odom_b[None], breaks=breaks)[0]


def path_covariances(a: int, targets: np.ndarray, *, cumulative: np.ndarray, loop_ends: np.ndarray,
                     loop_world_cov: np.ndarray, poses: np.ndarray,
                     breaks: np.ndarray | None = None) -> list[np.ndarray | None]:
    """:func:`relative_covariance` from ``a`` to each of ``targets`` (T,) at once (one path search), each
    moved into its target's tangent by its pose in ``poses`` (T, 4, 4)."""
    cuts = np.zeros(0, np.int64) if breaks is None else np.asarray(breaks, np.int64)
    targets = np.asarray(targets, np.int64)

    def segment(x: np.ndarray) -> np.ndarray:
        return np.searchsorted(cuts, x, side="right")

    def moved(total: np.ndarray, pose: np.ndarray) -> np.ndarray:
        to_b = adjoint(invert(pose))
        return to_b @ total @ to_b.T

    if not len(loop_ends):
        same = segment(targets) == segment(np.array([a]))[0]
        return [moved(cumulative[max(a, int(b))] - cumulative[min(a, int(b))], pose) if ok else None
                for b, pose, ok in zip(targets, poses, same, strict=True)]
    ends = np.unique(np.concatenate([[a], targets, loop_ends.ravel()]))  # E sorted nodes
    # edges: the odometry stretches between consecutive ends of one session, then the loops; covariances E' x 6 x 6
    tail = np.searchsorted(ends, loop_ends)  # L x 2 slots
    along = np.flatnonzero(segment(ends[:-1]) == segment(ends[1:]))  # stretches within a session
    first = np.concatenate([along, tail[:, 0]])
    second = np.concatenate([along + 1, tail[:, 1]])
    covs = np.concatenate([cumulative[ends[along + 1]] - cumulative[ends[along]], loop_world_cov])
    # the path's length: trace of the covariance, a radian weighing as PATH_LENGTH_M metres (in the first
    # target's tangent; the choice of path, not its covariance, depends on it)
    to_first = adjoint(invert(poses[0]))
    weight = to_first.T @ np.diag([PATH_LENGTH_M**2] * 3 + [1.0] * 3) @ to_first
    costs = np.maximum(np.einsum("eij,ij->e", covs, weight), 0.0).tolist()
    adjacency: list[list[tuple[int, int]]] = [[] for _ in ends]
    for e, (i, j) in enumerate(zip(first.tolist(), second.tolist(), strict=True)):
        adjacency[i].append((j, e))
        adjacency[j].append((i, e))
    start = int(np.searchsorted(ends, a))
    goals = {int(g) for g in np.searchsorted(ends, targets)}
    best = [math.inf] * len(ends)
    via: list[int] = [-1] * len(ends)
    best[start] = 0.0
    heap = [(0.0, start)]
    left = set(goals)
    while heap and left:
        d, i = heapq.heappop(heap)
        if d > best[i]:
            continue
        left.discard(i)
        for j, e in adjacency[i]:
            nd = d + costs[e]
            if nd < best[j]:
                best[j], via[j] = nd, e
                heapq.heappush(heap, (nd, j))
    out: list[np.ndarray | None] = []
    for b, pose in zip(targets, poses, strict=True):
        goal = int(np.searchsorted(ends, b))
        if not math.isfinite(best[goal]):
            out.append(None)
            continue
        path: list[int] = []
        i = goal
        while i != start:
            e = via[i]
            path.append(e)
            i = int(first[e]) if int(second[e]) == i else int(second[e])
        total = covs[path].sum(axis=0) if path else np.zeros((6, 6))  # 6 x 6
        out.append(moved(total, pose))
    return out
