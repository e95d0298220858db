"""Global initial alignment for the verifier: today's Scan Context / BEV starts against FPFH-based aligners.

    python benchmarks/studies/global_registration.py [--split test] [--trials 5] [--far 100] \\
        [--out out/global_registration]
    python benchmarks/studies/global_registration.py --tune     # choose the parameters on validation pairs

Question (docs/studies/global_registration.md): the verifier registers a candidate with small_gicp from
starts guessed by a Scan Context yaw and a bird's-eye-view x/y correlation; on real sensors it fails where
no start is close. Which global aligner gives a start close enough, at what cost per pair?

Sets, each pair with a known relative pose:
- ``walk_loop`` / ``campus`` (``livox_hku``, Livox Avia, ~70 deg view): true revisits
  (:func:`lcpr_offline.verification_pairs.true_pairs`) of the ``--split`` half (test by default;
  ``--tune`` uses the validation half). Known pose: the SLAM poses (a start or a result counts as right
  against optimized_poses.txt or odom_poses.txt, which disagree by ~0.27 m at walk_loop's loop);
- ``kitti``: every ordered pair of the four raw KITTI-00 scans, the query turned by a seeded random yaw
  in [0, 360) and shifted by up to 2 m, ``--trials`` times each (:mod:`lcpr_offline.kitti_scans`);
- ``campus_far``: ``--far`` of campus's far pairs (> 20 m) that Scan Context ranks nearest, of the same
  half: none may be accepted; they show what a fallback costs on wrong candidates and whether it lets
  any through.

Methods (all on the compact clouds a map keeps, ``GeometricVerifier().compact``):
- ``today``: ``GeometricVerifier().starts`` (is ANY start, and the FIRST, within 1.5 m / 10 deg);
  verdict: ``verify_prepared`` with no guess;
- ``wide``: the same with more Scan Context / BEV hypotheses (``--wide`` yaws, all registered);
- ``kiss``: :func:`lcpr_core.verification.global_align.global_alignment` (KISS-Matcher);
- ``o3d_ransac`` / ``o3d_fgr``: Open3D FPFH, then RANSAC / Fast Global Registration on feature matches;
- ``fpfh_kiss``: Open3D FPFH (made once per cloud, as a keyframe could keep it), mutual nearest feature
  matches, KISS-Matcher's pruning and solver (``prune_and_solve``): what caching features would cost a pair;
- ``fallback``: today's verdict, and when it rejects, ``kiss``'s start fed to the verifier.

For every start: the verdict of ``verify_prepared(q, m, initial_guess=start)``, right when accepted within
0.5 m / 3 deg. Time: per pair, the aligner alone (features of both clouds included, except ``o3d_*`` and
``fpfh_kiss`` whose features per cloud are reported apart) and the verifier; CPU time of the process,
pinned to one core (``--threads 1``: TBB and OpenMP then run one thread, as the verifier does beside the
network): the machine is shared, and CPU time does not count the waits for other processes.

Writes ``OUT/summary.json`` (every table), ``OUT/global_registration.png`` and, with ``--tune``,
``OUT/tune.json``. Needs the ``compare`` extra (open3d-cpu; on Debian also libusb-1.0-0) besides
kiss-matcher.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.verification import GeometricVerifier, PreparedCloud
    from lcpr_core.verification.global_align import GlobalAlignConfig

START_M, START_DEG = 1.5, 10.0  # a start this close converges (the coarse stage's reach)
RIGHT_M, RIGHT_DEG = 0.5, 3.0  # a verdict this close is right
METHODS = ("truth", "identity", "today", "wide", "kiss", "o3d_ransac", "o3d_fgr", "fpfh_kiss", "fallback",
           "fallback_cached")
SETS = ("walk_loop", "campus", "kitti")
FAR_METHODS = ("today", "kiss", "fpfh_kiss", "fallback", "fallback_cached")
FALLBACKS = {"fallback": "kiss", "fallback_cached": "fpfh_kiss"}  # policy -> the aligner it falls back on
FEATURE_METHODS = ("o3d_ransac", "o3d_fgr", "fpfh_kiss")  # Open3D FPFH made once per cloud, before the clock
# Chosen by --tune on validation pairs (docs/studies/global_registration.md): Open3D's voxel per method, RANSAC's budget
O3D_VOXEL = {"o3d_ransac": 0.6, "o3d_fgr": 1.0, "fpfh_kiss": 1.0}
RANSAC_ITERATIONS, RANSAC_CONFIDENCE = 100000, 0.999
UNCAPPED = 1_000_000  # max_points that never binds


@dataclass
class Case:
    """One pair: keys name the clouds (features are cached by key), ``truths`` the acceptable known poses."""

    name: str
    query_key: str
    match_key: str
    query: PreparedCloud
    match: PreparedCloud
    truths: list[np.ndarray]
    true_pair: bool = True


@dataclass
class Clock:
    """Wall and CPU seconds of a block (CPU: the whole process, every thread)."""

    wall: float = 0.0
    cpu: float = 0.0
    _t: tuple[float, float] = field(default=(0.0, 0.0), repr=False)

    def __enter__(self) -> Clock:
        self._t = (time.perf_counter(), time.process_time())
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall = time.perf_counter() - self._t[0]
        self.cpu = time.process_time() - self._t[1]


def pose_ok(T: np.ndarray, truths: list[np.ndarray], max_m: float, max_deg: float) -> bool:
    from lcpr_offline.verification_pairs import pose_error

    for truth in truths:
        err_m, err_deg = pose_error(T, truth)
        if err_m <= max_m and err_deg <= max_deg:
            return True
    return False


# ---------------------------------------------------------------------------------- open3d features
class Open3dFeatures:
    """FPFH of each cloud (by key), made once: a keyframe could keep its features beside its cloud."""

    def __init__(self, *, voxel: float, normal_gain: float = 3.0, fpfh_gain: float = 5.0, max_points: int = 2000
                 ) -> None:
        self.voxel, self.normal_gain, self.fpfh_gain, self.max_points = voxel, normal_gain, fpfh_gain, max_points
        self._cache: dict[str, tuple[Any, Any, np.ndarray, np.ndarray]] = {}
        self.cpu_seconds: list[float] = []

    def __call__(self, key: str, xyz: np.ndarray) -> tuple[Any, Any, np.ndarray, np.ndarray]:
        """(open3d cloud, open3d feature, N x 3 points, N x 33 float32 features) of one cloud."""
        import open3d as o3d

        if key not in self._cache:
            with Clock() as clock:
                raw = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, np.float64)))
                voxel = self.voxel
                cloud = raw.voxel_down_sample(voxel)
                if len(cloud.points) > self.max_points:  # a 360 deg scan: coarser, as global_align's max_points
                    voxel *= float(np.sqrt(len(cloud.points) / self.max_points))
                    cloud = raw.voxel_down_sample(voxel)
                cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=self.normal_gain * voxel,
                                                                            max_nn=30))
                feature = o3d.pipelines.registration.compute_fpfh_feature(
                    cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=self.fpfh_gain * voxel, max_nn=100))
            self.cpu_seconds.append(clock.cpu)
            self._cache[key] = (cloud, feature, np.asarray(cloud.points),
                                np.ascontiguousarray(np.asarray(feature.data).T, np.float32))
        return self._cache[key]


def o3d_ransac(f: Open3dFeatures, case: Case, *, iterations: int, confidence: float) -> np.ndarray:
    import open3d as o3d

    reg = o3d.pipelines.registration
    qc, qf, _, _ = f(case.query_key, case.query.xyz)
    mc, mf, _, _ = f(case.match_key, case.match.xyz)
    reach = 1.5 * f.voxel
    r = reg.registration_ransac_based_on_feature_matching(
        qc, mc, qf, mf, True, reach, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(reach)],
        reg.RANSACConvergenceCriteria(iterations, confidence))
    return np.asarray(r.transformation, np.float64)


def o3d_fgr(f: Open3dFeatures, case: Case) -> np.ndarray:
    import open3d as o3d

    reg = o3d.pipelines.registration
    qc, qf, _, _ = f(case.query_key, case.query.xyz)
    mc, mf, _, _ = f(case.match_key, case.match.xyz)
    r = reg.registration_fgr_based_on_feature_matching(
        qc, mc, qf, mf, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=1.5 * f.voxel))
    return np.asarray(r.transformation, np.float64)


def mutual_matches(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (i of a, j of b) that are each other's nearest feature (squared L2 by one matrix product)."""
    d = (a * a).sum(1)[:, None] - 2.0 * (a @ b.T) + (b * b).sum(1)[None, :]
    ab, ba = d.argmin(axis=1), d.argmin(axis=0)
    keep = np.flatnonzero(ba[ab] == np.arange(len(a)))
    return keep, ab[keep]


def fpfh_kiss(f: Open3dFeatures, case: Case, config: GlobalAlignConfig) -> np.ndarray:
    import kiss_matcher

    _, _, qp, qf = f(case.query_key, case.query.xyz)
    _, _, mp, mf = f(case.match_key, case.match.xyz)
    i, j = mutual_matches(qf, mf)
    T = np.eye(4)
    if len(i) < 3:
        return T
    km = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel_size=config.voxel))
    s = km.prune_and_solve(list(qp[i].astype(np.float32)), list(mp[j].astype(np.float32)))
    T[:3, :3], T[:3, 3] = np.asarray(s.rotation), np.asarray(s.translation).reshape(3)
    return T if np.isfinite(T).all() else np.eye(4)


# ---------------------------------------------------------------------------------- one case
def judge(verifier: GeometricVerifier, case: Case, start: np.ndarray | None) -> dict[str, Any]:
    """The verifier's verdict from ``start`` (None: its own starts) and whether it is right."""
    with Clock() as clock:
        v = verifier.verify_prepared(case.query, case.match, initial_guess=start)
    right = bool(v.accepted and pose_ok(v.match_T_query, case.truths, RIGHT_M, RIGHT_DEG))
    return {"accepted": bool(v.accepted), "right": right, "reason": v.reason, "coarse_fitness": v.coarse_fitness,
            "verify_cpu": clock.cpu, "verify_wall": clock.wall}


def run_method(name: str, case: Case, tools: dict[str, Any], *, verdict: bool = True) -> dict[str, Any]:
    """One method on one case: start(s), their closeness, the verdict (unless ``verdict`` is False), the times."""
    from lcpr_core.verification.global_align import global_alignment

    verifier: GeometricVerifier = tools["verifier"]
    out: dict[str, Any] = {}
    if name in ("today", "wide"):
        v = verifier if name == "today" else tools["wide"]
        with Clock() as clock:
            starts = v.starts(case.query, case.match)
        close = [pose_ok(T, case.truths, START_M, START_DEG) for T in starts]
        out.update(start_ok=any(close), first_ok=close[0], align_cpu=clock.cpu, align_wall=clock.wall)
        if verdict:
            out.update(judge(v, case, None))
        return out
    if name in ("truth", "identity"):
        T = case.truths[0] if name == "truth" else np.eye(4)
        out.update(start_ok=pose_ok(T, case.truths, START_M, START_DEG), align_cpu=0.0, align_wall=0.0)
        if verdict:
            out.update(judge(verifier, case, T))
        return out
    with Clock() as clock:
        if name == "kiss":
            found = global_alignment(case.query.xyz, case.match.xyz, config=tools["kiss_config"])
            T = found.match_T_query
            out["inliers"], out["valid"] = found.inliers, found.valid
        elif name == "o3d_ransac":
            T = o3d_ransac(tools["o3d_ransac_features"], case, iterations=tools["ransac_iterations"],
                           confidence=tools["ransac_confidence"])
        elif name == "o3d_fgr":
            T = o3d_fgr(tools["o3d_fgr_features"], case)
        elif name == "fpfh_kiss":
            T = fpfh_kiss(tools["fpfh_kiss_features"], case, tools["fpfh_kiss_config"])
        else:
            raise ValueError(f"method {name!r}; accepted: {', '.join(METHODS)}")
    out.update(start_ok=pose_ok(T, case.truths, START_M, START_DEG), align_cpu=clock.cpu, align_wall=clock.wall)
    if verdict:
        out.update(judge(verifier, case, T))
    return out


def prime_features(case: Case, f: Open3dFeatures) -> None:
    """Make both clouds' Open3D features before a method's clock starts (a keyframe would have them)."""
    f(case.query_key, case.query.xyz)
    f(case.match_key, case.match.xyz)


def evaluate(cases: Iterator[Case], total: int, desc: str, tools: dict[str, Any], methods: tuple[str, ...]
             ) -> dict[str, list[dict[str, Any]]]:
    """Every method on every case; a fallback policy reuses the rows of ``today`` and of its aligner."""
    from tqdm import tqdm

    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    for case in tqdm(cases, total=total, desc=desc, unit="pair"):
        for m in methods:
            if m in FEATURE_METHODS:
                prime_features(case, tools[f"{m}_features"])
        for m in methods:
            if m in FALLBACKS:
                today, other = rows["today"][-1], rows[FALLBACKS[m]][-1]
                used = not today["accepted"]
                rows[m].append({
                    "start_ok": today["start_ok"] or (used and other["start_ok"]),
                    "accepted": today["accepted"] or (used and other["accepted"]),
                    "right": today["right"] or (used and other["right"]),
                    "align_cpu": today["align_cpu"] + (other["align_cpu"] if used else 0.0),
                    "verify_cpu": today["verify_cpu"] + (other["verify_cpu"] if used else 0.0),
                    "fallback_used": used})
            else:
                rows[m].append(run_method(m, case, tools))
    return rows


def summarise(rows: dict[str, list[dict[str, Any]]]) -> dict[str, dict[str, float]]:
    """Per method: shares of close starts and right verdicts, and CPU ms per pair (median, p90)."""
    out: dict[str, dict[str, float]] = {}
    for m, r in rows.items():
        if not r:
            continue
        keys = ("start_ok", "first_ok", "accepted", "right", "fallback_used")
        if "verify_cpu" not in r[0]:
            for x in r:
                x["verify_cpu"] = 0.0
        share: dict[str, float] = {k: float(np.mean([x[k] for x in r])) for k in keys if k in r[0]}
        align = np.array([x["align_cpu"] for x in r]) * 1e3
        total = align + np.array([x["verify_cpu"] for x in r]) * 1e3
        out[m] = {"pairs": len(r), **share,
                  "align_ms_p50": float(np.median(align)), "align_ms_p90": float(np.percentile(align, 90)),
                  "total_ms_p50": float(np.median(total)), "total_ms_p90": float(np.percentile(total, 90))}
    return out


def print_table(name: str, summary: dict[str, dict[str, float]], *, true_pairs: bool) -> None:
    right = "right" if true_pairs else "accepted"
    print(f"\n{name}: {next(iter(summary.values()))['pairs']} pairs")
    print(f"  {'method':12s} {'start ok':>9s} {'first ok':>9s} {right:>9s} {'align ms p50/p90':>17s} "
          f"{'+verify ms p50/p90':>19s}")
    for m, s in summary.items():
        first = f"{s['first_ok']:.2f}" if "first_ok" in s else "-"
        print(f"  {m:12s} {s['start_ok']:9.2f} {first:>9s} {s[right]:9.2f} "
              f"{s['align_ms_p50']:8.1f}/{s['align_ms_p90']:<8.1f} {s['total_ms_p50']:9.1f}/{s['total_ms_p90']:<9.1f}")


# ---------------------------------------------------------------------------------- sets
def livox_cases(name: str, data: Path, split: str, verifier: GeometricVerifier, *, far: int, seed: int,
                limit: int) -> dict[str, tuple[list[Case], bool]]:
    """True pairs (and, for campus, hard far pairs) of one Livox set's half, as cases."""
    from lcpr_offline.verification_pairs import PreparedScans, far_pairs, split_at, split_pairs, true_pairs
    from msg_tools.convert.scan_folder import ScanFolder

    seq = ScanFolder(data / name)
    odom = ScanFolder(data / name, poses_file="odom_poses.txt")
    prepared = PreparedScans(verifier, seq)
    at = split_at(name, seq)
    true = split_pairs(true_pairs(seq), at, split)
    label = name
    if len(true) == 0:  # campus: all its revisits have their query in the first half
        true, label = true_pairs(seq), f"{name}_val"
        print(f"{name}: no true pair in the {split} half; its {len(true)} true pairs are all reported as "
              f"'{label}' (they are validation pairs: they took part in choosing the parameters)")
    sets = {label: (true, True)}
    if name == "campus" and far > 0:
        _, hard = far_pairs(seq, sample=0, hard=3, seed=seed)
        hard = split_pairs(hard, at, split)
        rng = np.random.default_rng(seed)
        sets["campus_far"] = (hard[np.sort(rng.choice(len(hard), size=min(far, len(hard)), replace=False))], False)
    out = {}
    for key, (pairs, is_true) in sets.items():
        if limit and len(pairs) > limit:
            pairs = pairs[np.linspace(0, len(pairs) - 1, limit).round().astype(np.int64)]
        out[key] = ([Case(key, f"{name}/{q}", f"{name}/{m}", prepared[int(q)], prepared[int(m)],
                          [np.linalg.inv(p[m]) @ p[q] for p in (seq.poses, odom.poses)], is_true)
                     for q, m in pairs], is_true)
    return out


def kitti_cases(folder: Path, verifier: GeometricVerifier, *, trials: int, seed: int) -> list[Case]:
    from lcpr_offline.kitti_scans import kitti_trials

    matches: dict[int, PreparedCloud] = {}
    cases = []
    for i, t in enumerate(kitti_trials(trials=trials, seed=seed, folder=folder)):
        if t.match not in matches:
            matches[t.match] = verifier.prepare(verifier.compact(t.match_xyz))
        cases.append(Case("kitti", f"kitti/trial{i}", f"kitti/{t.match}",
                          verifier.prepare(verifier.compact(t.query_xyz)), matches[t.match], [t.match_T_query]))
    return cases


# ---------------------------------------------------------------------------------- tuning
def tune(cases: list[Case], tools: dict[str, Any], out: Path) -> dict[str, Any]:
    """Sweep each aligner's parameters on validation pairs, scoring its start alone (no verdict: on these
    revisits, < 3 m and < 30 deg apart, the verifier's coarse stage converges from most starts, even identity).

    The pick per aligner: the most starts within 1.5 m / 10 deg, the cheapest within 2 points of it.
    """
    from tqdm import tqdm

    from lcpr_core.verification.global_align import GlobalAlignConfig

    results: dict[str, Any] = {"kiss": {}, "o3d_ransac": {}, "o3d_fgr": {}, "fpfh_kiss": {}}
    # no point cap in the sweep (max_points): the cap bounds 360 deg scans and leaves these clouds alone at the pick
    grid = [GlobalAlignConfig(voxel=v, fpfh_gain=g, max_points=UNCAPPED) for v in (0.4, 0.6, 0.8, 1.0)
            for g in (4.0, 5.0, 7.0)]
    grid += [GlobalAlignConfig(voxel=0.8, fpfh_gain=4.0, use_quatro=True, max_points=UNCAPPED)]
    for cfg in tqdm(grid, desc="kiss configs"):
        key = f"voxel={cfg.voxel} fpfh_gain={cfg.fpfh_gain} quatro={cfg.use_quatro}"
        rows = [run_method("kiss", c, {**tools, "kiss_config": cfg}, verdict=False) for c in cases]
        results["kiss"][key] = summarise({"kiss": rows})["kiss"]
    for voxel in (0.6, 0.8, 1.0):
        feats = Open3dFeatures(voxel=voxel, max_points=UNCAPPED)
        for c in tqdm(cases, desc=f"o3d features voxel {voxel}", leave=False):
            prime_features(c, feats)
        for iterations, confidence in ((10000, 0.99), (100000, 0.999)):
            t = {**tools, "o3d_ransac_features": feats, "ransac_iterations": iterations,
                 "ransac_confidence": confidence}
            rows = [run_method("o3d_ransac", c, t, verdict=False) for c in tqdm(cases, leave=False)]
            results["o3d_ransac"][f"voxel={voxel} iterations={iterations}"] = summarise({"r": rows})["r"]
        t = {**tools, "o3d_fgr_features": feats, "fpfh_kiss_features": feats,
             "fpfh_kiss_config": GlobalAlignConfig(voxel=voxel, max_points=UNCAPPED)}
        for method in ("o3d_fgr", "fpfh_kiss"):
            rows = [run_method(method, c, t, verdict=False) for c in tqdm(cases, leave=False)]
            results[method][f"voxel={voxel}"] = summarise({"r": rows})["r"]
            results[method][f"voxel={voxel}"]["features_ms_p50"] = float(np.median(feats.cpu_seconds) * 1e3)
    picks = {}
    for method, table in results.items():
        best = max(s["start_ok"] for s in table.values())
        near = {k: s for k, s in table.items() if s["start_ok"] >= best - 0.02}
        picks[method] = min(near, key=lambda k: near[k]["align_ms_p50"])
        print(f"\n{method} on {len(cases)} validation pairs (pick: {picks[method]})")
        for k, s in table.items():
            feats_ms = f"  (+ features {s['features_ms_p50']:.1f} ms a cloud)" if "features_ms_p50" in s else ""
            print(f"  {k:40s} start ok {s['start_ok']:.2f}  align ms p50/p90 {s['align_ms_p50']:.1f}/"
                  f"{s['align_ms_p90']:.1f}{feats_ms}")
    results["picks"] = picks
    out.mkdir(parents=True, exist_ok=True)
    (out / "tune.json").write_text(json.dumps(results, indent=2))
    return results


# ---------------------------------------------------------------------------------- figure
def figure(summaries: dict[str, dict[str, dict[str, float]]], path: Path, cpu: str) -> None:
    """Starts within 1.5 m / 10 deg, verdicts right, and right against cost, per set and method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lcpr_core.atomic import save_figure

    sets = [s for s in summaries if not s.endswith("_far")]
    methods = [m for m in METHODS if all(m in summaries[s] for s in sets)]
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    width = 0.8 / len(methods)
    for ax, key, title in ((axes[0], "start_ok", "start within 1.5 m / 10 deg (today, wide: any start)"),
                           (axes[1], "right", "verified right (0.5 m / 3 deg)")):
        for k, m in enumerate(methods):
            ax.bar(np.arange(len(sets)) + k * width, [summaries[s][m][key] for s in sets], width, label=m,
                   color=f"C{k}")
        ax.set_xticks(np.arange(len(sets)) + 0.4 - width / 2, sets)
        ax.set_ylim(0, 1.05)
        ax.set_title(title, fontsize=10)
    axes[0].legend(fontsize=7, ncol=2, loc="lower left")
    for s, marker in zip(sets, "os^v", strict=False):
        for k, m in enumerate(methods):
            axes[2].scatter(max(summaries[s][m]["total_ms_p50"], 1.0), summaries[s][m]["right"], marker=marker,
                            color=f"C{k}", label=s if k == 0 else None)
    axes[2].set_xscale("log")
    axes[2].set_xlabel(f"CPU ms a pair, aligner + verifier, median ({cpu}, 1 core)")
    axes[2].set_ylabel("verified right")
    axes[2].legend(fontsize=8, title="set (colours as left)")
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def pin_one_core() -> None:
    """Run on one core: TBB (KISS-Matcher) and OpenMP (Open3D, small_gicp) then start one thread each."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=None, help="the livox_hku folder (default: ../shared/data/livox_hku)")
    p.add_argument("--kitti", type=Path, default=None, help="the kitti00 folder (default: ../shared/data/kitti00)")
    p.add_argument("--split", choices=("test", "validation", "all"), default="test",
                   help="Livox pairs by query half (validation chose the parameters)")
    p.add_argument("--trials", type=int, default=5, help="turned queries per ordered pair of KITTI scans")
    p.add_argument("--far", type=int, default=100, help="hard far campus pairs (0: none)")
    p.add_argument("--limit", type=int, default=0, help="at most this many pairs per set, evenly spaced (0: all)")
    p.add_argument("--wide", type=int, default=8, help="Scan Context yaws (all registered) of the 'wide' method")
    p.add_argument("--threads", type=int, choices=(0, 1), default=1, help="1: pin to one core; 0: leave as is")
    p.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS),
                   help="which sets to run (a run updates OUT/summary.json, keeping the other sets' results)")
    p.add_argument("--tune", action="store_true", help="sweep the aligners' parameters on validation pairs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("out/global_registration"))
    args = p.parse_args(argv)
    if args.threads == 1:
        pin_one_core()

    from lcpr_common.shared_data import shared_path
    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_core.verification import config as config_module
    from lcpr_core.verification import verifier as verifier_module
    from lcpr_core.verification.global_align import GlobalAlignConfig

    data = args.data or shared_path("data", "livox_hku")
    cpu = cpu_model()
    verifier = GeometricVerifier(VerifierConfig())
    features = {v: Open3dFeatures(voxel=v) for v in set(O3D_VOXEL.values())}
    tools: dict[str, Any] = {
        "verifier": verifier, "kiss_config": GlobalAlignConfig(),
        "wide": GeometricVerifier(VerifierConfig(yaw_hypotheses=args.wide, registrations=args.wide)),
        **{f"{m}_features": features[v] for m, v in O3D_VOXEL.items()},
        "fpfh_kiss_config": GlobalAlignConfig(voxel=O3D_VOXEL["fpfh_kiss"]),
        "ransac_iterations": RANSAC_ITERATIONS, "ransac_confidence": RANSAC_CONFIDENCE}
    print(f"CPU: {cpu}; {'one core, one thread per library' if args.threads else 'threads as the libraries pick'}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.tune:
        cases: list[Case] = []
        for name in ("walk_loop", "campus"):
            found = livox_cases(name, data, "validation", verifier, far=0, seed=args.seed, limit=args.limit or 80)
            cases += next(iter(found.values()))[0]
        tune(cases, tools, args.out)
        return 0

    sets: dict[str, tuple[list[Case], bool]] = {}
    for name in ("walk_loop", "campus"):
        if name in args.sets:
            sets.update(livox_cases(name, data, args.split, verifier, far=args.far, seed=args.seed, limit=args.limit))
    kitti = args.kitti or shared_path("data", "kitti00")
    if "kitti" in args.sets and kitti.is_dir():
        sets["kitti"] = (kitti_cases(kitti, verifier, trials=args.trials, seed=args.seed), True)
    path = args.out / "summary.json"
    kept = json.loads(path.read_text()) if path.exists() else {"meta": {}, "summary": {}}
    summaries: dict[str, dict[str, dict[str, float]]] = kept["summary"]
    sources = [Path(m.__file__).read_bytes() for m in (verifier_module, config_module)]  # type: ignore[arg-type]
    every: dict[str, Any] = {}
    for name, (cases, true) in sets.items():
        rows = evaluate(iter(cases), len(cases), name, tools, METHODS if true else FAR_METHODS)
        summaries[name] = summarise(rows)
        every[name] = rows
        print_table(name, summaries[name], true_pairs=true)
        kept["meta"][name] = {
            "cpu": cpu, "verifier_sha256": hashlib.sha256(b"".join(sources)).hexdigest()[:12],
            "threads": args.threads, "split": args.split, "trials": args.trials, "seed": args.seed,
            "limit": args.limit, "kiss_config": tools["kiss_config"].__dict__, "wide_yaws": args.wide,
            "o3d_voxel": O3D_VOXEL, "ransac": [RANSAC_ITERATIONS, RANSAC_CONFIDENCE],
            "o3d_features_ms_p50": {str(v): float(np.median(f.cpu_seconds) * 1e3)
                                    for v, f in features.items() if f.cpu_seconds}}
    for v, f in features.items():
        if f.cpu_seconds:
            print(f"Open3D FPFH per cloud (voxel {v}): {np.median(f.cpu_seconds) * 1e3:.1f} ms median CPU over "
                  f"{len(f.cpu_seconds)} clouds")
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(kept, indent=2))
    (args.out / f"pairs_{'_'.join(sorted(sets))}.json").write_text(json.dumps(every, default=float))
    figure(summaries, args.out / "global_registration.png", cpu)
    print(f"wrote {path} (sets of earlier runs into {args.out} kept), the pairs and global_registration.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
