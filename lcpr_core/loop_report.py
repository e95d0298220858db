"""Scoring published loop closures against ground truth, and what a pose graph makes of them.

One home for the rule lcpr_eval (``lcpr_offline.lcpr_evaluate``) and the demo (``lcpr_ros.demo``)
both report by. Pure numpy; :func:`pose_graph_proof` needs GTSAM (optional, see
:mod:`lcpr_core.posegraph`) and matplotlib for its plot.

A loop is a :class:`PublishedLoop`: indices of the query and match keyframes into
the caller's keyframe arrays, and, when the LiDAR registration produced one, the
query's LiDAR frame expressed in the match's LiDAR frame (``match_T_query``) with
its 6 x 6 covariance (x, y, z, roll, pitch, yaw, in the match LiDAR frame; the
convention of :mod:`lcpr_core.posegraph`).

The rule (:func:`score_loops`):

* a loop is *correct* when the match keyframe's true position lies within
  ``radius`` metres of the query's (keyframes without a finite position never are);
* precision = correct / loops (None when there is no loop): the radius rule, all that
  retrieval alone (loops without a pose) can be judged by;
* a loop with a pose is judged by it (:func:`pose_right`, the one rule for "the right
  pose"): its ``match_T_query`` within :data:`POSE_OK_M` and :data:`POSE_OK_DEG` (the whole
  rotation angle) of the truth. Verified loops fall in three groups: right pose within the
  radius, right pose beyond it (a valid constraint for a pose graph, however far apart) and
  wrong pose (harmful, near or far); a loop whose pose cannot be judged (no pose, or no true
  pose of either keyframe) is in none and counts as not right.
  precision_by_pose = right pose / loops (None when no loop's pose can be judged);
* recall = revisiting queries (``has_revisit``) closed by at least one correct loop /
  revisiting queries (None when the drive has none); several loops of one query
  close it once;
* pose error, over the correct loops that carry a pose (and whose two keyframes have
  a ground-truth pose): :func:`lcpr_core.posegraph.relative_pose_error` of
  ``match_T_query`` against the true ``inv(world_T_lidar[m]) @ world_T_lidar[q]``:
  translation (m) and |yaw| (deg); median and 95th percentile (numpy's linear
  interpolation).
"""
from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputShapeError, InvalidValueError
from .geometry import relative, skew
from .metrics import PRResult, pr_sweep
from .posegraph import (
    DriftModel,
    LoopConstraint,
    PoseGraphConfig,
    ate_rmse,
    drift_odometry,
    lidar_to_body,
    optimize_pose_graph,
    plot_trajectories,
    relative_pose_error,
    rotation_error_deg,
)
from .positives import within_radius

__all__ = [
    "DEFAULT_LOOP_COVARIANCE", "POSE_OK_DEG", "POSE_OK_M", "LoopScore", "PoseGraphProof", "PublishedLoop",
    "covariance_lidar_to_body", "fitness_sweep", "loop_correct", "loop_pose_errors", "loop_pose_right",
    "pose_graph_proof", "pose_right", "score_loops", "verified_fitness_sweep", "verified_loop_right",
]

#: Covariance given to a loop that carries a pose but no covariance: 10 cm in x and y, 5 cm in z,
#: 0.5 deg roll and pitch, 1 deg yaw (what a verified ICP alignment typically claims), in the
#: (x, y, z, roll, pitch, yaw) order of :mod:`lcpr_core.posegraph`.
DEFAULT_LOOP_COVARIANCE = np.diag([
    0.1**2, 0.1**2, 0.05**2, math.radians(0.5) ** 2, math.radians(0.5) ** 2, math.radians(1.0) ** 2,
])
DEFAULT_LOOP_COVARIANCE.flags.writeable = False


@dataclass(frozen=True)
class PublishedLoop:
    """One loop closure a detector published; ``query`` and ``match`` index the keyframe arrays."""

    query: int
    match: int
    match_T_query: np.ndarray | None = None  # (4, 4) query LiDAR frame in the match's; None: no pose
    covariance: np.ndarray | None = None  # (6, 6) of match_T_query (x, y, z, roll, pitch, yaw); None: unknown


@dataclass(frozen=True)
class LoopScore:
    """Published loops against ground truth (the rule of the module docstring)."""

    loops: int  # loops published
    correct: int  # of them, matched within radius
    precision: float | None  # correct / loops; None without loops
    recall: float | None  # closed / true_revisits; None without true revisits
    true_revisits: int  # keyframes with a true revisit (has_revisit.sum())
    closed: int  # revisiting keyframes closed by a correct loop
    trans_err_median: float | None = None  # m, over the correct loops with a pose; None: none
    trans_err_p95: float | None = None
    yaw_err_median: float | None = None  # deg
    yaw_err_p95: float | None = None
    posed: int = 0  # correct loops with a pose and ground truth: the pose-error sample
    wrong_with_true_pose: int = 0  # equals right_beyond_radius; kept for the readers of that report.json key
    right_within_radius: int = 0  # loops within radius whose relative pose is right (pose_right)
    right_beyond_radius: int = 0  # loops beyond radius whose relative pose is right: valid constraints
    wrong_pose: int = 0  # loops whose relative pose is wrong, within the radius or beyond: harmful
    unjudged: int = 0  # loops whose pose cannot be judged (no pose, or no true pose of a keyframe)
    precision_by_pose: float | None = None  # right pose / loops; None when no loop's pose can be judged

    @property
    def judged_by_pose(self) -> bool:
        """Whether the loops' precision is judged by their poses (else by the radius rule alone)."""
        return self.precision_by_pose is not None

    @property
    def headline_precision(self) -> float | None:
        """The precision a verified loop is reported by: by pose when poses can be judged, else by radius."""
        return self.precision_by_pose if self.judged_by_pose else self.precision

    def groups_text(self, radius: float) -> str:
        """The loops in their groups, for a console line (by pose; by the radius rule when none is judged)."""
        if not self.judged_by_pose:
            return f"{self.correct} within {radius:g} m, {self.loops - self.correct} beyond"
        text = (f"{self.right_within_radius} right pose within {radius:g} m, {self.right_beyond_radius} right pose "
                f"beyond {radius:g} m (a valid constraint), {self.wrong_pose} wrong pose")
        return text + (f", {self.unjudged} without a pose to judge" if self.unjudged else "")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


#: A loop's relative pose is right (a valid pose-graph constraint, however far apart its keyframes lie) when it
#: is within this translation (m) and whole rotation angle (deg) of the truth; :func:`pose_right` applies it.
POSE_OK_M, POSE_OK_DEG = 0.3, 2.0


def _index(value: object, n: int, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= int(value) < n:
        raise InputShapeError(f"{what}={value!r}; expected a keyframe index 0..{n - 1}")
    return int(value)


def loop_correct(loops: Sequence[PublishedLoop], positions: np.ndarray, radius: float) -> np.ndarray:
    """(L,) bool: the match lies within ``radius`` m of the query (NaN positions: never)."""
    pos = np.asarray(positions, np.float64)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise InputShapeError(f"positions of shape {pos.shape}; expected (N, 3) (or (N, 2)) keyframe positions")
    if not (isinstance(radius, (int, float, np.floating)) and math.isfinite(radius) and radius > 0):
        raise InvalidValueError(f"radius={radius!r}; expected a positive distance in metres")
    out = np.zeros(len(loops), bool)
    for k, loop in enumerate(loops):
        q = _index(loop.query, len(pos), f"loops[{k}].query")
        m = _index(loop.match, len(pos), f"loops[{k}].match")
        out[k] = bool(within_radius(pos[q] - pos[m], radius))  # NaN positions: not a true loop
    return out


def pose_right(match_T_query: np.ndarray, true_match_T_query: np.ndarray) -> bool:
    """Whether an estimated (4, 4) relative pose is right: its translation within :data:`POSE_OK_M` m of the
    truth's and the rotation between them at most :data:`POSE_OK_DEG` deg (the whole angle, not the yaw alone:
    a handheld sensor tilts, and a pose graph uses all of it). The one rule a loop is judged by its pose by."""
    estimate = np.asarray(match_T_query, np.float64)
    truth = np.asarray(true_match_T_query, np.float64)
    return (relative_pose_error(estimate, truth)[0] <= POSE_OK_M
            and rotation_error_deg(estimate, truth) <= POSE_OK_DEG)


def _estimates_and_truths(
    loops: Sequence[PublishedLoop], world_T_lidar: np.ndarray | None
) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Per loop (its match_T_query, the true one), or None: no pose, no truth, or a keyframe's truth not finite."""
    if world_T_lidar is None:
        return [None] * len(loops)
    truth = np.asarray(world_T_lidar, np.float64)
    if truth.ndim != 3 or truth.shape[1:] != (4, 4):
        raise InputShapeError(f"world_T_lidar of shape {truth.shape}; expected (N, 4, 4) poses or None")
    out: list[tuple[np.ndarray, np.ndarray] | None] = []
    for k, loop in enumerate(loops):
        q = _index(loop.query, len(truth), f"loops[{k}].query")
        m = _index(loop.match, len(truth), f"loops[{k}].match")
        if loop.match_T_query is None or not (np.isfinite(truth[q]).all() and np.isfinite(truth[m]).all()):
            out.append(None)
            continue
        out.append((np.asarray(loop.match_T_query, np.float64), relative(truth[m], truth[q])))
    return out


def loop_pose_errors(
    loops: Sequence[PublishedLoop], world_T_lidar: np.ndarray | None
) -> list[tuple[float, float] | None]:
    """Per loop (translation m, |yaw| deg) of its match_T_query against the truth, or None.

    None: the loop has no pose, ``world_T_lidar`` is None, or either keyframe's true pose is not finite.
    """
    pairs = _estimates_and_truths(loops, world_T_lidar)
    return [None if pair is None else relative_pose_error(*pair) for pair in pairs]


def loop_pose_right(loops: Sequence[PublishedLoop], world_T_lidar: np.ndarray | None) -> list[bool | None]:
    """Per loop whether its relative pose is right (:func:`pose_right`), or None where it cannot be judged
    (as :func:`loop_pose_errors`)."""
    return [None if pair is None else pose_right(*pair) for pair in _estimates_and_truths(loops, world_T_lidar)]


def verified_loop_right(
    loops: Sequence[PublishedLoop], *, positions: np.ndarray, world_T_lidar: np.ndarray | None, radius: float
) -> np.ndarray:
    """(L,) bool: which loops a verified loop's precision counts as right.

    By pose (:func:`loop_pose_right`; a loop that cannot be judged is not right) when any loop's pose can be
    judged; otherwise, with no pose to judge by (retrieval alone, or no true poses), by the radius rule
    (:func:`loop_correct`).
    """
    verdicts = loop_pose_right(loops, world_T_lidar)
    if all(v is None for v in verdicts):
        return loop_correct(loops, positions, radius)
    return np.array([v is True for v in verdicts], bool)


def score_loops(
    loops: Sequence[PublishedLoop],
    *,
    positions: np.ndarray,
    world_T_lidar: np.ndarray | None,
    has_revisit: np.ndarray,
    radius: float,
) -> LoopScore:
    """Precision (by radius and by pose), recall, the pose groups and pose error of ``loops`` (the rule of the
    module docstring).

    positions (N, 3) true keyframe positions (NaN: unknown); world_T_lidar (N, 4, 4) true
    LiDAR poses or None (no pose errors then); has_revisit (N,) bool: the keyframe has a
    true revisit (what recall counts).
    """
    loops = list(loops)
    pos = np.asarray(positions, np.float64)
    revisit = np.asarray(has_revisit)
    if revisit.shape != (len(pos),) or revisit.dtype != bool:
        raise InputShapeError(f"has_revisit of shape {revisit.shape} and dtype {revisit.dtype}; "
                              f"expected ({len(pos)},) bool, one per keyframe")
    if world_T_lidar is not None and np.shape(world_T_lidar)[:1] != (len(pos),):
        raise InputShapeError(f"world_T_lidar of shape {np.shape(world_T_lidar)}; expected ({len(pos)}, 4, 4)")
    correct = loop_correct(loops, pos, radius)
    errors = loop_pose_errors(loops, world_T_lidar)
    verdicts = loop_pose_right(loops, world_T_lidar)
    closed = len({loop.query for loop, ok in zip(loops, correct, strict=True) if ok and revisit[loop.query]})
    true_revisits = int(revisit.sum())
    measured = np.array([e for e, ok in zip(errors, correct, strict=True) if ok and e is not None],
                        np.float64).reshape(-1, 2)
    stats: dict[str, float | None] = dict.fromkeys(
        ("trans_err_median", "trans_err_p95", "yaw_err_median", "yaw_err_p95"))
    if len(measured):
        (t50, y50), (t95, y95) = np.percentile(measured, [50, 95], axis=0)
        stats = {"trans_err_median": float(t50), "trans_err_p95": float(t95),
                 "yaw_err_median": float(y50), "yaw_err_p95": float(y95)}
    n_correct = int(correct.sum())
    right_within = sum(1 for v, ok in zip(verdicts, correct, strict=True) if v is True and ok)
    right_beyond = sum(1 for v, ok in zip(verdicts, correct, strict=True) if v is True and not ok)
    unjudged = sum(1 for v in verdicts if v is None)
    judged = len(loops) - unjudged
    return LoopScore(
        loops=len(loops), correct=n_correct, precision=n_correct / len(loops) if loops else None,
        recall=closed / true_revisits if true_revisits else None, true_revisits=true_revisits, closed=closed,
        posed=len(measured), wrong_with_true_pose=right_beyond, right_within_radius=right_within,
        right_beyond_radius=right_beyond, wrong_pose=judged - right_within - right_beyond, unjudged=unjudged,
        precision_by_pose=(right_within + right_beyond) / len(loops) if judged else None, **stats,
    )


def fitness_sweep(fitness: np.ndarray, correct: np.ndarray, *, num_positives: int, num_queries: int
                  ) -> PRResult | None:
    """Precision-recall of loops swept over their registration fitness (a loop counts when fitness >= t).

    The sweep's thresholds are the negated fitness values (``pr_sweep`` accepts at or
    below a threshold); None without loops.
    """
    fit = np.asarray(fitness, np.float64).reshape(-1)
    if not len(fit):
        return None
    return pr_sweep(-fit, np.asarray(correct, bool), num_positives=num_positives, num_queries=num_queries)


def verified_fitness_sweep(
    loops: Sequence[PublishedLoop],
    fitness: Sequence[float] | np.ndarray,
    *,
    positions: np.ndarray,
    world_T_lidar: np.ndarray | None,
    has_revisit: np.ndarray,
    radius: float,
) -> PRResult | None:
    """Precision-recall of verified loops swept over their fitness, a loop right as their precision counts it.

    Right: :func:`verified_loop_right` (by pose when poses can be judged). Positive: every keyframe with a true
    revisit and every query of a right loop (a right pose beyond the radius closes its query too). Loops with a
    non-finite fitness are left out of the sweep; None without a loop to sweep.
    """
    loops = list(loops)
    fit = np.asarray(fitness, np.float64).reshape(-1)
    if len(fit) != len(loops):
        raise InputShapeError(f"{len(fit)} fitness values for {len(loops)} loops; expected one per loop")
    right = verified_loop_right(loops, positions=positions, world_T_lidar=world_T_lidar, radius=radius)
    positive = np.array(has_revisit, bool, copy=True)
    positive[[loop.query for loop, ok in zip(loops, right, strict=True) if ok]] = True
    keep = np.isfinite(fit)
    return fitness_sweep(fit[keep], right[keep], num_positives=int(positive.sum()), num_queries=len(positive))


# ============================================================================ pose graph
def covariance_lidar_to_body(
    covariance: np.ndarray, match_T_query_lidar: np.ndarray, body_T_lidar: np.ndarray
) -> np.ndarray:
    """The (6, 6) covariance of a LiDAR-frame relative pose as that of the body-frame one.

    Both in the (x, y, z, roll, pitch, yaw) convention of :mod:`lcpr_core.posegraph`
    (errors in the parent frame, rotation on the left, translation added). With
    ``E = body_T_lidar = (R_e, t_e)`` and ``X = match_T_query_lidar = (R, t)``, the
    body pose ``E X E^-1`` moves by ``dtheta_b = R_e dtheta`` and
    ``dt_b = R_e dt + R_e [w]_x dtheta`` with ``w = R R_e^T t_e`` (the lever arm of the
    mount), so ``C_body = J C J^T``, ``J = [[R_e, R_e [w]_x], [0, R_e]]``.
    """
    cov = np.asarray(covariance, np.float64)
    x = np.asarray(match_T_query_lidar, np.float64)
    e = np.asarray(body_T_lidar, np.float64)
    if cov.shape != (6, 6) or x.shape != (4, 4) or e.shape != (4, 4):
        raise InputShapeError(f"covariance {cov.shape}, match_T_query {x.shape}, body_T_lidar {e.shape}; "
                              "expected (6, 6), (4, 4), (4, 4)")
    re, te = e[:3, :3], e[:3, 3]
    w = x[:3, :3] @ re.T @ te
    j = np.zeros((6, 6))
    j[:3, :3] = j[3:, 3:] = re
    j[:3, 3:] = re @ skew(w)
    out = j @ cov @ j.T
    return 0.5 * (out + out.T)


@dataclass(frozen=True)
class PoseGraphProof:
    """ATE of a drifted odometry chain before and after adding the loops to a pose graph."""

    ate_drifted: float  # m, RMSE of the drifted odometry against the truth (no alignment)
    ate_corrected: float  # m, of the optimised trajectory
    ratio: float  # ate_corrected / ate_drifted (1.0 when the drift is 0: a single pose)
    # the same after the rigid transform that fits each best to the truth (Umeyama, as ``evo_ape --align``): drift
    # before the first revisit moves the whole revisited part, which no loop can observe; this leaves it out
    ate_drifted_aligned: float
    ate_corrected_aligned: float
    loops_used: int  # loops added as between-factors (those with a pose)
    drift: DriftModel
    loops_skipped: int = 0  # loops without a pose (not added)
    robust: str = "cauchy"  # m-estimator on the loop factors
    truth: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False, compare=False)
    drifted: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False, compare=False)
    corrected: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False, compare=False)
    loop_pairs: tuple[tuple[int, int], ...] = field(default=(), repr=False, compare=False)  # (query, match) used

    def to_dict(self) -> dict[str, Any]:
        return {
            "ate_drifted": self.ate_drifted, "ate_corrected": self.ate_corrected, "ratio": self.ratio,
            "ate_drifted_aligned": self.ate_drifted_aligned, "ate_corrected_aligned": self.ate_corrected_aligned,
            "loops_used": self.loops_used, "loops_skipped": self.loops_skipped, "robust": self.robust,
            "poses": len(self.truth), "drift": dataclasses.asdict(self.drift),
        }

    def text(self) -> str:
        """One line: ATE before -> after from the first pose, and after the best rigid alignment."""
        aligned = (self.ate_corrected_aligned / self.ate_drifted_aligned if self.ate_drifted_aligned > 0
                   else 1.0)
        return (f"ATE {self.ate_drifted:.2f} m drifted -> {self.ate_corrected:.2f} m with {self.loops_used} loops "
                f"({self.ratio:.0%}); aligned {self.ate_drifted_aligned:.2f} -> {self.ate_corrected_aligned:.2f} m "
                f"({aligned:.0%})")

    def write_plot(self, path: str | os.PathLike[str], *,
                   title: str = "Pose graph with verified loop closures") -> None:
        """Top view of truth, drifted odometry and the optimised trajectory (PNG, atomically)."""
        plot_trajectories(self.truth, self.drifted, self.corrected, path, loops=self.loop_pairs, title=title)


def pose_graph_proof(
    truth_body: np.ndarray,
    loops: Sequence[PublishedLoop],
    *,
    body_T_lidar: np.ndarray,
    drift: DriftModel = DriftModel(seed=0),
    plot: str | os.PathLike[str] | None = None,
    title: str = "Pose graph with verified loop closures",
    config: PoseGraphConfig = PoseGraphConfig(),
) -> PoseGraphProof:
    """What the loops buy a SLAM back end: ATE of drifted odometry before and after a pose graph.

    ``truth_body`` (N, 4, 4) world_T_body keyframe poses are turned into an odometry
    chain by :func:`lcpr_core.posegraph.drift_odometry` with ``drift``: independent
    Gaussian noise on every step of length ``d`` m, std dev (defaults of
    :class:`~lcpr_core.posegraph.DriftModel`) ``0.015 d`` m in x and y, ``0.005 d`` m in
    z, ``0.1 sqrt(d)`` deg in yaw and ``0.01 sqrt(d)`` deg in roll and pitch, seed 0: a
    heading random walk that leaves a straight drive ~1 % of its length off after
    100-300 m and ~2 % after 500 m. Each loop with a pose becomes a
    :class:`~lcpr_core.posegraph.LoopConstraint`: ``match_T_query`` moved from the LiDAR
    to the body frame (:func:`~lcpr_core.posegraph.lidar_to_body` with ``body_T_lidar``),
    its covariance likewise (:func:`covariance_lidar_to_body`; a loop without one, or
    with NaN in it, gets :data:`DEFAULT_LOOP_COVARIANCE`); loops without a pose are
    skipped. The graph is optimised by :func:`~lcpr_core.posegraph.optimize_pose_graph`
    (``config``: a Cauchy kernel on loop factors by default, so a wrong loop costs
    little) and ATE is :func:`~lcpr_core.posegraph.ate_rmse` without alignment (from the true first pose) and
    after the best rigid alignment (what the loops can observe: drift before the first revisit moves the
    revisited part as a whole).
    ``plot``: a path to write the top view (truth, drifted, optimised, loops) to as PNG;
    the returned proof keeps the trajectories, so :meth:`PoseGraphProof.write_plot` can
    draw it later too.

    Raises :class:`~lcpr_core.errors.PoseGraphError` (an ``LcprError``) when GTSAM is not
    installed or the inputs cannot be used; callers catch it and print a note.
    """
    truth = np.asarray(truth_body, np.float64)
    ext = np.asarray(body_T_lidar, np.float64)
    drifted, step_covs = drift_odometry(truth, model=drift)
    constraints: list[LoopConstraint] = []
    skipped = 0
    for loop in loops:
        if loop.match_T_query is None:
            skipped += 1
            continue
        rel_lidar = np.asarray(loop.match_T_query, np.float64)
        cov = None if loop.covariance is None else np.asarray(loop.covariance, np.float64)
        if cov is None or cov.shape != (6, 6) or not np.isfinite(cov).all():
            cov = DEFAULT_LOOP_COVARIANCE
        constraints.append(LoopConstraint(
            query=int(loop.query), match=int(loop.match), match_T_query=lidar_to_body(rel_lidar, ext),
            covariance=covariance_lidar_to_body(cov, rel_lidar, ext),
        ))
    result = optimize_pose_graph(drifted, step_covs, constraints, config=config)
    before = ate_rmse(drifted, truth)
    after = ate_rmse(result.optimized, truth)
    proof = PoseGraphProof(
        ate_drifted=before, ate_corrected=after, ratio=after / before if before > 0 else 1.0,
        ate_drifted_aligned=ate_rmse(drifted, truth, align=True),
        ate_corrected_aligned=ate_rmse(result.optimized, truth, align=True),
        loops_used=len(constraints), drift=drift, loops_skipped=skipped, robust=config.robust,
        truth=truth, drifted=drifted, corrected=result.optimized,
        loop_pairs=tuple((c.query, c.match) for c in constraints),
    )
    if plot is not None:
        proof.write_plot(plot, title=title)
    return proof
