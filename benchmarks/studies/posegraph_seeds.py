"""How much of the drift loops can remove on the demo drive, over drift seeds (true loops, no detector).

    python benchmarks/studies/posegraph_seeds.py [--seeds 6]

The demo drive (seed 7, 200 keyframes) with one loop per revisiting keyframe (its nearest
earlier keyframe within 9 m, >= 30 s older) at the TRUE relative pose and the verifier's
smallest covariance (2 cm, 0.2 deg): the best any loop detector can give this pose graph.
Prints the ATE ratio (optimised / drifted) per drift seed and robust kernel. What is left
after optimisation is drift along stretches driven once, which no loop observes.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from citysim import SynthConfig, SyntheticDrive
from lcpr_core.loop_report import PublishedLoop, pose_graph_proof
from lcpr_core.posegraph import DriftModel, PoseGraphConfig
from lcpr_core.revisits import revisit_pairs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=6)
    args = p.parse_args(argv)
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", frames=200, seed=7, image_size=(64, 32)))
    truth = np.stack([drive.pose(i) for i in range(len(drive))])
    body_T_lidar = np.asarray(drive.rig.lidar.base_T_lidar, np.float64)
    pairs = revisit_pairs(truth[:, :3, 3], np.asarray(drive.keyframes.stamps), radius=9.0, min_time_gap=30.0)
    nearest: dict[int, tuple[int, float]] = {}
    for q, m in pairs.tolist():
        gap = float(np.linalg.norm(truth[q, :3, 3] - truth[m, :3, 3]))
        if q not in nearest or gap < nearest[q][1]:
            nearest[q] = (m, gap)
    world_T_lidar = truth @ body_T_lidar
    cov = np.diag([0.02**2] * 3 + [np.radians(0.2) ** 2] * 3)
    loops = [PublishedLoop(q, m, np.linalg.inv(world_T_lidar[m]) @ world_T_lidar[q], cov)
             for q, (m, _) in nearest.items()]
    print(f"{len(loops)} true loops on {len(truth)} keyframes")
    for robust, k in (("cauchy", 1.0), ("huber", 1.0), ("none", 1.0)):
        ratios = [pose_graph_proof(truth, loops, body_T_lidar=body_T_lidar, drift=DriftModel(seed=s),
                                   config=PoseGraphConfig(robust=robust, robust_param=k)).ratio
                  for s in range(args.seeds)]
        print(f"  {robust:7s} ATE optimised / drifted per drift seed: {np.round(ratios, 2).tolist()} "
              f"(median {np.median(ratios):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
