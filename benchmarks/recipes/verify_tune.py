"""Choose the verifier's acceptance thresholds on validation data only, and print them.

    python benchmarks/recipes/verify_tune.py [--frames 160] [--out out/verify_tune]

Validation data (never reported as held out):
- a synthetic nuScenes-rig drive of city seed 3 and a KITTI-rig drive of city seed 4
  (the demo uses seed 7, the README's evaluation seeds 7 and 11): true pairs are
  keyframes <= 9 m apart and >= 30 s apart, false pairs > 20 m apart (the Scan Context
  nearest, i.e. the look-alikes, plus a random sample);
- the first halves of ``livox_hku/campus`` (pairs whose query keyframe is in the first
  half of its keyframes) and of ``livox_hku/walk_loop``'s true pairs (queries in the first
  half of its return); ``benchmarks/tools/verify_real.py --split test`` reports the rest.

Every pair is registered with acceptance switched off; the script then picks the
(``min_constraint``, ``min_fitness``) pair that accepts the most validation true pairs
while at most 0.1 % of the validation false pairs pass, then the largest ``early_reject``
that turns away at most 2 % of the true pairs those thresholds accept, and prints what that leaves:
the defaults of :class:`lcpr_core.verification.VerifierConfig`.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lcpr_common.shared_data import shared_path
from lcpr_core.posegraph import relative_pose_error
from lcpr_core.timing import cpu_model
from lcpr_core.verification import GeometricVerifier, VerifierConfig
from lcpr_offline.verification_pairs import (
    PreparedScans,
    Scans,
    SyntheticLidar,
    far_pairs,
    split_at,
    split_pairs,
    synthetic_pairs,
    true_pairs,
)
from msg_tools.convert.scan_folder import ScanFolder

OPEN: dict[str, Any] = dict(min_fitness=0.0, min_constraint=0.0, early_reject=0.0)  # chosen here; the other rules stay
FALSE_RATE = 0.001


def evidence(verifier: GeometricVerifier, seq: Scans, pairs: np.ndarray, desc: str) -> dict[str, np.ndarray]:
    """Per pair, registered with acceptance switched off: what each threshold reads, and the pose error."""
    prepared = PreparedScans(verifier, seq)
    rows = []
    for q, m in tqdm(pairs, desc=desc, unit="pair"):
        v = verifier.verify_prepared(prepared[q], prepared[m])
        err_m, err_deg = relative_pose_error(v.match_T_query, np.linalg.inv(seq.poses[m]) @ seq.poses[q])
        rows.append((v.fitness, v.constraint, v.rmse, v.correction_m, v.correction_deg, err_m, err_deg,
                     v.reason != "accepted", v.coarse_fitness))
    arr = np.array(rows, np.float64).reshape(-1, 9)
    # "blocked": refused by a rule not tuned here (too few points, residual, correction bound)
    return dict(zip(("fitness", "constraint", "rmse", "corr_m", "corr_deg", "err_m", "err_deg", "blocked",
                     "coarse_fitness"), arr.T, strict=True))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=shared_path("data", "livox_hku"))
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--far", type=int, default=1500)
    p.add_argument("--out", type=Path, default=Path("out/verify_tune"))
    args = p.parse_args(argv)
    base = VerifierConfig()
    verifier = GeometricVerifier(dataclasses.replace(base, **OPEN))
    print(f"CPU: {cpu_model()}")
    true_sets, false_sets = {}, {}
    for rig, seed in (("nuscenes", 3), ("kitti", 4)):
        seq = SyntheticLidar(rig, seed, args.frames)
        t, f = synthetic_pairs(seq, far_random=args.far // 2, seed=seed)
        true_sets[f"synthetic {rig} seed {seed}"] = evidence(verifier, seq, t, f"{rig} true")
        false_sets[f"synthetic {rig} seed {seed}"] = evidence(verifier, seq, f, f"{rig} far")
    campus = ScanFolder(args.data / "campus")
    at = split_at("campus", campus)
    t = split_pairs(true_pairs(campus), at, "validation")
    rand, hard = far_pairs(campus, sample=args.far, hard=3, seed=0, before=at)
    f = np.concatenate([rand, hard])
    true_sets["campus validation half"] = evidence(verifier, campus, t, "campus true")
    false_sets["campus validation half"] = evidence(verifier, campus, f, "campus far")
    walk = ScanFolder(args.data / "walk_loop")
    t = split_pairs(true_pairs(walk), split_at("walk_loop", walk), "validation")
    true_sets["walk_loop validation half"] = evidence(verifier, walk, t, "walk_loop true")

    keys = ("fitness", "constraint", "blocked", "coarse_fitness")
    allf = {k: np.concatenate([s[k] for s in false_sets.values()]) for k in keys}
    allt = {k: np.concatenate([s[k] for s in true_sets.values()]) for k in keys}
    chosen = choose(allf, allt)
    chosen["early_reject"] = choose_early_reject(allt, chosen)
    print(f"\nchosen on validation (<= {FALSE_RATE:.1%} of {len(allf['fitness'])} false pairs accepted): "
          f"min_fitness={chosen['min_fitness']:.3f} min_constraint={chosen['min_constraint']:.2f} "
          f"early_reject={chosen['early_reject']:.1f}")
    report: dict[str, Any] = {"chosen": chosen, "sets": {}}
    for name, s in {**{f"true: {k}": v for k, v in true_sets.items()},
                    **{f"false: {k}": v for k, v in false_sets.items()}}.items():
        ok = _passes(s, chosen)
        line = {"pairs": len(ok), "accepted": float(ok.mean()) if len(ok) else None,
                "fitness_p50": float(np.median(s["fitness"])) if len(ok) else None}
        if name.startswith("true") and ok.any():
            line["err_m_p50"] = float(np.median(s["err_m"][ok]))
            line["err_deg_p50"] = float(np.median(s["err_deg"][ok]))
        report["sets"][name] = line
        print(f"  {name:40s} {json.dumps(line)}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "chosen.json").write_text(json.dumps(report, indent=2))
    evidence_arrays: dict[str, Any] = {  # Any: np.savez's keywords also name its own allow_pickle flag
        f"{kind}/{name}/{k}": v for kind, sets in (("true", true_sets), ("false", false_sets))
        for name, s in sets.items() for k, v in s.items()}
    np.savez(args.out / "evidence.npz", **evidence_arrays)
    return 0


def choose(false: dict[str, np.ndarray], true: dict[str, np.ndarray]) -> dict[str, float]:
    """The (min_constraint, min_fitness) pair that accepts most validation true pairs while at most
    FALSE_RATE of the validation false pairs pass (grids: constraint 0..0.1 by 0.01, fitness by 0.005);
    of pairs that accept as many, the largest min_constraint (degenerate geometry is what it guards against)."""
    best: tuple[float, float, float] | None = None
    for min_constraint in np.round(np.arange(0.0, 0.101, 0.01), 3):
        for fitness in np.arange(0.0, 1.0, 0.005):
            t = {"min_fitness": round(float(fitness), 3), "min_constraint": float(min_constraint)}
            if _passes(false, t).mean() <= FALSE_RATE:
                recall = float(_passes(true, t).mean())
                if best is None or recall >= best[0] - 1e-9:  # a tie goes to the stricter min_constraint
                    best = (recall, t["min_fitness"], t["min_constraint"])
                break
    assert best is not None
    return {"min_fitness": best[1], "min_constraint": best[2]}


def choose_early_reject(true: dict[str, np.ndarray], t: dict[str, float]) -> float:
    """The largest early_reject (0.9, 0.8, ... 0.1) that turns away at most 2 % of the validation true pairs the
    thresholds accept: a speed knob (wrong candidates skip the fine registration; on the synthetic city, 0.6
    instead of 0.4 takes 10 uncached candidates from ~260 to ~200 ms) that costs little recall."""
    accepted = _passes(true, t)
    for early in np.round(np.arange(0.9, 0.05, -0.1), 1):
        if (accepted & (true["coarse_fitness"] < early * t["min_fitness"])).sum() <= 0.02 * accepted.sum():
            return float(early)
    return 0.0


def _passes(s: dict[str, np.ndarray], t: dict[str, float]) -> np.ndarray:
    return (s["blocked"] == 0) & (s["fitness"] >= t["min_fitness"]) & (s["constraint"] >= t["min_constraint"])


if __name__ == "__main__":
    sys.exit(main())
