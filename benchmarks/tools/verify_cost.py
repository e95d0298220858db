"""Cost of verifying one keyframe's candidates (the issue's "10 candidates <= 150 ms p50, 2 cores").

    python benchmarks/tools/verify_cost.py [--queries 30] [--candidates 10] [--frames 160] [--max-points N]
                                           [--set overlap_points=0 --set bev_points=0 ...]

A synthetic nuScenes-rig drive (city seed 3, 32-beam LiDAR, compact clouds capped at ``--max-points``).
For each revisiting keyframe, the ``--candidates`` earlier keyframes *nearest in position*
(at least 20 keyframes older) are verified: a harder mix than retrieval's top 10, since
near candidates are the ones that reach the fine stage. Per keyframe the time covers
preparing the query cloud and verifying every candidate; the candidates' clouds are
prepared beforehand (the node caches 64 of them), and ``uncached`` adds preparing them too.
``--set NAME=VALUE`` overrides a numeric :class:`~lcpr_core.verification.VerifierConfig` field (to
compare settings back to back). Prints medians and p90 on this CPU, wall time and the CPU time of the
verifying thread (less sensitive to other jobs on a shared machine).
"""
from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--queries", type=int, default=30)
    p.add_argument("--candidates", type=int, default=10)
    p.add_argument("--repeats", type=int, default=3, help="passes over the queries (the first one warms up)")
    p.add_argument("--max-points", type=int, default=None, help="compact cloud cap (default: CloudConfig's)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a numeric VerifierConfig field, e.g. overlap_points=0 (repeatable)")
    args = p.parse_args(argv)

    from dataclasses import replace

    from tqdm import tqdm

    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_offline.verification_pairs import SyntheticLidar, synthetic_pairs

    seq = SyntheticLidar("nuscenes", 3, args.frames)
    true, _ = synthetic_pairs(seq, far_random=1, seed=3)
    overrides: dict[str, Any] = dict(_setting(item) for item in args.set)  # Any: fields of several types
    config = replace(VerifierConfig(), **overrides)
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
    if not cases or args.repeats < 2:
        raise SystemExit(f"--frames {args.frames} gives {len(cases)} revisiting keyframes and --repeats "
                         f"{args.repeats}; accepted: a drive with revisits (the default 160 frames) and >= 2 passes")
    prepared = {i: verifier.prepare(compact[i]) for c in cases for i in c[1]}
    cached, cached_cpu, uncached, accepted = [], [], [], []
    for _ in tqdm(range(args.repeats), desc="passes"):
        for q, candidates in cases:
            tic, cpu = time.perf_counter(), time.thread_time()
            query = verifier.prepare(compact[q])
            verdicts = [verifier.verify_prepared(query, prepared[m]) for m in candidates]
            cached.append(time.perf_counter() - tic)
            cached_cpu.append(time.thread_time() - cpu)
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
    print(f"  verification per keyframe, candidate clouds cached: {ms(cached)} (CPU time {ms(cached_cpu)})")
    print(f"  verification per keyframe, nothing cached:          {ms(uncached)}")
    return 0


def _setting(item: str) -> tuple[str, int | float]:
    """"name=value" -> (name, int or float), or SystemExit naming the item and the accepted form."""
    name, sep, text = item.partition("=")
    try:
        value: int | float = int(text) if text.lstrip("-").isdigit() else float(text)
    except ValueError:
        value = float("nan")
    if not sep or not name or value != value:
        raise SystemExit(f"--set {item!r}; accepted: NAME=NUMBER, NAME a VerifierConfig field")
    return name.strip(), value


if __name__ == "__main__":
    sys.exit(main())
