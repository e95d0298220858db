"""The evaluation report: its JSON file and the console tables (both protocols, latency, verified loops).

Retrieval is judged by the radius rule (it has no pose); verified loops by their poses
(:mod:`lcpr_core.loop_report`): right pose within the radius, right pose beyond it (a valid
constraint) and wrong pose, with the precision over those.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..atomic import atomic_path
from ..loop_report import POSE_OK_DEG, POSE_OK_M, LoopScore
from .latency import LatencyStats
from .protocols import GroundTruth, OperatingPoint, ProtocolResult
from .results import MethodResult, VerifiedLoops


class BackendSummary(Protocol):
    """What the report needs of a pose-graph back end's run (lcpr_core.backend.replay.BackendEvaluation has it):
    typed here, so that the evaluation does not import the back end that consumes the detectors."""

    @property
    def odometry_name(self) -> str: ...  # what made the odometry
    def to_dict(self) -> dict[str, Any]: ...  # report.json's "backend"
    def text(self) -> str: ...  # its console lines
    def write_plot(self, path: str | os.PathLike[str], *, title: str) -> None: ...  # backend.png


@dataclass
class StageTimes:
    """Where an evaluation's run went, in seconds (``lcpr_eval`` prints each one's share of ``run``): the network
    thread, the main thread's parts (they add up to about ``run``) and the verification workers."""

    run: float = 0.0  # the frames read and through the detector (EvaluationReport.detect_time_s)
    describe: float = 0.0  # the network thread: keyframes decided, preprocessed and described
    store: float = 0.0  # main thread: matched, stored, verification handed over (search+store)
    record: float = 0.0  # main thread: results recorded, with the Scan Context baseline
    read_wait: float = 0.0  # main thread waiting for the bag's frames
    network_wait: float = 0.0  # ... for the network's descriptors
    verify_wait: float = 0.0  # ... for verdicts (and verifying the pairs of a worker that failed)
    workers: int = 0  # verification worker processes running behind the map; 0: verified within "store"
    verify_busy: float = 0.0  # wall seconds the workers spent verifying, all together
    verify_cpu: float = 0.0  # their CPU seconds
    cpu: float = 0.0  # CPU seconds of the evaluating process itself (every thread: main, network, bag reader)
    cores: int = 0  # cores the process may run on

    def text(self) -> str:
        """One line: each stage's share of the run."""
        run = self.run if self.run > 0 else math.nan

        def pct(seconds: float) -> str:
            return f"{100.0 * seconds / run:.0f}%"
        if self.workers:
            verify = (f"{self.workers} verification workers busy {100.0 * self.verify_busy / (run * self.workers):.0f}%"
                      f" (wall {self.verify_busy:.1f} s, CPU {self.verify_cpu:.1f} s)")
        else:
            verify = "verification in the main thread (within search+store)"
        busy = (f"; CPU {(self.cpu + self.verify_cpu) / run:.2f} of {self.cores} cores busy (this process "
                f"{self.cpu:.1f} s, the workers {self.verify_cpu:.1f} s)" if self.cores else "")
        return (f"stages (share of the {self.run:.2f} s run): network thread busy {pct(self.describe)}; {verify}; "
                f"main thread: search+store {pct(self.store)}, recording + Scan Context {pct(self.record)}, waiting "
                f"for the bag {pct(self.read_wait)} / the network {pct(self.network_wait)} / verification "
                f"{pct(self.verify_wait)}{busy}")


@dataclass
class EvaluationReport:
    source: str  # what was evaluated (a bag path)
    settings: dict[str, Any]
    counts: dict[str, Any]  # frames, keyframes, reasons, degraded, reader statistics
    ground_truth: GroundTruth
    methods: list[MethodResult]
    wall_time_s: float = 0.0
    setup_time_s: float = 0.0  # of wall_time_s: building the detector (loading, auto's measurement, graph capture)
    detect_time_s: float = 0.0  # of wall_time_s: the frames read and through the detector (then the evaluation)
    verified: VerifiedLoops | None = None  # LCPR + verification; None when verification was off
    backend: BackendSummary | None = None  # the bag's LiDAR odometry corrected by the back end; None = not run
    stages: StageTimes | None = None  # where the run's time went; None: not measured

    def to_dict(self) -> dict[str, Any]:
        return _jsonable({
            "source": self.source, "settings": self.settings, "counts": self.counts,
            "ground_truth": self.ground_truth.summary(), "wall_time_s": self.wall_time_s,
            "setup_time_s": self.setup_time_s, "detect_time_s": self.detect_time_s,
            "methods": [m.to_dict() for m in self.methods],
            "verified": None if self.verified is None else self.verified.to_dict(),
            "backend": None if self.backend is None else self.backend.to_dict(),
            "stages": self.stages,
        })

    def write_json(self, path: str | os.PathLike[str]) -> None:
        """Write the report (atomically: readers see the old file or the whole new one)."""
        text = json.dumps(self.to_dict(), indent=1, allow_nan=False)
        with atomic_path(path) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(dataclasses.asdict(value))
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def _fmt(value: float | None, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def summary_table(report: EvaluationReport, *, n_values: Sequence[int] = (1, 5, 10)) -> str:
    """A few lines for the console: both protocols and latency, one column per method."""
    gt = report.ground_truth.summary()
    c = report.counts
    lines = [
        f"{c.get('frames', '?')} frames, {c.get('keyframes', '?')} keyframes ({c.get('degraded_keyframes', 0)} with a "
        f"missing camera), {c.get('dropped_clouds', 0)} clouds dropped by the reader; "
        f"{gt['queries_with_true_loop']} keyframes with a true loop (<= {gt['radius']:g} m, >= "
        f"{gt['exclude_recent_s']:g} s older); path {gt['path_length_m']:.0f} m",
    ]
    if gt["split_time"] is None:
        lines.append("database/query: no revisit after more than 2 x radius of driving; protocol not applicable")
    else:
        lines.append(f"database/query: {gt['database_size']} database keyframes (first pass), "
                     f"{gt['query_count']} queries from {gt['split_offset_s']:.1f} s on")
    ns = "/".join(f"@{n}" for n in n_values)
    width = max(14, *(len(m.name) + 2 for m in report.methods))
    head = f"{'':<34}" + "".join(f"{m.name:>{width + 8}}" for m in report.methods)
    rows = [head]

    def row(label: str, cell: Callable[[MethodResult], str]) -> None:
        rows.append(f"{label:<34}" + "".join(f"{cell(m):>{width + 8}}" for m in report.methods))

    def recalls(p: ProtocolResult | None) -> str:
        if p is None or not p.recall_at:
            return "-"
        return " / ".join(_fmt(p.recall_at.get(n), ".2f") for n in n_values)

    row(f"online     Recall{ns}", lambda m: recalls(m.online))
    row("online     max F1 (R at P=1)",
        lambda m: f"{_fmt(m.online.max_f1)} ({_fmt(m.online.recall_at_full_precision, '.2f')})")
    row("online     TP/FP at threshold", lambda m: _op(m.online.operating_point))
    row(f"db/query   Recall{ns}", lambda m: recalls(m.database_query))
    row("db/query   max F1", lambda m: _fmt(None if m.database_query is None else m.database_query.max_f1))
    row("latency    p50 / p90 ms (total)", lambda m: _lat(m.latency.get("total")))
    lines.append("\n".join(rows))
    if report.verified is not None:
        lines.append(verification_table(report))
    return "\n".join(lines)


def throughput_line(report: EvaluationReport) -> str:
    """Keyframes per second through the detector (the bag read and every frame processed) and where a keyframe's
    time went (the first method's stages), beside the setup before and the evaluation after; with
    ``report.stages``, a second line with each stage's share of the run (they overlap)."""
    keyframes = int(report.counts.get("keyframes", 0))
    if not keyframes or report.wall_time_s <= 0:
        return "throughput: no keyframe"
    stages = {k: v for k, v in report.methods[0].latency.items() if k != "total"} if report.methods else {}
    staged = sum(v.mean_ms for v in stages.values()) * keyframes / 1e3
    run = report.detect_time_s if report.detect_time_s > 0 else report.wall_time_s - report.setup_time_s
    after = max(report.wall_time_s - report.setup_time_s - run, 0.0)
    parts = ", ".join(f"{k} {v.mean_ms:.2f}" for k, v in stages.items())
    rest = (f"the other {run - staged:.2f} s: reading the bag (waited for), frames that were not keyframes"
            if run >= staged else f"the stages overlapped by {staged - run:.2f} s (a batch described while the one "
            "before was matched, verified behind them)")
    line = (f"throughput: {keyframes} keyframes in {run:.2f} s = {keyframes / run:.1f} keyframes/s (after "
            f"{report.setup_time_s:.1f} s of setup; then {after:.1f} s of evaluation); per keyframe (mean ms) {parts}; "
            f"{rest}")
    return line if report.stages is None else f"{line}\n{report.stages.text()}"


def _op(point: OperatingPoint | None) -> str:
    if point is None:
        return "-"
    where = "max F1 " if point.source == "max F1" else ""
    return f"{point.true_positives}/{point.false_positives} @ {where}{point.threshold:.3g}"


def _lat(stats: LatencyStats | None) -> str:
    return "-" if stats is None else f"{stats.p50_ms:.1f} / {stats.p90_ms:.1f}"


def verification_table(report: EvaluationReport) -> str:
    """The verified loops beside the retrieval LCPR's online numbers, and the pose-graph line."""
    v = report.verified
    if v is None:
        return ""
    retrieval = next((m for m in report.methods if m.name == "LCPR"), report.methods[0] if report.methods else None)
    left = "LCPR (retrieval)" if retrieval is None else f"{retrieval.name} (retrieval)"
    s = v.score
    radius = report.ground_truth.radius
    by_pose = f"pose {POSE_OK_M:g} m / {POSE_OK_DEG:g} deg" if s.judged_by_pose else f"within {radius:g} m"
    width = max(22, len(v.name) + 2, len(left) + 2, len(by_pose) + 2)
    out = [f"{'':<34}{left:>{width}}{v.name:>{width}}"]

    def row(label: str, a: str, b: str) -> None:
        out.append(f"{label:<34}{a:>{width}}{b:>{width}}")

    point = None if retrieval is None else retrieval.online.operating_point
    row("online     loops (right/wrong)", "-" if point is None else
        f"{point.true_positives + point.false_positives} ({_op(point)})", _verified_loops(s))
    row(f"           right pose <= / > {radius:g} m", "-",
        f"{s.right_within_radius} / {s.right_beyond_radius}" if s.judged_by_pose else "-")
    row("online     precision / recall",
        "-" if point is None else f"{_fmt(point.precision, '.2f')} / {_fmt(point.recall, '.2f')}",
        f"{_fmt(s.headline_precision, '.2f')} / {_fmt(s.recall, '.2f')}")
    row("           right means", f"within {radius:g} m", by_pose)
    row("online     max F1 (R at P=1)",
        "-" if retrieval is None else
        f"{_fmt(retrieval.online.max_f1)} ({_fmt(retrieval.online.recall_at_full_precision, '.2f')})",
        f"{_fmt(v.max_f1)} ({_fmt(v.recall_at_full_precision, '.2f')})")
    row("           swept over", "descriptor distance", "fitness")
    row("loop pose error median m / deg", "-", _err(s.trans_err_median, s.yaw_err_median))
    row("loop pose error p95    m / deg", "-", _err(s.trans_err_p95, s.yaw_err_p95))
    verify = None if retrieval is None else retrieval.latency.get("verify")
    row("latency    p50 / p90 ms (verify)", "-", _lat(verify))
    g = v.pose_graph
    if g is not None:
        out.append(f"pose graph (seeded odometry drift, verified loops as between-factors, {g.robust} kernel): "
                   f"{g.text()}")
    elif v.pose_graph_note:
        out.append(f"pose graph: {v.pose_graph_note}")
    if v.base_T_lidar_source:
        out.append(f"loop poses vs ground truth: base_T_lidar from {v.base_T_lidar_source}")
    return "\n".join(out)


def _verified_loops(s: LoopScore) -> str:
    """'loops (right/wrong)': by pose (and how many cannot be judged), or by the radius rule without poses."""
    if not s.judged_by_pose:
        return f"{s.loops} ({s.correct}/{s.loops - s.correct})"
    unjudged = f", {s.unjudged} no pose" if s.unjudged else ""
    return f"{s.loops} ({s.right_within_radius + s.right_beyond_radius}/{s.wrong_pose}{unjudged})"


def _err(metres: float | None, degrees: float | None) -> str:
    return "-" if metres is None or degrees is None else f"{metres:.3f} / {degrees:.2f}"
