"""Geometric verification on real Livox Avia keyframes (../shared/data/livox_hku), against the SLAM poses.

    python benchmarks/tools/verify_real.py [--far 3000] [--hard 3] [--out out/verify_real]

Pairs (:mod:`lcpr_offline.verification_pairs`; poses: the folders' optimized_poses.txt, a SLAM system's estimates):
- true revisits: < 3 m apart, > 30 s apart, relative rotation < 30 deg, in ``walk_loop``
  and ``campus``; a pair counts as verified correctly when accepted with its relative
  pose within 0.3 m and 2 deg of the SLAM poses';
- far pairs (> 20 m apart) in ``campus``: a seeded random sample of ``--far`` pairs, and
  the ``--hard`` far keyframes per query whose Scan Context is nearest (what a retrieval
  stage proposes); none may be accepted.

``--split test`` (default) keeps the pairs whose query lies in the second half of each
set (campus: its keyframes; walk_loop: its return, see ``split_at``): the first halves
chose the thresholds and the coarse stage (benchmarks/recipes/verify_tune.py). walk_loop's target
counts all its true pairs, so they are reported as ``walk_loop/true_all`` too.

Pose errors are reported against both pose files: at walk_loop's loop the optimized
poses and the odometry disagree by ~0.27 m (the SLAM system's own loop correction),
and scan-to-scan registration agrees with the odometry to a few cm.

Prints the acceptance rates, pose errors and verification time (median, on this CPU)
and writes every pair's evidence to ``OUT/pairs.npz``. Nothing here chooses a threshold.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.verification import GeometricVerifier
    from lcpr_offline.verification_pairs import PreparedScans
    from msg_tools.convert.scan_folder import ScanFolder

SETS = ("walk_loop", "campus")
POSE_OK_M, POSE_OK_DEG = 0.3, 2.0


def run_pairs(verifier: GeometricVerifier, seq: ScanFolder, pairs: np.ndarray, prepared: PreparedScans, desc: str,
              odom: ScanFolder) -> dict[str, np.ndarray]:
    """Verify every pair; per pair the verdict, its evidence and the pose error against both pose files."""
    from tqdm import tqdm

    from lcpr_offline.verification_pairs import pose_error

    rows: dict[str, list] = {k: [] for k in ("accepted", "reason", "fitness", "rmse", "corr_m", "corr_deg",
                                             "constraint", "err_m", "err_deg", "odom_err_m", "odom_err_deg",
                                             "seconds")}
    for q, m in tqdm(pairs, desc=desc, unit="pair"):
        v = verifier.verify_prepared(prepared[q], prepared[m])
        truth = np.linalg.inv(seq.poses[m]) @ seq.poses[q]
        err_m, err_deg = pose_error(v.match_T_query, truth)
        odom_m, odom_deg = pose_error(v.match_T_query, np.linalg.inv(odom.poses[m]) @ odom.poses[q])
        for key, value in (("accepted", v.accepted), ("reason", v.reason), ("fitness", v.fitness),
                           ("rmse", v.rmse), ("corr_m", v.correction_m), ("corr_deg", v.correction_deg),
                           ("constraint", v.constraint), ("err_m", err_m), ("err_deg", err_deg),
                           ("odom_err_m", odom_m), ("odom_err_deg", odom_deg), ("seconds", v.seconds)):
            rows[key].append(value)
    return {k: np.asarray(v) for k, v in rows.items()}


def summarise(name: str, r: dict[str, np.ndarray], *, true: bool) -> dict[str, float]:
    """Acceptance rates, pose errors and time of one set of pairs, printed and returned."""
    n = len(r["accepted"])
    acc = r["accepted"].astype(bool)
    out: dict[str, float] = {"pairs": n, "accepted": float(acc.mean()) if n else float("nan")}
    if true:
        good = acc & (r["err_m"] <= POSE_OK_M) & (r["err_deg"] <= POSE_OK_DEG)
        out["accepted_with_pose_ok"] = float(good.mean()) if n else float("nan")
        good_odom = acc & (r["odom_err_m"] <= POSE_OK_M) & (r["odom_err_deg"] <= POSE_OK_DEG)
        out["accepted_with_pose_ok_vs_odometry"] = float(good_odom.mean()) if n else float("nan")
        if acc.any():
            out["err_m_median"] = float(np.median(r["err_m"][acc]))
            out["err_deg_median"] = float(np.median(r["err_deg"][acc]))
            out["err_m_p95"] = float(np.percentile(r["err_m"][acc], 95))
            out["err_deg_p95"] = float(np.percentile(r["err_deg"][acc], 95))
            out["odom_err_m_median"] = float(np.median(r["odom_err_m"][acc]))
    out["seconds_median"] = float(np.median(r["seconds"])) if n else float("nan")
    reasons, counts = np.unique(r["reason"], return_counts=True)
    out["reasons"] = {str(k): int(c) for k, c in zip(reasons, counts, strict=True)}  # type: ignore[assignment]
    print(f"  {name:28s} {json.dumps(out)}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=None, help="the livox_hku folder (default: ../shared/data/livox_hku)")
    p.add_argument("--far", type=int, default=3000, help="random far pairs from campus")
    p.add_argument("--hard", type=int, default=3, help="hardest far pairs per campus keyframe (Scan Context)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", choices=("test", "validation", "all"), default="test",
                   help="pairs by query half (validation: the first half, used by benchmarks/recipes/verify_tune.py)")
    p.add_argument("--out", type=Path, default=Path("out/verify_real"))
    args = p.parse_args(argv)
    from lcpr_common.shared_data import shared_path
    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_offline.verification_pairs import PreparedScans, far_pairs, split_at, split_pairs, true_pairs
    from msg_tools.convert.scan_folder import ScanFolder

    data = args.data or shared_path("data", "livox_hku")
    verifier = GeometricVerifier(VerifierConfig())
    print(f"CPU: {platform.processor() or platform.machine()} ({cpu_model()}), verifier threads "
          f"{verifier.config.num_threads}")
    results: dict[str, Any] = {}  # Any: np.savez's keywords also name its own allow_pickle flag
    summary = {}
    for name in SETS:
        seq = ScanFolder(data / name)
        odom = ScanFolder(data / name, poses_file="odom_poses.txt")
        prepared = PreparedScans(verifier, seq)
        sets = {"true": true_pairs(seq)}
        if name == "campus":
            sets["far_random"], sets["far_hard"] = far_pairs(seq, sample=args.far, hard=args.hard, seed=args.seed)
        at = split_at(name, seq)
        sets = {k: split_pairs(v, at, args.split) for k, v in sets.items()}
        if args.split == "test" and name == "walk_loop":  # the target counts all of walk_loop's true pairs
            sets["true_all"] = true_pairs(seq)
        for kind, pairs in sets.items():
            key = f"{name}/{kind}"
            r = run_pairs(verifier, seq, pairs, prepared, key, odom)
            results.update({f"{key}/{k}": v for k, v in r.items()})
            results[f"{key}/pairs"] = pairs
            summary[key] = summarise(key, r, true=kind.startswith("true"))
    args.out.mkdir(parents=True, exist_ok=True)
    np.savez(args.out / "pairs.npz", **results)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
