"""Retrieval alone beside verified loops on a rendered drive (``vseq2pc_eval --verify DRIVE.npz``).

Input: a drive file of benchmarks/tools/vseq2pc_verify_data.py (per frame: pose, LiDAR structure
feature, the scan's compact cloud; per depth variant: camera features and each frame's pseudo-cloud).
Protocol (as :mod:`lcpr_core.vseq2pc.evaluate`'s retrieval): the map is every scan; a query (every
``query_step``-th complete sequence) searches the scans more than ``min_frame_gap`` frames back, top
``k``; it is a *loop query* when such a scan lies within ``loop_radius`` m.

* retrieval alone: each query publishes its most probable candidate; swept over the probability.
* verified: each query's pseudo-cloud (its frames stacked with the poses) is registered against its
  top-k candidates (:class:`~lcpr_core.vseq2pc.verify.SequenceVerifier`, the detector's code); it
  publishes the verified candidate with the best fitness; swept over the fitness.

Correct: a retrieved loop when its scan lies within ``loop_radius`` m of the query; a verified loop when its
match_T_query is within ``max_pose_m`` / ``max_pose_deg`` of the truth inv(world_T_scan) world_T_query
lidar_T_cam (a constraint a back end can use, whatever the scan's distance). Precision = correct /
published; recall = correct loops of loop queries / loop queries.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..atomic import atomic_path, save_figure
from ..errors import InvalidValueError
from ..geometry import rotation_angle_deg
from ..pretrained import default_vseq2pc_weights
from ..verification.clouds import dequantise
from .net import Vseq2pcNet
from .pseudo_cloud import accumulate
from .retrieval import ScanDatabase, ScanMatch, SearchConfig
from .sequence import sequence_table
from .verify import SequenceVerifier, SequenceVerifyConfig, support_counts

__all__ = ["DriveData", "QueryOutcome", "VerifyEvalConfig", "choose", "evaluate_verification", "load_drive",
           "bundled_net", "run", "summary", "sweep", "table"]


@dataclass(frozen=True)
class VerifyEvalConfig:
    k: int = 10
    min_frame_gap: int = 50
    loop_radius: float = 5.0
    query_step: int = 3  # every this-many complete sequence is a query (cost)
    # a verified loop is correct when its camera pose is within these of the truth (a constraint a back end can
    # use, whatever the scan's distance); a retrieved one when its scan lies within loop_radius
    max_pose_m: float = 1.0
    max_pose_deg: float = 3.0

    def __post_init__(self) -> None:
        if self.k < 1 or self.min_frame_gap < 0 or not self.loop_radius > 0 or self.query_step < 1:
            raise InvalidValueError(f"k={self.k} (>= 1), min_frame_gap={self.min_frame_gap} (>= 0), loop_radius="
                                    f"{self.loop_radius} (> 0), query_step={self.query_step} (>= 1)")


@dataclass
class DriveData:
    poses: np.ndarray  # N x 4 x 4 world_T_base
    stamps: np.ndarray  # N
    lidar: np.ndarray  # N x 12 x 360
    scan_clouds: list[np.ndarray]  # N of M x 3
    camera: np.ndarray  # N x 12 x 90 (the variant's)
    valid: np.ndarray  # N
    frame_clouds: list[np.ndarray]  # N of M x 3, vehicle frame (the variant's)
    lidar_T_cam: np.ndarray
    variant: str
    seed: int


def _split(points: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    ends = np.cumsum(counts)
    return [dequantise(points[e - c:e]) for e, c in zip(ends, counts, strict=True)]


def load_drive(path: str, variant: str) -> DriveData:
    """One depth variant of a drive file of benchmarks/tools/vseq2pc_verify_data.py."""
    with np.load(path) as z:
        variants = [str(v) for v in z["variants"]]
        if variant not in variants:
            raise InvalidValueError(f"{path} holds depth variants {variants}; not {variant!r}")
        counts = z[f"{variant}_counts"]
        return DriveData(poses=z["poses"], stamps=z["stamps"], lidar=z["lidar"],
                         scan_clouds=_split(z["scan_points"], z["scan_counts"]), camera=z[f"{variant}_camera"],
                         valid=z[f"{variant}_valid"], frame_clouds=_split(z[f"{variant}_points"], counts),
                         lidar_T_cam=z["lidar_T_cam"], variant=variant, seed=int(z["seed"]))


@dataclass(frozen=True)
class Accepted:
    """A registration the verifier accepted (before the consensus rule), with its support and pose error."""

    fitness: float
    support: int
    correct: bool  # pose within max_pose_m / max_pose_deg of the truth
    error_m: float
    error_deg: float


@dataclass
class QueryOutcome:
    frame: int
    loop_query: bool  # a scan within loop_radius more than min_frame_gap frames back exists
    top: ScanMatch | None  # retrieval alone: the most probable candidate
    top_correct: bool
    accepted: list[Accepted] = field(default_factory=list)
    seconds: float = 0.0  # verification of this query's candidates (pseudo-cloud included)
    reasons: dict[str, int] = field(default_factory=dict)

    def loop(self, min_support: int) -> Accepted | None:
        """The verified loop under the consensus rule ``min_support``: the best fitness among those with support."""
        kept = [a for a in self.accepted if a.support >= min_support]
        return max(kept, key=lambda a: a.fitness) if kept else None


def evaluate_verification(data: DriveData, net: Vseq2pcNet, *, verify: SequenceVerifyConfig | None = None,
                          config: VerifyEvalConfig = VerifyEvalConfig(), scans: DriveData | None = None,
                          progress: bool = True) -> list[QueryOutcome]:
    """Every query's retrieval and verification outcome. ``scans``: another drive as the map (its scans only; the
    frame-gap rule is then off), e.g. a drive that never comes near the query drive."""
    vcfg = replace(verify if verify is not None else SequenceVerifyConfig(), min_support=1)  # consensus: later
    verifier = SequenceVerifier(vcfg)
    mapped = scans if scans is not None else data
    db = ScanDatabase(weights_id=net.weights_id)
    db.add(net.slice_descriptors(mapped.lidar), stamps=mapped.stamps, poses=mapped.poses)
    seqs = sequence_table(data.poses[:, :3, 3], data.valid)
    queries = np.flatnonzero(seqs[:, 0] >= 0)[:: config.query_step]
    d_seq = net.query_descriptors(data.camera[seqs[queries]])
    scan_xy = mapped.poses[:, :2, 3]
    search = SearchConfig(k=config.k, exclude_recent_s=None,
                          exclude_recent_rows=config.min_frame_gap if scans is None else 0)
    out = []
    for qi, frame in enumerate(tqdm(queries.tolist(), desc=f"verify {data.variant}", unit="query",
                                    disable=not progress)):
        rows = None if scans is not None else np.array([frame])
        found = db.search(d_seq[qi], net.descriptor, config=search, rows=rows)[0]
        dist = np.linalg.norm(scan_xy - data.poses[frame, :2, 3], axis=1)
        allowed = np.arange(len(mapped.stamps)) if scans is not None else np.arange(max(frame - config.min_frame_gap,
                                                                                        0))
        loop_query = bool(len(allowed)) and bool((dist[allowed] <= config.loop_radius).any())
        tic = time.perf_counter()
        last = int(seqs[frame, -1])
        frames = [(data.frame_clouds[i], data.poses[i]) for i in range(frame, last + 1)
                  if data.valid[i] and len(data.frame_clouds[i])]
        checked: list[ScanMatch] = []
        if frames:
            query = verifier.prepare_query(accumulate(frames, query_pose=data.poses[frame], config=vcfg.pseudo))
            checked = verifier.verify_all(query, found[: vcfg.top_k], lambda m: mapped.scan_clouds[m.row],
                                          lidar_T_cam=data.lidar_T_cam)
        seconds = time.perf_counter() - tic
        reasons: dict[str, int] = {}
        for c in checked:
            reasons[c.verification] = reasons.get(c.verification, 0) + 1
        top = found[0] if found else None
        outcome = QueryOutcome(frame, loop_query, top, top is not None and dist[top.row] <= config.loop_radius,
                               seconds=seconds, reasons=reasons)
        for c, n in zip(checked, support_counts(checked, vcfg), strict=True):
            if not c.verified or c.match_T_query is None:
                continue
            truth = np.linalg.inv(mapped.poses[c.row]) @ data.poses[frame] @ data.lidar_T_cam
            err_m = float(np.linalg.norm(c.match_T_query[:3, 3] - truth[:3, 3]))
            err_deg = float(rotation_angle_deg((np.linalg.inv(truth) @ c.match_T_query)[:3, :3]))
            right = err_m <= config.max_pose_m and err_deg <= config.max_pose_deg
            outcome.accepted.append(Accepted(c.fitness, n, right, err_m, err_deg))
        out.append(outcome)
    return out


def sweep(outcomes: list[QueryOutcome], *, min_support: int | None = None) -> dict[str, np.ndarray]:
    """Precision and recall of loop queries at every threshold: retrieval alone (``min_support`` None) over the
    probability of the most probable candidate, verified over the fitness of the loop under ``min_support``."""
    loops = max(sum(o.loop_query for o in outcomes), 1)
    pub = []  # (score, correct, counts for recall)
    for o in outcomes:
        if min_support is None:
            if o.top is not None:
                pub.append((o.top.probability, o.top_correct, o.top_correct and o.loop_query))
        else:
            a = o.loop(min_support)
            if a is not None:
                pub.append((a.fitness, a.correct, a.correct and o.loop_query))
    if not pub:
        return {"threshold": np.zeros(0), "precision": np.zeros(0), "recall": np.zeros(0)}
    score = np.array([p[0] for p in pub])
    order = np.argsort(-score, kind="stable")
    ok = np.array([p[1] for p in pub])[order]
    hit = np.array([p[2] for p in pub])[order]
    n = np.arange(1, len(order) + 1)
    return {"threshold": score[order], "precision": np.cumsum(ok) / n, "recall": np.cumsum(hit) / loops}


def choose(outcomes: list[QueryOutcome], *, precision: float = 0.95, supports: tuple[int, ...] = (1, 2, 3, 4)
           ) -> tuple[int, float] | None:
    """(min_support, fitness threshold) with the most recall at ``precision`` on these (validation) queries; None
    when no setting keeps that precision. Ties keep the smaller support."""
    best: tuple[float, int, float] | None = None
    for support in supports:
        s = sweep(outcomes, min_support=support)
        ok = np.flatnonzero(s["precision"] >= precision)
        if not len(ok):
            continue
        i = ok[np.argmax(s["recall"][ok])]
        i = ok[ok >= i][-1] if s["recall"][ok[-1]] == s["recall"][i] else i  # same recall: the lowest threshold
        if best is None or s["recall"][i] > best[0]:
            best = (float(s["recall"][i]), support, float(s["threshold"][i]))
    return None if best is None else (best[1], best[2])


def summary(outcomes: list[QueryOutcome], *, setting: tuple[int, float] | None = None) -> dict[str, Any]:
    """Both methods' numbers; ``setting``: (min_support, fitness threshold) chosen on validation."""
    loops = sum(o.loop_query for o in outcomes)
    out: dict[str, Any] = {"queries": len(outcomes), "loop_queries": loops}
    r = sweep(outcomes)
    f1 = 2 * r["precision"] * r["recall"] / np.maximum(r["precision"] + r["recall"], 1e-12)
    published = [o for o in outcomes if o.top is not None]
    correct = [o for o in published if o.top_correct]
    out["retrieval"] = {"max_f1": float(f1.max()) if len(f1) else 0.0, "published": len(published),
                        "precision": len(correct) / max(len(published), 1),
                        "recall": sum(o.loop_query for o in correct) / max(loops, 1)}
    row: dict[str, Any] = {}
    for support in (1, 2, 3, 4):
        s = sweep(outcomes, min_support=support)
        f = 2 * s["precision"] * s["recall"] / np.maximum(s["precision"] + s["recall"], 1e-12)
        row[f"max_f1_support{support}"] = float(f.max()) if len(f) else 0.0
    if setting is not None:
        support, threshold = setting
        loops_at = [(o, a) for o in outcomes if (a := o.loop(support)) is not None and a.fitness >= threshold]
        good = [(o, a) for o, a in loops_at if a.correct]
        errors_m = np.array([a.error_m for _, a in good])
        errors_deg = np.array([a.error_deg for _, a in good])
        row["at_setting"] = {
            "min_support": support, "threshold": threshold, "published": len(loops_at),
            "precision": len(good) / max(len(loops_at), 1),
            "recall": sum(o.loop_query for o, _ in good) / max(loops, 1),
            "pose_m_median": float(np.median(errors_m)) if len(good) else None,
            "pose_m_p95": float(np.percentile(errors_m, 95)) if len(good) else None,
            "pose_deg_median": float(np.median(errors_deg)) if len(good) else None,
            "pose_deg_p95": float(np.percentile(errors_deg, 95)) if len(good) else None,
            "all_pose_m_median": float(np.median([a.error_m for _, a in loops_at])) if loops_at else None,
        }
        s = sweep(outcomes, min_support=support)
        f = 2 * s["precision"] * s["recall"] / np.maximum(s["precision"] + s["recall"], 1e-12)
        row["max_f1"] = float(f.max()) if len(f) else 0.0
    seconds = np.array([o.seconds for o in outcomes if o.seconds > 0])
    row["verify_ms_p50"] = float(np.median(seconds) * 1e3) if len(seconds) else None
    reasons: dict[str, int] = {}
    for o in outcomes:
        for k, v in o.reasons.items():
            reasons[k] = reasons.get(k, 0) + v
    row["verdicts"] = reasons
    out["verified"] = row
    return out


# -- vseq2pc_eval --verify ------------------------------------------------------------------------------
def bundled_net(variant: str) -> Vseq2pcNet:
    """The bundled weights for the variant's depth: the exact-depth set for exact depth, else the network set."""
    files = default_vseq2pc_weights(depth="exact" if variant == "exact" else "network")
    if files is None:
        raise InvalidValueError("the bundled VSeq2PC weights are missing from this install (weights/)")
    return Vseq2pcNet.from_files(sequence=files[0], descriptor=files[1])


def run(args: argparse.Namespace) -> int:
    """``vseq2pc_eval --verify VAL TEST [--verify-never DRIVE] [--variants ...] [--out DIR]``."""
    val_path, test_path = args.verify
    config = VerifyEvalConfig(k=10, min_frame_gap=args.min_frame_gap, loop_radius=args.loop_radius,
                              query_step=args.query_step)
    sweep_cfg = SequenceVerifyConfig(min_fitness=0.0)  # every registration that passes the other checks; swept
    report: dict[str, Any] = {"validation": val_path, "test": test_path, "never": args.verify_never,
                              "config": asdict(config), "variants": {}}
    curves: dict[str, Any] = {}
    for variant in args.variants:
        net = bundled_net(variant)
        val = evaluate_verification(load_drive(val_path, variant), net, verify=sweep_cfg, config=config)
        chosen = choose(val, precision=args.precision)
        setting = chosen if chosen is not None else (4, 1.0 + 1e-9)  # unreachable: nothing is published
        test_outcomes = evaluate_verification(load_drive(test_path, variant), net, verify=sweep_cfg, config=config)
        entry: dict[str, Any] = {"setting": chosen, "validation": summary(val, setting=setting),
                                 "test": summary(test_outcomes, setting=setting)}
        curves[variant] = (sweep(test_outcomes), sweep(test_outcomes, min_support=setting[0]))
        if args.verify_never:
            try:
                never = load_drive(args.verify_never, variant)
            except InvalidValueError:
                never = None
            if never is not None:
                found = evaluate_verification(never, net, verify=sweep_cfg, config=config)
                entry["never"] = {"queries": len(found), "loop_queries": sum(o.loop_query for o in found),
                                  "retrieval_published": sum(o.top is not None for o in found),
                                  "verified_published": sum((a := o.loop(setting[0])) is not None
                                                            and a.fitness >= setting[1] for o in found)}
        report["variants"][variant] = entry
    print(table(report))
    if args.out:
        out = Path(args.out)
        with atomic_path(out / "verify_eval.json") as tmp:
            tmp.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        plot(curves, report, out / "verify_pr.png")
        print(f"wrote {out / 'verify_eval.json'} and {out / 'verify_pr.png'}")
    return 0


def _f(v: object, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def table(report: dict[str, Any]) -> str:
    """The held-out drive's numbers per depth variant: retrieval alone, verified at the validation setting."""
    lines = ["variant  method                 published  precision  recall  max F1  pose m med/p95  "
             "pose deg med/p95  verify ms p50  never-revisit loops"]
    for variant, entry in report["variants"].items():
        test = entry["test"]
        never = entry.get("never")
        r = test["retrieval"]
        lines.append(f"{variant:8} retrieval alone        {r['published']:9d}  {r['precision']:9.2f}  "
                     f"{r['recall']:6.2f}  {r['max_f1']:6.2f}  {'':14}  {'':16}  {'':13}  "
                     f"{_f(None if never is None else never['retrieval_published'], 'd')}")
        v = test["verified"]
        at = v.get("at_setting", {})
        setting = entry["setting"]
        name = "verified: unreachable" if setting is None else f"verified s>={setting[0]} f>={setting[1]:.2f}"
        lines.append(f"{variant:8} {name:22} {at.get('published', 0):9d}  {at.get('precision', 0.0):9.2f}  "
                     f"{at.get('recall', 0.0):6.2f}  {v.get('max_f1', 0.0):6.2f}  "
                     f"{_f(at.get('pose_m_median'))}/{_f(at.get('pose_m_p95')):8}  "
                     f"{_f(at.get('pose_deg_median'))}/{_f(at.get('pose_deg_p95')):10}  "
                     f"{_f(v['verify_ms_p50'], '.0f'):>13}  "
                     f"{_f(None if never is None else never['verified_published'], 'd')}")
    return "\n".join(lines)


def plot(curves: dict[str, Any], report: dict[str, Any], path: Path) -> None:
    """Precision-recall of retrieval alone and verified loops on the held-out drive, one colour per depth variant;
    and recall at the validation threshold against the depth error."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.5))
    for i, (variant, (ret, ver)) in enumerate(curves.items()):
        colour = f"C{i}"
        ax.plot(ret["recall"], ret["precision"], ":", color=colour, label=f"{variant} retrieval alone")
        ax.plot(ver["recall"], ver["precision"], "-", color=colour, label=f"{variant} verified")
    ax.set_xlabel("recall of loop queries")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("held-out drive: retrieval alone vs verified")
    noise = {"exact": 0.0, "net5": 5.0, "net10": 10.0, "net20": 20.0}
    names = [v for v in report["variants"] if v in noise]
    xs = [noise[v] for v in names]
    at = [report["variants"][v]["test"]["verified"].get("at_setting", {}) for v in names]
    bx.plot(xs, [a.get("recall", 0.0) for a in at], "o-", label="recall at the validation setting")
    bx.plot(xs, [a.get("precision", 0.0) for a in at], "s-", label="precision at the validation setting")
    bx.plot(xs, [report["variants"][v]["test"]["verified"].get("max_f1", 0.0) for v in names], "^-",
            label="max F1 (verified)")
    bx.plot(xs, [report["variants"][v]["test"]["retrieval"]["max_f1"] for v in names], "v:",
            label="max F1 (retrieval alone)")
    bx.set_xlabel("depth error, % (1 sigma, smooth; exact = 0, no range cut)")
    bx.set_ylim(0, 1.02)
    bx.grid(alpha=0.3)
    bx.legend(fontsize=7)
    bx.set_title("verification against depth error")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
