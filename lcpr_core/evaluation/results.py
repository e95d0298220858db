"""What a method produced on a run and how it scored: the retrieval methods (both protocols and their
latency, judged by the radius rule) and the verified loops ("LCPR + verification", scored by
:mod:`lcpr_core.loop_report`: judged by their poses)."""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputShapeError, InvalidValueError
from ..loop_report import (
    LoopScore,
    PoseGraphProof,
    PublishedLoop,
    loop_correct,
    loop_pose_errors,
    loop_pose_right,
    score_loops,
    verified_fitness_sweep,
)
from ..metrics import PRResult
from .latency import LatencyStats, latency_stats
from .protocols import (
    GroundTruth,
    ProtocolResult,
    Retrieve,
    database_query_protocol,
    online_protocol,
    operating_point,
    recall_at_full_precision,
)


@dataclass
class MethodRun:
    """What one method produced on the keyframes of a run (rows in keyframe order)."""

    name: str
    ranked_ids: np.ndarray  # (N, K) keyframe rows of the online candidates, best first, -1 = none
    ranked_distances: np.ndarray  # (N, K), inf = none
    threshold: float | None  # distance under which the method accepts a loop; None = its max-F1 threshold
    timings: list[dict[str, float]] = field(default_factory=list)  # per keyframe, stage -> seconds
    descriptors: np.ndarray | None = None  # (N, D) L2 descriptors for the database/query protocol
    retrieve: Retrieve | None = None  # or a ranked search over rows, for non-L2 distances
    distance: str = "L2"  # what the distances are, for the report


@dataclass
class MethodResult:
    name: str
    distance: str
    online: ProtocolResult
    database_query: ProtocolResult | None
    latency: dict[str, LatencyStats]
    timings: list[dict[str, float]] = field(default_factory=list, repr=False)
    descriptors: np.ndarray | None = field(default=None, repr=False)  # (N, D) per keyframe; not in the JSON

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "distance": self.distance, "online": self.online.to_dict(),
            "database_query": None if self.database_query is None else self.database_query.to_dict(),
            "latency_ms": {stage: dataclasses.asdict(s) for stage, s in self.latency.items()},
        }


def evaluate_method(
    run: MethodRun, gt: GroundTruth, *, n_values: Sequence[int] = (1, 5, 10), warmup: int = 0
) -> MethodResult:
    online = online_protocol(gt, run.ranked_ids, run.ranked_distances, n_values=n_values, threshold=run.threshold)
    if run.threshold is None and online.pr is not None:
        point = operating_point(online.top1_distance, online.top1_correct, online.num_positives,
                                online.pr.max_f1_threshold, source="max F1")
        online = dataclasses.replace(online, operating_point=point)
    has_split = len(gt.database) > 0 and len(gt.queries) > 0
    dbq = None
    if has_split and (run.descriptors is not None or run.retrieve is not None):
        dbq = database_query_protocol(
            gt, descriptors=run.descriptors, retrieve=None if run.descriptors is not None else run.retrieve,
            n_values=n_values,
        )
    return MethodResult(name=run.name, distance=run.distance, online=online, database_query=dbq,
                        latency=latency_stats(run.timings, warmup=warmup), timings=list(run.timings),
                        descriptors=run.descriptors)


# ============================================================================ verified loops
@dataclass(frozen=True)
class VerifiedLoops:
    """"LCPR + verification": each keyframe's verified loop, scored like a published loop.

    ``pr`` sweeps the loops' fitness (a loop is accepted when its fitness is at least
    the threshold); its ``thresholds`` are the negated fitness values (pr_sweep accepts
    at or below a threshold), :attr:`max_f1_min_fitness` gives the fitness itself. A loop
    counts as right as its precision counts it (:func:`lcpr_core.loop_report.verified_loop_right`:
    by pose when poses can be judged).
    """

    name: str
    score: LoopScore  # lcpr_core.loop_report.score_loops of all loops
    pr: PRResult | None  # None: no loop or no positive keyframe
    loops: tuple[PublishedLoop, ...] = field(default=(), repr=False)  # keyframe rows, one loop per query at most
    fitness: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # (L,)
    correct: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)  # (L,) within the radius
    pose_errors: tuple[tuple[float, float] | None, ...] = field(default=(), repr=False)  # (m, deg) or None
    pose_right: tuple[bool | None, ...] = field(default=(), repr=False)  # right pose; None: cannot be judged
    pose_graph: PoseGraphProof | None = None  # the loops in a pose graph over drifted odometry
    pose_graph_note: str = ""  # why there is no pose graph
    base_T_lidar: np.ndarray | None = None  # the extrinsic the ground truth LiDAR poses used
    base_T_lidar_source: str = ""  # where it came from
    # every candidate's verdict by "query-match" keyframe ids (lcpr_offline.verdicts records; not in to_dict)
    verdicts: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)

    @property
    def max_f1(self) -> float | None:
        return None if self.pr is None else self.pr.max_f1

    @property
    def max_f1_min_fitness(self) -> float | None:
        return None if self.pr is None else -self.pr.max_f1_threshold

    @property
    def recall_at_full_precision(self) -> float | None:
        return recall_at_full_precision(self.pr)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, **self.score.to_dict(),
            "max_f1": self.max_f1, "max_f1_min_fitness": self.max_f1_min_fitness,
            "recall_at_full_precision": self.recall_at_full_precision,
            "pr_curve": None if self.pr is None else {
                "min_fitness": -self.pr.thresholds, "precision": self.pr.precision,
                "recall": self.pr.recall, "f1": self.pr.f1,
            },
            "accepted_loops": [
                {"query": loop.query, "match": loop.match, "fitness": float(f), "correct": bool(ok),
                 "trans_err_m": None if err is None else err[0], "yaw_err_deg": None if err is None else err[1],
                 "right_pose": right}
                for loop, f, ok, err, right in zip(self.loops, self.fitness, self.correct, self.pose_errors,
                                                   self._pose_right(), strict=True)
            ],
            "pose_graph": None if self.pose_graph is None else self.pose_graph.to_dict(),
            "pose_graph_note": self.pose_graph_note,
            "base_T_lidar": self.base_T_lidar, "base_T_lidar_source": self.base_T_lidar_source,
        }

    def _pose_right(self) -> tuple[bool | None, ...]:
        return self.pose_right if len(self.pose_right) == len(self.loops) else (None,) * len(self.loops)


def evaluate_verified(
    gt: GroundTruth,
    loops: Sequence[PublishedLoop],
    fitness: Sequence[float],
    *,
    world_T_lidar: np.ndarray | None = None,
    name: str = "LCPR + verification",
) -> VerifiedLoops:
    """Score verified loops (keyframe rows of ``gt``, at most one per query) against ``gt``.

    ``world_T_lidar`` (N, 4, 4) true LiDAR poses (NaN rows: unknown) give the pose errors and judge
    each loop by its pose. The sweep is :func:`~lcpr_core.loop_report.verified_fitness_sweep`: a loop
    right as the precision counts it, positive every keyframe with a true loop and every query of a
    right loop, as the online protocol does.
    """
    loops = tuple(loops)
    fit = np.asarray(fitness, np.float64).reshape(-1)
    if len(fit) != len(loops):
        raise InputShapeError(f"{len(fit)} fitness values for {len(loops)} loops; expected one per loop")
    queries = [loop.query for loop in loops]
    if len(set(queries)) != len(queries):
        raise InvalidValueError("several loops share a query; expected at most one verified loop per keyframe")
    score = score_loops(loops, positions=gt.positions, world_T_lidar=world_T_lidar, has_revisit=gt.has_loop,
                        radius=gt.radius)
    correct = loop_correct(loops, gt.positions, gt.radius)
    pr = verified_fitness_sweep(loops, fit, positions=gt.positions, world_T_lidar=world_T_lidar,
                                has_revisit=gt.has_loop, radius=gt.radius)
    return VerifiedLoops(name=name, score=score, pr=pr, loops=loops, fitness=fit, correct=correct,
                         pose_errors=tuple(loop_pose_errors(loops, world_T_lidar)),
                         pose_right=tuple(loop_pose_right(loops, world_T_lidar)))
