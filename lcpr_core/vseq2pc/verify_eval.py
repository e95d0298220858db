"""Retrieval alone beside verified loops on a rendered drive (``vseq2pc_eval --verify DRIVE.npz``).

Input: a drive file of benchmarks/tools/vseq2pc_verify_data.py (per frame: pose, LiDAR structure
feature, the scan's compact cloud; per depth variant: camera features and each frame's pseudo-cloud).
Protocol (as :mod:`lcpr_core.vseq2pc.evaluate`'s retrieval): the map is every scan; a query (every
``query_step``-th complete sequence) searches the scans more than ``min_frame_gap`` frames back, top
``k``; it is a *loop query* when such a scan lies within ``loop_radius`` m.

* retrieval alone: each query publishes its most probable candidate; swept over the probability.
* verified: each query's pseudo-cloud (its frames stacked with the poses) is registered against its
  top-k candidates (:class:`~lcpr_core.vseq2pc.verify.SequenceVerifier`, the detector's code) once; the
  fitness threshold, the consensus and the temporal-consistency gate
  (:class:`~lcpr_core.vseq2pc.consistency.ConsistencyGate`, the node's) are replayed over the queries in
  stream order for each setting; a query publishes the verified candidate with the best fitness.

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
from typing import Any, cast

import numpy as np
from tqdm import tqdm

from ..atomic import atomic_path, save_figure
from ..errors import InvalidValueError
from ..geometry import rotation_angle_deg
from ..pretrained import default_vseq2pc_weights
from ..verification.clouds import dequantise
from .consistency import MAX_HISTORY, ConsistencyConfig, ConsistencyGate, map_camera_pose
from .net import Vseq2pcNet
from .pseudo_cloud import accumulate
from .retrieval import ScanDatabase, ScanMatch, SearchConfig
from .sequence import sequence_table
from .verify import SequenceVerifier, SequenceVerifyConfig, support_counts

__all__ = ["DriveData", "QueryOutcome", "Setting", "VerifyEvalConfig", "choose", "evaluate_verification",
           "gated_curve", "load_drive", "bundled_net", "published", "run", "summary", "sweep", "table"]


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
    placed: np.ndarray | None = None  # 4 x 4: the camera's pose in the map (world_T_scan @ match_T_query)


@dataclass
class QueryOutcome:
    frame: int
    loop_query: bool  # a scan within loop_radius more than min_frame_gap frames back exists
    top: ScanMatch | None  # retrieval alone: the most probable candidate
    top_correct: bool
    accepted: list[Accepted] = field(default_factory=list)
    seconds: float = 0.0  # verification of this query's candidates (pseudo-cloud included)
    reasons: dict[str, int] = field(default_factory=dict)
    odom: np.ndarray | None = None  # 4 x 4 world_T_base of the query frame (the drive's odometry)
    agree: np.ndarray | None = None  # N x N consensus agreement of the accepted registrations (filled once)

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
            query = verifier.prepare_query(accumulate(frames, query_pose=data.poses[frame], config=vcfg.pseudo,
                                                       lidar_T_cam=data.lidar_T_cam))
            checked = verifier.verify_all(query, found[: vcfg.top_k], lambda m: mapped.scan_clouds[m.row],
                                          lidar_T_cam=data.lidar_T_cam)
        seconds = time.perf_counter() - tic
        reasons: dict[str, int] = {}
        for c in checked:
            reasons[c.verification] = reasons.get(c.verification, 0) + 1
        top = found[0] if found else None
        outcome = QueryOutcome(frame, loop_query, top, top is not None and dist[top.row] <= config.loop_radius,
                               seconds=seconds, reasons=reasons, odom=data.poses[frame])
        for c, n in zip(checked, support_counts(checked, vcfg), strict=True):
            if not c.verified or c.match_T_query is None:
                continue
            truth = np.linalg.inv(mapped.poses[c.row]) @ data.poses[frame] @ data.lidar_T_cam
            err_m = float(np.linalg.norm(c.match_T_query[:3, 3] - truth[:3, 3]))
            err_deg = float(rotation_angle_deg((np.linalg.inv(truth) @ c.match_T_query)[:3, :3]))
            right = err_m <= config.max_pose_m and err_deg <= config.max_pose_deg
            outcome.accepted.append(Accepted(c.fitness, n, right, err_m, err_deg, map_camera_pose(c)))
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


#: The validation sweep: fitness thresholds, consensus supports, consistency counts and tolerances (m, deg).
THRESHOLDS = tuple(round(0.30 + 0.025 * i, 3) for i in range(27))  # 0.30 .. 0.95
SUPPORTS = (1, 2, 3, 4)
COUNTS = (1, 2, 3, 4)
TOLERANCES = ((0.5, 2.0), (1.0, 3.0), (2.0, 5.0))
MARGIN = 0.05  # a chosen fitness threshold keeps the asked precision down to this much below it as well


@dataclass(frozen=True)
class Setting:
    """What decides a published loop: consensus support, fitness threshold, temporal consistency."""

    min_support: int
    min_fitness: float
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)

    @classmethod
    def of(cls, config: SequenceVerifyConfig) -> Setting:
        return cls(config.min_support, config.min_fitness, config.consistency)

    def label(self) -> str:
        c = self.consistency
        gate = "" if c.count <= 1 else f" k={c.count} {c.max_m:g}m/{c.max_deg:g}deg"
        return f"s>={self.min_support} f>={self.min_fitness:.3g}{gate}"

    def as_dict(self) -> dict[str, Any]:
        return {"min_support": self.min_support, "min_fitness": self.min_fitness,
                "consistency": asdict(self.consistency)}


#: The defaults before the temporal gate (support 2, fitness 0.75, chosen on validation at precision 0.95): a row to
#: compare with.
PREVIOUS = Setting(2, 0.75, ConsistencyConfig(count=1))


def _agreement(o: QueryOutcome, config: SequenceVerifyConfig) -> np.ndarray | None:
    """N x N: accepted registrations i and j put the camera within consensus_m / consensus_deg of one map pose
    (computed once per query); None without poses."""
    if o.agree is None and o.accepted and all(a.placed is not None for a in o.accepted):
        placed = [np.asarray(a.placed) for a in o.accepted]
        agree = np.eye(len(placed), dtype=bool)
        for i, Ti in enumerate(placed):
            inv = np.linalg.inv(Ti)
            for j in range(i + 1, len(placed)):
                d = inv @ placed[j]
                agree[i, j] = agree[j, i] = bool(np.linalg.norm(d[:3, 3]) <= config.consensus_m
                                                 and rotation_angle_deg(d[:3, :3]) <= config.consensus_deg)
        o.agree = agree
    return o.agree


def _verified(o: QueryOutcome, setting: Setting, config: SequenceVerifyConfig) -> list[Accepted]:
    """The accepted registrations the node verifies: fitness at the threshold, then consensus among those (as the
    node counts it); the stored support (counted at any fitness) when the poses are missing."""
    kept = [i for i, a in enumerate(o.accepted) if a.fitness >= setting.min_fitness]
    agree = _agreement(o, config)
    if agree is None:
        return [o.accepted[i] for i in kept if o.accepted[i].support >= setting.min_support]
    support = agree[np.ix_(kept, kept)].sum(axis=1) if kept else np.zeros(0)
    return [o.accepted[i] for i, n in zip(kept, support, strict=True) if n >= setting.min_support]


def published(outcomes: list[QueryOutcome], setting: Setting, *, lidar_T_cam: np.ndarray) -> list[Accepted | None]:
    """Per query (in stream order) the loop the detector would publish under ``setting``: fitness, consensus,
    then the temporal-consistency gate (:class:`~lcpr_core.vseq2pc.consistency.ConsistencyGate`, the node's)."""
    vcfg = SequenceVerifyConfig()
    gate = ConsistencyGate(setting.consistency, lidar_T_cam=lidar_T_cam)
    out: list[Accepted | None] = [None] * len(outcomes)
    verified_of: dict[int, list[Accepted]] = {}
    for q, o in enumerate(outcomes):
        verified = verified_of[q] = _verified(o, setting, vcfg)
        ok = gate.admit_poses(o.odom, [a.placed for a in verified], key=q, scores=[a.fitness for a in verified])
        passed = [n for n, y in enumerate(ok) if y]
        if passed:
            best = max(passed, key=lambda n: verified[n].fitness)
            out[q] = verified[best]
            for earlier, n in gate.confirm(best):  # loops confirmed late (ConsistencyConfig.backfill)
                out[cast(int, earlier)] = verified_of[cast(int, earlier)][n]
        verified_of.pop(q - MAX_HISTORY, None)
    return out


def metrics(outcomes: list[QueryOutcome], loops: list[Accepted | None]) -> dict[str, Any]:
    """Published, wrong, precision, recall of loop queries, F1 and the right loops' pose errors."""
    n_loop = max(sum(o.loop_query for o in outcomes), 1)
    pub = [(o, a) for o, a in zip(outcomes, loops, strict=True) if a is not None]
    good = [(o, a) for o, a in pub if a.correct]
    precision = len(good) / len(pub) if pub else 0.0
    recall = sum(o.loop_query for o, _ in good) / n_loop
    errors_m = np.array([a.error_m for _, a in good])
    errors_deg = np.array([a.error_deg for _, a in good])
    return {"published": len(pub), "wrong": len(pub) - len(good), "precision": precision, "recall": recall,
            "f1": 2 * precision * recall / max(precision + recall, 1e-12),
            "pose_m_median": float(np.median(errors_m)) if len(good) else None,
            "pose_m_p95": float(np.percentile(errors_m, 95)) if len(good) else None,
            "pose_deg_median": float(np.median(errors_deg)) if len(good) else None,
            "pose_deg_p95": float(np.percentile(errors_deg, 95)) if len(good) else None,
            "wrong_pose_m": [round(a.error_m, 2) for _, a in pub if not a.correct]}


def gated_curve(outcomes: list[QueryOutcome], setting: Setting, *, lidar_T_cam: np.ndarray,
                thresholds: tuple[float, ...] = THRESHOLDS) -> dict[str, np.ndarray]:
    """Precision, recall, F1, published and wrong loops at every fitness threshold (the rest of ``setting``
    fixed): the gate's history depends on the threshold, so each one is replayed."""
    rows = [metrics(outcomes, published(outcomes, replace(setting, min_fitness=t), lidar_T_cam=lidar_T_cam))
            for t in thresholds]
    return {"threshold": np.array(thresholds), **{k: np.array([r[k] for r in rows], np.float64)
                                                   for k in ("precision", "recall", "f1", "published", "wrong")}}


def choose(outcomes: list[QueryOutcome], *, lidar_T_cam: np.ndarray, precision: float = 1.0,
           margin: float = MARGIN, supports: tuple[int, ...] = SUPPORTS, counts: tuple[int, ...] = COUNTS,
           tolerances: tuple[tuple[float, float], ...] = TOLERANCES, thresholds: tuple[float, ...] = THRESHOLDS,
           spacing_m: float = ConsistencyConfig().spacing_m) -> Setting | None:
    """The setting with the most recall on these (validation) queries that keeps ``precision`` with a margin: at its
    fitness threshold and down to ``margin`` below it, and so does each looser neighbour (one query fewer in the
    chain, one less support, the next wider tolerance). None when no such setting publishes a right loop.
    Ties: the stricter gate (more queries, tighter tolerance, more support), then the lower threshold."""
    curves: dict[tuple[int, int, int], dict[str, np.ndarray]] = {}
    for support in supports:
        for count in counts:
            for ti, (max_m, max_deg) in enumerate(tolerances if count > 1 else tolerances[:1]):
                gate = ConsistencyConfig(count=count, max_m=max_m, max_deg=max_deg, spacing_m=spacing_m)
                curves[(support, count, ti)] = gated_curve(outcomes, Setting(support, thresholds[0], gate),
                                                           lidar_T_cam=lidar_T_cam, thresholds=thresholds)

    def safe(key: tuple[int, int, int], t: float) -> bool:
        """No looser threshold within the margin drops under the precision (a key outside the sweep: no check)."""
        c = curves.get((key[0], key[1], key[2] if key[1] > 1 else 0))
        if c is None:
            return True
        near = (c["threshold"] >= t - margin - 1e-9) & (c["threshold"] <= t + 1e-9)
        return bool(((c["precision"] >= precision) | (c["published"] == 0))[near].all())

    best: tuple[tuple[float, int, int, float, float], Setting] | None = None
    for (support, count, ti), c in curves.items():
        looser = [(support, count, ti), (support, count - 1, ti), (support - 1, count, ti)]
        if count > 1 and ti + 1 < len(tolerances):
            looser.append((support, count, ti + 1))
        for i, t in enumerate(thresholds):
            if c["recall"][i] <= 0 or not all(safe(k, t) for k in looser if k[0] >= 1 and k[1] >= 1):
                continue
            max_m, max_deg = tolerances[ti]
            key = (float(c["recall"][i]), count, support, -max_m, -t)
            if best is None or key > best[0]:
                gate = ConsistencyConfig(count=count, max_m=max_m, max_deg=max_deg, spacing_m=spacing_m)
                best = (key, Setting(support, t, gate))
    return None if best is None else best[1]


def summary(outcomes: list[QueryOutcome], settings: dict[str, Setting], *, lidar_T_cam: np.ndarray
            ) -> dict[str, Any]:
    """Retrieval alone, and the verified loops under each named setting (with the max F1 over its threshold)."""
    loops = sum(o.loop_query for o in outcomes)
    out: dict[str, Any] = {"queries": len(outcomes), "loop_queries": loops}
    r = sweep(outcomes)
    f1 = 2 * r["precision"] * r["recall"] / np.maximum(r["precision"] + r["recall"], 1e-12)
    published_top = [o for o in outcomes if o.top is not None]
    correct = [o for o in published_top if o.top_correct]
    out["retrieval"] = {"max_f1": float(f1.max()) if len(f1) else 0.0, "published": len(published_top),
                        "wrong": len(published_top) - len(correct),
                        "precision": len(correct) / max(len(published_top), 1),
                        "recall": sum(o.loop_query for o in correct) / max(loops, 1)}
    for name, setting in settings.items():
        row = metrics(outcomes, published(outcomes, setting, lidar_T_cam=lidar_T_cam))
        c = gated_curve(outcomes, setting, lidar_T_cam=lidar_T_cam)
        row["max_f1"] = float(c["f1"].max())
        row["setting"] = setting.as_dict()
        out[name] = row
    seconds = np.array([o.seconds for o in outcomes if o.seconds > 0])
    out["verify_ms_p50"] = float(np.median(seconds) * 1e3) if len(seconds) else None
    reasons: dict[str, int] = {}
    for o in outcomes:
        for k, v in o.reasons.items():
            reasons[k] = reasons.get(k, 0) + v
    out["verdicts"] = reasons
    return out


# -- vseq2pc_eval --verify ------------------------------------------------------------------------------
def bundled_net(variant: str) -> Vseq2pcNet:
    """The bundled weights for the variant's depth: the exact-depth set for exact depth, else the network set."""
    files = default_vseq2pc_weights(depth="exact" if variant == "exact" else "network")
    if files is None:
        raise InvalidValueError("the bundled VSeq2PC weights are missing from this install (weights/)")
    return Vseq2pcNet.from_files(sequence=files[0], descriptor=files[1])


def variant_report(val: list[QueryOutcome], test: list[QueryOutcome], never: list[QueryOutcome] | None, *,
                   lidar_T_cam: np.ndarray, precision: float) -> tuple[dict[str, Any], dict[str, Any]]:
    """One depth variant's entry of the report (the setting chosen on ``val``; the defaults before the temporal gate
    existed, today's without and with it, and that setting, on both drives and the never-revisit one) and the
    held-out curves."""
    defaults = SequenceVerifyConfig()
    settings = {"previous": PREVIOUS,
                "no_gate": Setting(defaults.min_support, defaults.min_fitness, ConsistencyConfig(count=1)),
                "no_backfill": Setting(defaults.min_support, defaults.min_fitness,
                                       replace(defaults.consistency, backfill=False)),
                "default": Setting.of(defaults)}
    chosen = choose(val, lidar_T_cam=lidar_T_cam, precision=precision)
    if chosen is not None:
        settings["chosen"] = chosen
    entry: dict[str, Any] = {"setting": None if chosen is None else chosen.as_dict(),
                             "validation": summary(val, settings, lidar_T_cam=lidar_T_cam),
                             "test": summary(test, settings, lidar_T_cam=lidar_T_cam)}
    if never is not None:
        entry["never"] = {"queries": len(never), "loop_queries": sum(o.loop_query for o in never),
                          "retrieval_published": sum(o.top is not None for o in never),
                          **{f"{name}_published": sum(a is not None for a in
                                                      published(never, st, lidar_T_cam=lidar_T_cam))
                             for name, st in settings.items()}}
    curves = {name: gated_curve(test, st, lidar_T_cam=lidar_T_cam) for name, st in settings.items()}
    return entry, curves


def run(args: argparse.Namespace) -> int:
    """``vseq2pc_eval --verify VAL TEST [--verify-never DRIVE] [--variants ...] [--out DIR]``."""
    val_path, test_path = args.verify
    config = VerifyEvalConfig(k=10, min_frame_gap=args.min_frame_gap, loop_radius=args.loop_radius,
                              query_step=args.query_step)
    sweep_cfg = SequenceVerifyConfig(min_fitness=0.0)  # every registration that passes the other checks; swept
    report: dict[str, Any] = {"validation": val_path, "test": test_path, "never": args.verify_never,
                              "config": asdict(config), "precision": args.precision, "margin": MARGIN,
                              "variants": {}}
    curves: dict[str, Any] = {}
    for variant in args.variants:
        net = bundled_net(variant)
        val = evaluate_verification(load_drive(val_path, variant), net, verify=sweep_cfg, config=config)
        test_drive = load_drive(test_path, variant)
        test_outcomes = evaluate_verification(test_drive, net, verify=sweep_cfg, config=config)
        found = None
        if args.verify_never:
            try:
                never = load_drive(args.verify_never, variant)
            except InvalidValueError:
                never = None
            if never is not None:
                found = evaluate_verification(never, net, verify=sweep_cfg, config=config)
        entry, curves[variant] = variant_report(val, test_outcomes, found, lidar_T_cam=test_drive.lidar_T_cam,
                                                precision=args.precision)
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


ROWS = (("previous", "before the gate"), ("no_gate", "default, k=1"), ("no_backfill", "default, no late"),
        ("default", "default"), ("chosen", "chosen on val"))


def table(report: dict[str, Any]) -> str:
    """The held-out drive's numbers per depth variant: retrieval alone, then verified loops with the defaults before
    the temporal gate, today's defaults without the gate (k=1), with it but no late loops (backfill off), as they are,
    and this variant's validation choice."""
    lines = ["variant  method           setting                         published wrong precision recall max F1  "
             "pose m med/p95  pose deg med/p95  val pub/wrong/recall  never-revisit loops"]
    for variant, entry in report["variants"].items():
        test, val = entry["test"], entry["validation"]
        never = entry.get("never") or {}
        r = test["retrieval"]
        lines.append(f"{variant:8} retrieval alone  {'most probable scan':31} {r['published']:9d} {r['wrong']:5d} "
                     f"{r['precision']:9.2f} {r['recall']:6.2f} {r['max_f1']:6.2f}  {'':14}  {'':16}  "
                     f"{'':20}  {_f(never.get('retrieval_published'), 'd')}")
        for key, name in ROWS:
            if key not in test:
                lines.append(f"{variant:8} {name:16} {'no setting keeps the precision':31} {0:9d}")
                continue
            v, w = test[key], val[key]
            st = v["setting"]
            label = Setting(st["min_support"], st["min_fitness"], ConsistencyConfig(**st["consistency"])).label()
            lines.append(f"{variant:8} {name:16} {label:31} {v['published']:9d} {v['wrong']:5d} "
                         f"{v['precision']:9.2f} {v['recall']:6.2f} {v['max_f1']:6.2f}  "
                         f"{_f(v['pose_m_median'])}/{_f(v['pose_m_p95']):9}  "
                         f"{_f(v['pose_deg_median'])}/{_f(v['pose_deg_p95']):11}  "
                         f"{w['published']:3d}/{w['wrong']:d}/{w['recall']:.2f}{'':11}  "
                         f"{_f(never.get(f'{key}_published'), 'd')}")
    return "\n".join(lines)


def plot(curves: dict[str, Any], report: dict[str, Any], path: Path) -> None:
    """Held-out drive: precision and recall against the fitness threshold without the temporal gate, with it but
    without late loops, and the default, one colour per depth variant; and the wrong loops published at each
    threshold."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.5))
    for i, (variant, named) in enumerate(curves.items()):
        colour = f"C{i}"
        for name, style in (("no_gate", ":"), ("no_backfill", "--"), ("default", "-")):
            c = named.get(name)
            if c is None:
                continue
            some = c["published"] > 0  # a threshold that publishes nothing has no precision
            ax.plot(c["recall"][some], c["precision"][some], style, marker=".", color=colour,
                    label=f"{variant} {name}")
            bx.plot(c["threshold"], c["wrong"], style, color=colour, label=f"{variant} {name}")
    ax.set_xlabel("recall of loop queries")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("held-out drive, fitness threshold swept")
    bx.set_xlabel("fitness threshold")
    bx.set_ylabel("wrong loops published")
    bx.grid(alpha=0.3)
    bx.legend(fontsize=7)
    bx.set_title("wrong loops: no gate (k=1), the gate without and with late loops")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
