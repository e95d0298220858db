"""What the verifier accepts just beyond the demo's 9 m radius, and whether those poses are right.

    python benchmarks/studies/verify_near_misses.py [--seed 7] [--frames 200]

Every pair of the demo drive's keyframes that is >= 30 s apart and 9-25 m apart (the
demo scores a loop between them as wrong) is verified on its LiDAR clouds; the script
prints how many are accepted and, for those, the distance and the relative-pose error
against the ground truth.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
from tqdm import tqdm

from lcpr_core.posegraph import relative_pose_error
from lcpr_core.verification import GeometricVerifier
from lcpr_offline.verification_pairs import PreparedScans, SyntheticLidar


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--frames", type=int, default=200)
    args = p.parse_args(argv)
    seq = SyntheticLidar("nuscenes", args.seed, args.frames)
    positions = seq.poses[:, :3, 3]
    dist = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    gap = seq.stamps[:, None] - seq.stamps[None]
    queries, matches = np.nonzero((gap >= 30.0) & (dist > 9.0) & (dist <= 25.0))
    verifier = GeometricVerifier()
    prepared = PreparedScans(verifier, seq)
    accepted = []
    for q, m in tqdm(list(zip(queries.tolist(), matches.tolist(), strict=True)), desc="pairs 9-25 m", unit="pair"):
        v = verifier.verify_prepared(prepared[q], prepared[m])
        if v.accepted:
            err = relative_pose_error(v.match_T_query, np.linalg.inv(seq.poses[m]) @ seq.poses[q])
            accepted.append((dist[q, m], *err))
    print(f"{len(accepted)} of {len(queries)} pairs 9-25 m apart accepted")
    if accepted:
        a = np.array(accepted)
        print(f"  distance {a[:, 0].min():.1f}-{a[:, 0].max():.1f} m; pose error max {a[:, 1].max():.3f} m / "
              f"{a[:, 2].max():.2f} deg, median {np.median(a[:, 1]):.3f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
