"""How much of a pair lies in the other scan's free space: true pairs against wrong poses, per data set.

    python benchmarks/studies/verify_free_space.py [--cities 3 9 7] [--frames 200] [--out out/verify_free_space]

For each pair, :meth:`GeometricVerifier.contradiction` at a pose: the larger share of either cloud's points that
lie where the other sensor's beams passed through (:mod:`lcpr_core.verification.free_space`).

- Cities (nuScenes rig, 32-beam LiDAR, exact poses): verify_cost.py's construction (the 10 earlier keyframes nearest
  in position of each revisiting keyframe), verified with the free-space and ambiguity tests off so that the wrong
  poses they exist for are accepted; each accepted pair at its registered pose, counted wrong when more than
  0.5 m / 3 deg off the truth. Seed 3 is the validation city, 7 and 9 are held out.
- KITTI-00: the 12 ordered pairs of the four raw HDL-64 scans (0.7-12 m apart) at their known pose.
- Livox Avia (``livox_hku``): up to 120 true revisits per set (< 3 m, > 30 s, < 30 deg) at the SLAM poses,
  single keyframes, split into validation (the first halves, as for every verifier threshold) and test.

Prints, per set, the contradiction of the true pairs (median, p99, max) and of the wrong poses (min, median), and
how many of each ``verify.max_contradiction`` refuses; writes ``OUT/rows.json`` and ``OUT/free_space.png``. The
validation sets (city seed 3, KITTI, the Livox first halves) chose the threshold: between their true pairs' largest
value and their wrong poses' smallest (docs/verification.md, Free space); the held-out sets only report.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

POSE_OK_M, POSE_OK_DEG = 0.5, 3.0
LIVOX_PAIRS = 120  # true pairs per Livox set at most (evenly spaced)


def city_rows(seed: int, frames: int) -> list[dict[str, Any]]:
    """The accepted nearest-candidate pairs of a synthetic city, free-space and ambiguity tests off."""
    from tqdm import tqdm

    from lcpr_core.geometry import invert
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_offline.verification_pairs import PreparedScans, SyntheticLidar, pose_error, synthetic_pairs

    seq = SyntheticLidar("nuscenes", seed, frames)
    true, _ = synthetic_pairs(seq, far_random=1, seed=seed)
    verifier = GeometricVerifier(replace(VerifierConfig(), max_contradiction=1.0, ambiguity_constraint=0.0))
    clouds = PreparedScans(verifier, seq)
    positions = seq.poses[:, :3, 3]
    rows = []
    for q in tqdm(np.unique(true[:, 0]), desc=f"city seed {seed}", unit="query"):
        d = np.linalg.norm(positions[: max(q - 20, 0)] - positions[q], axis=1)
        for m in np.argsort(d)[:10]:
            v = verifier.verify_prepared(clouds[int(q)], clouds[int(m)])
            if not v.accepted:
                continue
            err_m, err_deg = pose_error(v.match_T_query, invert(seq.poses[m]) @ seq.poses[q])
            rows.append({"set": f"city seed {seed}", "query": int(q), "match": int(m), "apart_m": float(d[m]),
                         "wrong": bool(err_m > POSE_OK_M or err_deg > POSE_OK_DEG), "fitness": v.fitness,
                         "contradiction": verifier.contradiction(clouds[int(q)], clouds[int(m)], v.match_T_query)})
    return rows


def kitti_rows() -> list[dict[str, Any]]:
    """The raw KITTI-00 scan pairs at their known pose."""
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_offline.kitti_scans import FRAMES, kitti_folder, load_scan, reference_poses

    verifier = GeometricVerifier(VerifierConfig())
    root = kitti_folder()
    clouds = {f: verifier.prepare(verifier.compact(load_scan(root, f)[:, :3])) for f in FRAMES}
    return [{"set": "KITTI-00", "query": q, "match": m, "apart_m": float(np.linalg.norm(T[:3, 3])), "wrong": False,
             "contradiction": verifier.contradiction(clouds[q], clouds[m], T)}
            for (q, m), T in sorted(reference_poses(folder=root).items())]


def livox_rows(name: str) -> list[dict[str, Any]]:
    """True revisits of a Livox set at the SLAM poses, single keyframes, labelled by split."""
    from lcpr_common.shared_data import shared_path
    from lcpr_core.geometry import invert
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_offline.verification_pairs import PreparedScans, split_at, true_pairs
    from msg_tools.convert.scan_folder import ScanFolder

    seq = ScanFolder(shared_path("data", "livox_hku", name))
    verifier = GeometricVerifier(VerifierConfig())
    clouds = PreparedScans(verifier, seq)
    pairs, at = true_pairs(seq), split_at(name, seq)
    rows = []
    for q, m in pairs[:: max(1, -(-len(pairs) // LIVOX_PAIRS))]:
        T = invert(seq.poses[m]) @ seq.poses[q]
        rows.append({"set": f"{name} {'validation' if q < at else 'test'}", "query": int(q), "match": int(m),
                     "apart_m": float(np.linalg.norm(T[:3, 3])), "wrong": False,
                     "contradiction": verifier.contradiction(clouds[int(q)], clouds[int(m)], T)})
    return rows


def summary(rows: list[dict[str, Any]], threshold: float) -> list[str]:
    lines = [f"{'set':24s} {'true':>5s} {'median':>7s} {'p99':>6s} {'max':>6s} {'refused':>7s} | "
             f"{'wrong':>5s} {'min':>6s} {'median':>7s} {'refused':>7s}"]
    for name in dict.fromkeys(r["set"] for r in rows):
        t = np.array([r["contradiction"] for r in rows if r["set"] == name and not r["wrong"]])
        w = np.array([r["contradiction"] for r in rows if r["set"] == name and r["wrong"]])
        line = (f"{name:24s} {len(t):5d} {np.median(t):7.3f} {np.percentile(t, 99):6.3f} {t.max():6.3f} "
                f"{int((t > threshold).sum()):7d} | ") if len(t) else f"{name:24s} {0:5d} {'':30s} | "
        line += (f"{len(w):5d} {w.min():6.3f} {np.median(w):7.3f} {int((w > threshold).sum()):7d}" if len(w)
                 else f"{0:5d}")
        lines.append(line)
    return lines


def plot(rows: list[dict[str, Any]], threshold: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["set"] for r in rows))
    fig, ax = plt.subplots(figsize=(9, 0.5 * len(names) + 1.6))
    rng = np.random.default_rng(0)
    labelled: set[str] = set()
    for i, name in enumerate(names):
        for wrong, colour, label in ((False, "tab:blue", "true pair"), (True, "tab:red", "wrong pose")):
            x = np.array([r["contradiction"] for r in rows if r["set"] == name and r["wrong"] == wrong])
            if len(x):
                ax.scatter(np.maximum(x, 1e-4), i + rng.uniform(-0.2, 0.2, len(x)), s=9, c=colour, alpha=0.6,
                           label=None if label in labelled else label)
                labelled.add(label)
    ax.axvline(threshold, color="k", ls="--", lw=1, label=f"verify.max_contradiction {threshold}")
    ax.set_xscale("log")
    ax.set_yticks(range(len(names)), names)
    ax.invert_yaxis()
    ax.set_xlabel("contradiction: the larger share of either cloud's points in the other's free space (0 at 1e-4)")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("Free space: true pairs against wrong poses")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cities", type=int, nargs="*", default=[3, 9, 7], help="city seeds (3 validation; 7, 9 held out)")
    p.add_argument("--frames", type=int, default=200, help="keyframes of each city drive")
    p.add_argument("--no-real", action="store_true", help="skip KITTI and the Livox sets")
    p.add_argument("--out", type=Path, default=Path("out/verify_free_space"))
    args = p.parse_args(argv)

    from lcpr_core.atomic import write_atomic
    from lcpr_core.verification import VerifierConfig

    threshold = VerifierConfig().max_contradiction
    rows: list[dict[str, Any]] = []
    for seed in args.cities:
        rows += city_rows(seed, args.frames)
    if not args.no_real:
        rows += kitti_rows()
        for name in ("walk_loop", "campus"):
            rows += livox_rows(name)
    print("\n".join(summary(rows, threshold)))
    args.out.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out / "rows.json", lambda path: path.write_text(json.dumps(rows, indent=1) + "\n"))
    plot(rows, threshold, args.out / "free_space.png")
    print(f"written: {args.out / 'rows.json'}, {args.out / 'free_space.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
