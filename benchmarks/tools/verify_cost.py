"""Cost of verifying one keyframe's candidates (the issue's "10 candidates <= 150 ms p50, 2 cores").

    python benchmarks/tools/verify_cost.py [--queries 30] [--candidates 10] [--frames 160]

A synthetic nuScenes-rig drive (city seed 3, 32-beam LiDAR, compact clouds capped at ``--max-points``).
For each revisiting keyframe, the ``--candidates`` earlier keyframes *nearest in position*
(at least 20 keyframes older) are verified: a harder mix than retrieval's top 10, since
near candidates are the ones that reach the fine stage. Per keyframe the time covers
preparing the query cloud and verifying every candidate; the candidates' clouds are
prepared beforehand (the node caches 64 of them), and ``uncached`` adds preparing them too.
Prints medians and p90 on this CPU.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--queries", type=int, default=30)
    p.add_argument("--candidates", type=int, default=10)
    p.add_argument("--repeats", type=int, default=3, help="passes over the queries (the first one warms up)")
    p.add_argument("--max-points", type=int, default=None, help="compact cloud cap (default: CloudConfig's)")
    args = p.parse_args(argv)

    from dataclasses import replace

    from tqdm import tqdm

    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_offline.verification_pairs import SyntheticLidar, synthetic_pairs

    seq = SyntheticLidar("nuscenes", 3, args.frames)
    true, _ = synthetic_pairs(seq, far_random=1, seed=3)
    config = VerifierConfig()
    if args.max_points is not None:
        config = replace(config, cloud=replace(config.cloud, max_points=args.max_points))
    verifier = GeometricVerifier(config)
    compact = [verifier.compact(seq.points(i)) for i in tqdm(range(len(seq)), desc="compact clouds")]
    positions = seq.poses[:, :3, 3]
    queries = np.unique(true[:, 0])[: args.queries]
    cases = []
    for q in queries:
        d = np.linalg.norm(positions[: max(q - 20, 0)] - positions[q], axis=1)
        cases.append((int(q), np.argsort(d)[: args.candidates].tolist()))
    prepared = {i: verifier.prepare(compact[i]) for c in cases for i in c[1]}
    cached, uncached, accepted = [], [], []
    for _ in tqdm(range(args.repeats), desc="passes"):
        for q, candidates in cases:
            tic = time.perf_counter()
            query = verifier.prepare(compact[q])
            verdicts = [verifier.verify_prepared(query, prepared[m]) for m in candidates]
            cached.append(time.perf_counter() - tic)
            accepted.append(sum(v.accepted for v in verdicts))
            tic = time.perf_counter()
            query = verifier.prepare(compact[q])
            for m in candidates:
                verifier.verify_prepared(query, verifier.prepare(compact[m]))
            uncached.append(time.perf_counter() - tic)
    skip = len(cases)  # the warm-up pass
    ms = lambda xs: f"p50 {1e3 * np.median(xs[skip:]):.1f} ms, p90 {1e3 * np.percentile(xs[skip:], 90):.1f} ms"  # noqa: E731
    print(f"CPU: {cpu_model()}, verifier threads {verifier.config.num_threads}; {len(cases)} keyframes x "
          f"{args.candidates} candidates (accepted per keyframe: median {np.median(accepted):.0f})")
    print(f"  verification per keyframe, candidate clouds cached: {ms(cached)}")
    print(f"  verification per keyframe, nothing cached:          {ms(uncached)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
