"""Offline evaluation of loop-closure detection: ground truth, two protocols, the report and its plots.

Pure numpy and matplotlib, one module per job: :mod:`.protocols` (ground truth, both protocols),
:mod:`.latency`, :mod:`.results` (per method, verified loops), :mod:`.report` (JSON, console
tables), :mod:`.plots`. The bag-reading driver is ``lcpr_offline.lcpr_evaluate`` (command line:
``lcpr_ros.evaluate``).

Ground truth. Keyframe positions come from odometry (NaN where unknown; such
keyframes are neither queries nor counted as correct matches). Keyframe ``m`` is a
true loop of query ``q`` when ``|p_q - p_m| <= radius`` and ``m`` is at least
``exclude_recent_s`` older: the time rule the detector uses to skip recent keyframes.

Online protocol (what a SLAM back end experiences): every keyframe, in time order,
is a query against all earlier ones (recent ones excluded). Its best candidate is a
true positive when it is a true loop, a false positive otherwise; a query is
positive when it has any true loop. Sweeping the top-1 distance threshold gives the
precision-recall curve, max F1 and the recall at 100 % precision; Recall@N counts
positive queries with a true loop among their N best candidates.

Database/query protocol (the paper's): the first pass of the drive is the
database, later keyframes that revisit it are the queries. The split time ``T`` is
the stamp of the first real revisit: the first keyframe with a true loop reached
after more than ``2 * radius`` metres of driving (a vehicle standing still for
``exclude_recent_s`` does not count). Database: keyframes stamped up to
``T - exclude_recent_s``; queries: keyframes from ``T`` on with a database keyframe
within ``radius`` (others are removed, as in the paper). Every query-database pair
is thus at least ``exclude_recent_s`` apart, so no query is matched by its temporal
neighbours. Descriptors compared by L2 go through :mod:`lcpr_core.metrics`; other
distances (Scan Context) through a ranked retrieval the caller provides.

Verified loops ("LCPR + verification", :func:`evaluate_verified`): with geometric
verification on, each keyframe's loop is the verified candidate with the best
registration fitness (``Result.loop``), or none. They are scored by the rule of
:mod:`lcpr_core.loop_report` (the one the demo uses): judged by their poses, in three
groups (right pose within the radius, right pose beyond it: a valid constraint, wrong
pose: harmful), precision over the loops by pose, recall over the keyframes with a
true loop, relative-pose error against the ground truth; the precision-recall sweep
(max F1, recall at precision 1) uses the fitness of each keyframe's loop as its score
(higher accepts first) and counts a loop right as the precision does. Retrieval has
no pose: the radius rule alone judges it.
"""
from __future__ import annotations

from ..metrics import pr_sweep
from .latency import LatencyStats, latency_stats
from .plots import plot_latency, plot_pr_curves, plot_trajectory
from .protocols import (
    GroundTruth,
    OperatingPoint,
    ProtocolResult,
    Retrieve,
    database_query_protocol,
    ground_truth,
    online_protocol,
    operating_point,
    ranked_protocol,
    recall_at_full_precision,
)
from .report import EvaluationReport, StageTimes, summary_table, throughput_line, verification_table
from .results import MethodResult, MethodRun, VerifiedLoops, evaluate_method, evaluate_verified

__all__ = [
    "GroundTruth", "LatencyStats", "MethodResult", "MethodRun", "OperatingPoint", "ProtocolResult", "Retrieve",
    "EvaluationReport", "StageTimes", "database_query_protocol", "evaluate_method", "ground_truth", "latency_stats",
    "online_protocol", "operating_point", "plot_latency", "plot_pr_curves", "plot_trajectory", "pr_sweep",
    "ranked_protocol", "recall_at_full_precision", "summary_table", "throughput_line", "VerifiedLoops",
    "evaluate_verified", "verification_table",
]
