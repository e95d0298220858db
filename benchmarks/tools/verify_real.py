"""Geometric verification on real Livox Avia keyframes (../shared/data/livox_hku), against the SLAM poses.

    python benchmarks/tools/verify_real.py [--far 3000] [--hard 3] [--submap off|on|auto] [--out out/verify_real]
                                           [--save VERDICTS.json] [--compare VERDICTS.json]

Pairs (:mod:`lcpr_offline.verification_pairs`; poses: the folders' optimized_poses.txt, a SLAM system's estimates):
- true revisits: < 3 m apart, > 30 s apart, relative rotation < 30 deg, in ``walk_loop``
  and ``campus``; a pair counts as verified correctly when accepted with its relative
  pose within 0.5 m and 3 deg of the SLAM poses';
- far pairs (> 20 m apart) in ``campus``: a seeded random sample of ``--far`` pairs, and
  the ``--hard`` far keyframes per query whose Scan Context is nearest (what a retrieval
  stage proposes); none may be accepted.
- middle pairs (5-20 m apart, > 30 s apart) in both sets, a seeded sample of ``--mid``: the
  sensor may see the same walls from there, so accepting one is no error, but its relative
  pose must then be right (``accepted_with_wrong_pose``: off by more than 0.5 m / 3 deg).

``--split test`` (default) keeps the pairs whose query lies in the second half of each
set (campus: its keyframes; walk_loop: its return, see ``split_at``): the first halves
chose the thresholds and the coarse stage (benchmarks/recipes/verify_tune.py). walk_loop's target
counts all its true pairs, so they are reported as ``walk_loop/true_all`` too.

``--submap on|auto`` verifies each pair with local submaps (:mod:`lcpr_core.verification.submap`), built by
``build_submap`` exactly as the detector builds them: the query's previous keyframes, the match's neighbours on
both sides (never reaching the query's own keyframes), stitched by ``odom_poses.txt`` (the odometry a node
receives), ``--travel-m`` / ``--max-keyframes`` / ``--max-points`` as ``SubmapConfig``'s fields. Every scan of
a folder is a keyframe (about 0.2 m apart). The default, ``off``, verifies single keyframes.

Pose errors are reported against both pose files: at walk_loop's loop the optimized
poses and the odometry disagree by ~0.27 m (the SLAM system's own loop correction),
and scan-to-scan registration agrees with the odometry to a few cm.

Prints the acceptance rates, pose errors and verification time (median, on this CPU)
and writes every pair's evidence to ``OUT/pairs.npz``. Nothing here chooses a threshold.

``--save FILE`` writes every pair's verdict (decision, reason, fitness, pose; named ``set/kind/query-match``);
``--compare FILE`` checks this run's against such a file (e.g. before and after a change to the verifier),
prints what differs and exits with status 1 when a decision or a reason differs or a pose moved more than
1 mm / 0.01 deg (:mod:`lcpr_offline.verdicts`).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.verification import GeometricVerifier, PreparedCloud, SubmapConfig
    from lcpr_offline.verdicts import Record
    from lcpr_offline.verification_pairs import PreparedScans
    from msg_tools.convert.scan_folder import ScanFolder

SETS = ("walk_loop", "campus")
POSE_OK_M, POSE_OK_DEG = 0.5, 3.0
MID_M = (5.0, 20.0)  # m: the middle pairs' distance range


def mid_pairs(seq: ScanFolder, *, sample: int, seed: int) -> np.ndarray:
    """A seeded sample of (query, match) pairs MID_M apart and more than 30 s apart in time (query the later)."""
    from lcpr_offline.verification_pairs import TRUE_GAP_S

    P = seq.poses[:, :3, 3]
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    late = seq.stamps[:, None] - seq.stamps[None] > TRUE_GAP_S
    q, m = np.nonzero((d > MID_M[0]) & (d <= MID_M[1]) & late)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(q), size=min(sample, len(q)), replace=False)
    return np.stack([q[pick], m[pick]], axis=1).reshape(-1, 2)


class PairClouds:
    """The prepared clouds a pair is verified with: each scan's own (PreparedScans), or submaps built from the
    scans' compact clouds and the odometry by ``build_submap``, as ``LoopDetector`` builds them; each made once."""

    def __init__(self, verifier: GeometricVerifier, prepared: PreparedScans, odom: ScanFolder,
                 submap: SubmapConfig) -> None:
        self.verifier, self.prepared, self.odom, self.config = verifier, prepared, odom, submap
        self._compact: dict[int, np.ndarray] = {}
        self._cache: dict[tuple[int, tuple[int, ...]], PreparedCloud] = {}
        self.build_seconds: list[float] = []  # stitching and preparing each submap made
        self.sizes: list[int] = []  # keyframes in each submap made

    def compact(self, i: int) -> np.ndarray:
        if i not in self._compact:
            self._compact[i] = self.verifier.compact(self.odom.points(i))
        return self._compact[i]

    def pair(self, q: int, m: int) -> tuple[PreparedCloud, PreparedCloud]:
        if self.config.mode == "off":
            return self.prepared[q], self.prepared[m]
        query = self._submap(q, end=q + 1, before_only=True)
        first = query[0][1][0]  # the query's own keyframes start here
        if m >= first:  # the match is one of them: scan against scan, as the detector does
            return self.prepared[q], self.prepared[m]
        return query[1], self._submap(m, end=first, before_only=False)[1]

    def _submap(self, centre: int, *, end: int, before_only: bool
                ) -> tuple[tuple[int, tuple[int, ...]], PreparedCloud]:
        import time

        from lcpr_core.verification import build_submap

        tic = time.perf_counter()
        sub = build_submap(centre, world_T_base=self.odom.poses[:end], stamps=self.odom.stamps[:end],
                           cloud=self.compact, config=self.config, before_only=before_only)
        assert sub is not None  # every scan has a cloud
        key = (centre, sub.rows)
        if key not in self._cache:
            self._cache[key] = self.verifier.prepare(sub.xyz)
            self.build_seconds.append(time.perf_counter() - tic)
            self.sizes.append(len(sub.rows))
        return key, self._cache[key]


def run_pairs(verifier: GeometricVerifier, seq: ScanFolder, pairs: np.ndarray, clouds: PairClouds, desc: str,
              odom: ScanFolder, *, verdicts: dict[str, Record] | None = None) -> dict[str, np.ndarray]:
    """Verify every pair; per pair the verdict, its evidence and the pose error against both pose files.
    ``verdicts``: also keep each pair's verdict record there, named ``desc/query-match``."""
    from tqdm import tqdm

    from lcpr_offline.verdicts import record
    from lcpr_offline.verification_pairs import pose_error

    rows: dict[str, list] = {k: [] for k in ("accepted", "reason", "fitness", "rmse", "corr_m", "corr_deg",
                                             "constraint", "err_m", "err_deg", "odom_err_m", "odom_err_deg",
                                             "seconds")}
    for q, m in tqdm(pairs, desc=desc, unit="pair"):
        v = verifier.verify_prepared(*clouds.pair(int(q), int(m)))
        if verdicts is not None:
            verdicts[f"{desc}/{q}-{m}"] = record(v)
        truth = np.linalg.inv(seq.poses[m]) @ seq.poses[q]
        err_m, err_deg = pose_error(v.match_T_query, truth)
        odom_m, odom_deg = pose_error(v.match_T_query, np.linalg.inv(odom.poses[m]) @ odom.poses[q])
        for key, value in (("accepted", v.accepted), ("reason", v.reason), ("fitness", v.fitness),
                           ("rmse", v.rmse), ("corr_m", v.correction_m), ("corr_deg", v.correction_deg),
                           ("constraint", v.constraint), ("err_m", err_m), ("err_deg", err_deg),
                           ("odom_err_m", odom_m), ("odom_err_deg", odom_deg), ("seconds", v.seconds)):
            rows[key].append(value)
    return {k: np.asarray(v) for k, v in rows.items()}


def summarise(name: str, r: dict[str, np.ndarray], *, true: bool, posed: bool = False) -> dict[str, float]:
    """Acceptance rates, pose errors and time of one set of pairs, printed and returned. ``posed``: the pairs
    may be accepted but only with the right pose (the middle pairs)."""
    n = len(r["accepted"])
    acc = r["accepted"].astype(bool)
    out: dict[str, float] = {"pairs": n, "accepted": float(acc.mean()) if n else float("nan")}
    if posed:
        wrong = acc & ((r["err_m"] > POSE_OK_M) | (r["err_deg"] > POSE_OK_DEG))
        out["accepted_with_wrong_pose"] = int(wrong.sum())
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


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=None, help="the livox_hku folder (default: ../shared/data/livox_hku)")
    p.add_argument("--far", type=int, default=3000, help="random far pairs from campus")
    p.add_argument("--hard", type=int, default=3, help="hardest far pairs per campus keyframe (Scan Context)")
    p.add_argument("--mid", type=int, default=1000,
                   help="pairs 5-20 m apart per set (accepted only with the right pose)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", choices=("test", "validation", "all"), default="test",
                   help="pairs by query half (validation: the first half, used by benchmarks/recipes/verify_tune.py)")
    p.add_argument("--submap", choices=("off", "on", "auto"), default="off",
                   help="verify with local submaps (lcpr_core.verification.submap) stitched by odom_poses.txt")
    p.add_argument("--travel-m", type=float, default=None, help="SubmapConfig.travel_m (default: its default)")
    p.add_argument("--max-keyframes", type=int, default=None, help="SubmapConfig.max_keyframes")
    p.add_argument("--max-points", type=int, default=None, help="SubmapConfig.max_points")
    p.add_argument("--only", choices=SETS, default=None, help="one set only (tuning runs)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a numeric VerifierConfig field, e.g. fine_points=2048 (repeatable)")
    p.add_argument("--out", type=Path, default=Path("out/verify_real"))
    p.add_argument("--save", type=Path, default=None, help="write every pair's verdict to this JSON file")
    p.add_argument("--compare", type=Path, default=None, help="compare the verdicts with a --save file")
    args = p.parse_args(argv)
    if args.compare is not None and not args.compare.is_file():
        raise SystemExit(f"--compare {args.compare}: no such file; accepted: a file written by --save")
    from lcpr_common.shared_data import shared_path
    from lcpr_core.errors import VerificationError
    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier, SubmapConfig, VerifierConfig
    from lcpr_core.verification.config import with_settings
    from lcpr_offline import verdicts as verdict_file
    from lcpr_offline.verification_pairs import PreparedScans, far_pairs, split_at, split_pairs, true_pairs
    from msg_tools.convert.scan_folder import ScanFolder

    data = args.data or shared_path("data", "livox_hku")
    try:
        verifier = GeometricVerifier(with_settings(VerifierConfig(), args.set))
    except VerificationError as err:
        raise SystemExit(f"--set: {err}") from err
    options = {"travel_m": args.travel_m, "max_keyframes": args.max_keyframes, "max_points": args.max_points}
    submap = SubmapConfig(mode=args.submap, **{k: v for k, v in options.items() if v is not None})
    print(f"CPU: {platform.processor() or platform.machine()} ({cpu_model()}), verifier threads "
          f"{verifier.config.num_threads}; {submap}; settings {args.set or 'the defaults'}")
    results: dict[str, Any] = {}  # Any: np.savez's keywords also name its own allow_pickle flag
    summary = {}
    records: dict[str, verdict_file.Record] = {}  # the verdicts by pair name
    for name in (args.only,) if args.only else SETS:
        seq = ScanFolder(data / name)
        odom = ScanFolder(data / name, poses_file="odom_poses.txt")
        clouds = PairClouds(verifier, PreparedScans(verifier, seq), odom, submap)
        sets = {"true": true_pairs(seq)}
        if name == "campus":
            sets["far_random"], sets["far_hard"] = far_pairs(seq, sample=args.far, hard=args.hard, seed=args.seed)
        if args.mid:
            sets["mid"] = mid_pairs(seq, sample=args.mid, seed=args.seed)
        at = split_at(name, seq)
        sets = {k: split_pairs(v, at, args.split) for k, v in sets.items()}
        if args.split == "test" and name == "walk_loop":  # the target counts all of walk_loop's true pairs
            sets["true_all"] = true_pairs(seq)
        for kind, pairs in sets.items():
            key = f"{name}/{kind}"
            r = run_pairs(verifier, seq, pairs, clouds, key, odom, verdicts=records)
            results.update({f"{key}/{k}": v for k, v in r.items()})
            results[f"{key}/pairs"] = pairs
            summary[key] = summarise(key, r, true=kind.startswith("true"), posed=kind == "mid")
        if clouds.sizes:
            summary[f"{name}/submaps"] = built = {
                "made": len(clouds.sizes), "keyframes_median": float(np.median(clouds.sizes)),
                "build_and_prepare_seconds_median": float(np.median(clouds.build_seconds))}
            print(f"  {name + '/submaps':28s} {json.dumps(built)}")
    args.out.mkdir(parents=True, exist_ok=True)
    np.savez(args.out / "pairs.npz", **results)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    return verdict_file.keep(records, save_to=args.save, compare_with=args.compare,
                             same_run="run with the same --split/--far/--hard/--mid/--seed/--only")


if __name__ == "__main__":
    sys.exit(main())
